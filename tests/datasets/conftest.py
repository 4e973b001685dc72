"""Fixtures of the download tests: the local HTTP server and a tiny rendered TUM sequence."""

from __future__ import annotations

from pathlib import Path

import pytest
from dl_server import Server
from synth import make_tum_dir


@pytest.fixture
def server():
    s = Server()
    yield s
    s.close()


@pytest.fixture(scope="module")
def tum_src(tmp_path_factory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("src"), scene="room", n=6, width=64, height=48)

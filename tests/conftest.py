"""Shared fixtures: real-data location, tolerances, seeded RNG."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# pytest-xdist's workers (`make test` runs two) inherit COLUMNS=80 and LINES=24 from it, not from a terminal: the CLI's
# console would take them as the user's width and wrap its tables at 80 columns, where a captured one-process run sees
# a pipe (cli/common.PIPED_WIDTH). Dropped before any test imports the CLI, so both see a pipe.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("COLUMNS", "LINES"):
        os.environ.pop(_name, None)

# Tolerances in one place (STYLE §4): dtype -> (rtol, atol).
TOL = {np.float32: (1e-4, 1e-5), np.float64: (1e-7, 1e-9)}

_DEFAULT_SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_data_root() -> Path | None:
    """``$MSLAM_SHARED_DATA`` or ``../shared/data`` beside the repository, if present."""
    root = Path(os.environ.get("MSLAM_SHARED_DATA", _DEFAULT_SHARED))
    return root if root.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder with the real sequences (tum_fr1_xyz, icl_lr_kt2, ...); skips when absent."""
    root = shared_data_root()
    if root is None:
        pytest.skip("real sequences not found (set MSLAM_SHARED_DATA or provide ../shared/data)")
    return root


@pytest.fixture
def one_torch_thread():
    """CPU is shared: one torch thread avoids OpenMP oversubscription stalls (restored after)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def assert_close(actual, expected, dtype=np.float64) -> None:
    """``np.testing.assert_allclose`` with the table's tolerance for ``dtype``."""
    rtol, atol = TOL[dtype]
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=atol)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> tuple[Path, Path]:
    """``(tmp, seq)``: a 12-frame synthetic room in TUM layout and random Monodepth2 weights under
    ``tmp / "weights"`` (the size of ``configs/smoke.yaml``'s network), for end-to-end runs."""
    import torch
    from synth import make_tum_dir

    from mutualslam_cli.adapt.depthnet import DepthNet
    from mutualslam_cli.adapt.weights import save_monodepth2

    tmp = tmp_path_factory.mktemp("run")
    torch.manual_seed(0)
    save_monodepth2(DepthNet(), tmp / "weights", 64, 96)
    return tmp, make_tum_dir(tmp, scene="room", n=12, width=128, height=96)

"""Every ``>>>`` example in the package runs and shows what it says (the docstrings' examples are tests too).

The modules holding an example are found by their text, so a new example is run without being listed here; each
is imported and run with :mod:`doctest` (numpy's and torch's reprs as they print; ``ELLIPSIS`` and
``NORMALIZE_WHITESPACE`` on).
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "mutualslam_cli"


def _modules_with_examples() -> list[str]:
    out = []
    for path in sorted(ROOT.rglob("*.py")):
        if path.name != "__main__.py" and ">>> " in path.read_text(encoding="utf-8"):
            parts = ("mutualslam_cli",) + path.relative_to(ROOT).with_suffix("").parts
            out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


def test_the_package_has_examples():
    assert len(_modules_with_examples()) >= 5


@pytest.mark.parametrize("name", _modules_with_examples())
def test_examples_run(name: str):
    module = importlib.import_module(name)
    res = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, report=True)
    assert res.attempted > 0, f"{name}: no example found by doctest"
    assert res.failed == 0, f"{name}: {res.failed} of {res.attempted} examples failed (the report above)"

"""The exception hierarchy: all classes in errors.py; user errors are MslamError, bugs are not."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from mutualslam_cli import errors
from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample
from mutualslam_cli.types import check_shape

PACKAGE_ROOT = Path(errors.__file__).resolve().parent


def _exception_names() -> set[str]:
    """Built-in exception names and the classes of errors.py."""
    import builtins

    names = {n for n, v in vars(builtins).items() if isinstance(v, type) and issubclass(v, BaseException)}
    return names | {n for n, v in vars(errors).items() if isinstance(v, type) and issubclass(v, BaseException)}


def test_every_exception_class_is_defined_in_errors_py():
    known = _exception_names()
    elsewhere = []
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        if path.name == "errors.py" and path.parent == PACKAGE_ROOT:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else b.attr for b in node.bases
                         if isinstance(b, (ast.Name, ast.Attribute))}
                if bases & known:
                    elsewhere.append(f"{path.relative_to(PACKAGE_ROOT.parent)}:{node.lineno} {node.name}")
    assert not elsewhere, "exception classes outside mutualslam_cli/errors.py:\n" + "\n".join(elsewhere)


@pytest.mark.parametrize("cls", [errors.DatasetError, errors.ConfigError, errors.GeometryError,
                                 errors.KeyframeError, errors.ResultsLocked])
def test_user_errors_are_mslam_errors(cls):
    assert issubclass(cls, errors.MslamError)


@pytest.mark.parametrize(("cls", "base"), [(errors.ShapeError, ValueError), (errors.TransitionError, RuntimeError)])
def test_programming_errors_are_not_mslam_errors(cls, base):
    assert issubclass(cls, base)
    assert not issubclass(cls, errors.MslamError)


def test_check_shape_raises_a_programming_error():
    with pytest.raises(errors.ShapeError) as info:
        check_shape(np.zeros((2, 3)), ["N", "N"])
    assert not isinstance(info.value, errors.MslamError)


def _sample(k: int) -> KeyframeSample:
    return KeyframeSample(kf_id=k, image=torch.zeros(3, 4, 6), K=torch.eye(3), pose=np.eye(4),
                          uv=torch.zeros(3, 2), depth=torch.ones(3))


def test_keyframe_buffer_errors():
    b = KeyframeBuffer()
    b.add(_sample(3), training=True)
    with pytest.raises(errors.KeyframeError, match="must increase"):
        b.add(_sample(3), training=True)
    with pytest.raises(errors.KeyframeError, match="not stored"):
        b.get(7)
    with pytest.raises(errors.ConfigError, match="replay_capacity"):
        KeyframeBuffer(capacity=2)

"""Plain data types shared by every stage, and the one shape-check helper.

Conventions (used everywhere in mslam):

- Poses are 4×4 float64 ``T_wc`` (camera-to-world) unless a name says otherwise.
- Images are ``(H, W, 3)`` uint8 RGB in numpy; ``(B, 3, H, W)`` float in [0, 1] in torch.
- Depth maps are ``(H, W)`` float32 metres (or map units for VO output); 0 means invalid.
- Pixels are ``(N, 2)`` float ``(u, v)`` = (column, row), origin at the centre of the
  top-left pixel.
- Timestamps are float seconds (ICL-NUIM: frame numbers).
"""

from __future__ import annotations

from collections.abc import Callable
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np

from mutualslam_cli.errors import ShapeError

Scalar: TypeAlias = str | int | float | bool | None
"""One JSON/YAML leaf value."""
JSON: TypeAlias = Scalar | list["JSON"] | dict[str, "JSON"]
"""Any value ``json.loads`` can return (a parsed file before its fields are checked)."""
JSONObject: TypeAlias = dict[str, JSON]
"""A parsed JSON/YAML mapping (a manifest, a config section, a record) before it is read into a typed record."""
Document: TypeAlias = dict[str, object]
"""A mapping about to be written as JSON or YAML (a manifest, a record): any values ``results.summary.plain``
makes JSON-safe on writing (numpy scalars and arrays, paths)."""
Info: TypeAlias = dict[str, object]
"""Free-form figures for logs and progress callbacks: read for display only, never for control."""

Predictor = Callable[[list[np.ndarray]], np.ndarray]
"""A batched depth predictor: ``(H, W, 3)`` uint8 RGB frames → ``(B, h, w)`` float32 depth at the network's size."""

Progress = Callable[[str, Info], None]
"""``progress(stage, info)``: a stage's name (``vo``, ``adapt``, ``eval``, ``dense``, ``decode``…) and a
dict of figures (``done``, ``total``, …). The library reports through it; the CLI draws the bars."""


def check_shape(x: object, shape: Seq[str | int], name: str = "array") -> None:
    """Raise :class:`ShapeError` unless ``x.shape`` matches ``shape``.

    ``shape`` entries are ints (exact size), digit strings (exact size) or names (any size,
    but the same name must have the same size everywhere). ``"*"`` matches any number of
    leading dimensions and may appear only first.

    >>> check_shape(np.zeros((2, 3, 4)), ["*", 3, "W"])
    >>> check_shape(np.zeros((2, 3)), ["N", "N"])
    Traceback (most recent call last):
    ...
    mutualslam_cli.errors.ShapeError: array: expected shape [N, N], got (2, 3)
    """
    actual = tuple(getattr(x, "shape", ()))
    spec = list(shape)
    if spec and spec[0] == "*":
        spec = spec[1:]
        actual_tail = actual[len(actual) - len(spec):] if len(actual) >= len(spec) else None
    else:
        actual_tail = actual if len(actual) == len(spec) else None
    ok = actual_tail is not None
    sizes: dict[str, int] = {}
    if ok:
        for want, got in zip(spec, actual_tail):  # type: ignore[arg-type]
            if isinstance(want, int) or (isinstance(want, str) and want.isdigit()):
                ok = int(want) == got
            else:
                ok = sizes.setdefault(want, got) == got
            if not ok:
                break
    if not ok:
        pretty = ", ".join(str(s) for s in shape)
        raise ShapeError(f"{name}: expected shape [{pretty}], got {actual}")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one camera at a given image size.

    ``dist`` holds OpenCV radial-tangential coefficients ``(k1, k2, p1, p2, k3)`` when the
    images are not undistorted (TUM fr1), else ``None``. ``fy`` may be negative (ICL-NUIM
    convention, decided from the data).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] | None = None

    def K(self) -> np.ndarray:
        """The 3×3 float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics for the same camera resized to ``width`` × ``height`` pixels.

        Pixel centres are kept consistent: ``c' = (c + 0.5)·s − 0.5``. Distortion
        coefficients are unchanged (they act on normalised coordinates).
        """
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width),
            height=int(height),
        )

    def as_list(self) -> list[float]:
        """``[fx, fy, cx, cy]`` for manifests and tables."""
        return [self.fx, self.fy, self.cx, self.cy]


@dataclass
class Trajectory:
    """A timed sequence of poses.

    Attributes:
        timestamps: ``(N,)`` float64 seconds, strictly increasing.
        poses: ``(N, 4, 4)`` float64 camera-to-world transforms.
    """

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64)
        check_shape(self.poses, [len(self.timestamps), 4, 4], "Trajectory.poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def subset(self, mask_or_index: np.ndarray) -> Trajectory:
        """A new trajectory with the selected rows."""
        return Trajectory(self.timestamps[mask_or_index], self.poses[mask_or_index])


@dataclass(frozen=True)
class FrameRef:
    """One associated RGB(-D) frame of a sequence on disk (nothing loaded yet).

    Attributes:
        index: position in the sequence, 0-based.
        timestamp: image time in seconds (ICL-NUIM: frame number).
        rgb_path: colour image file.
        depth_path: depth image file, or ``None`` when the frame has no depth.
        pose: ``(4, 4)`` GT ``T_wc`` at the image time, or ``None`` when GT does not cover it.
    """

    index: int
    timestamp: float
    rgb_path: Path
    depth_path: Path | None
    pose: np.ndarray | None = field(default=None, compare=False, repr=False)


@dataclass
class SequenceSpec:
    """A ``datasets.yaml`` entry (or a folder given on the command line), resolved.

    Attributes:
        name: short name used in result paths.
        root: folder holding the sequence.
        format: ``tum`` | ``icl`` (``*_frei_png``) | ``icl_loop`` (native) | ``lab`` | ``synthetic``.
        intrinsics: ``None`` means "from the format's family default / the data".
        depth_scale: raw depth units per metre (TUM 5000, 7-Scenes 1000).
        gt_file: trajectory file relative to ``root``, or ``None`` (no GT poses).
        extra: free-form options of the format (e.g. ``fy_sign: auto``).
    """

    name: str
    root: Path
    format: str
    intrinsics: Intrinsics | None = None
    depth_scale: float = 5000.0
    gt_file: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

"""TUM-style text files: list files, trajectories, timestamp association, GT at image times.

Formats (Sturm et al., IROS 2012, the TUM RGB-D benchmark):

- list files (``rgb.txt``, ``depth.txt``): ``timestamp path`` per line, ``#`` comments;
- trajectories (``groundtruth.txt``, ``*.gt.freiburg``): ``timestamp tx ty tz qx qy qz qw``,
  camera-to-world, translation in metres;
- association files (``associations.txt``): ``t_a path_a t_b path_b``.

Every reader accepts a path or a text stream (``io.StringIO``) and raises
:class:`DatasetError` naming the file and line of a malformed entry.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, overload

import numpy as np

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import interpolate_pose, pose_from_tq, rot_to_quat
from mutualslam_cli.types import Trajectory

PathOrStream = str | os.PathLike | IO[str]

MAX_DT = 0.02
"""Association window in seconds (TUM benchmark ``associate.py`` default): RGB↔depth pairing
(:func:`associate`) and the default of the ATE's estimate↔reference association
(:mod:`mutualslam_cli.metrics.trajectory`)."""

@overload
def stamps_match(dt: np.ndarray, max_dt: float) -> np.ndarray: ...
@overload
def stamps_match(dt: float, max_dt: float) -> bool: ...
def stamps_match(dt: np.ndarray | float, max_dt: float) -> np.ndarray | bool:
    """The package's one association window: ``|dt| ≤ max_dt``, ``dt`` in seconds, any shape.

    Inclusive, as evo's matching, so the ATE pairs are evo's to the last pair (the TUM benchmark
    script's window is strict; the two differ only for a pair exactly ``max_dt`` apart). No
    tolerance: a float64 difference of two stamps is exact IEEE arithmetic, the same on every
    CPU, so unlike a projected pixel it cannot fall on either side of the bound by machine.
    """
    return np.abs(dt) <= max_dt


MAX_GT_GAP = 0.1
"""GT interpolation: both bracketing GT samples must lie within this many seconds of the image
time. The TUM motion capture runs at 100 Hz; fr1_xyz has one 0.11 s hole, which this still
bridges (its images are ≤ 0.06 s from either side), while longer dropouts give ``None``.
ICL-NUIM timestamps are frame numbers, so there only exact matches qualify."""


@dataclass
class ListFile:
    """A parsed list file.

    Attributes:
        name: file name used in messages.
        timestamps: ``(N,)`` float64 seconds, in file order.
        columns: per entry, the remaining whitespace-separated fields (first is the path).
        lines: per entry, its 1-based line number in the file.
    """

    name: str
    timestamps: np.ndarray
    columns: list[list[str]]
    lines: list[int]

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def paths(self) -> list[str]:
        """The first field after the timestamp of every entry."""
        return [c[0] for c in self.columns]


def _open(src: PathOrStream) -> tuple[str, list[str]]:
    """Read all lines of a path or stream; return ``(display name, lines)``."""
    if isinstance(src, (str, os.PathLike)):
        path = Path(src)
        if not path.is_file():
            raise DatasetError(f"{path}: file not found")
        with open(path, encoding="utf-8", errors="replace") as f:
            return str(path), f.read().splitlines()
    name = getattr(src, "name", None) or "<stream>"
    return str(name), src.read().splitlines()


def _data_lines(lines: list[str]) -> list[tuple[int, list[str]]]:
    out = []
    for k, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        out.append((k, s.replace(",", " ").split()))
    return out


def read_list_file(src: PathOrStream, min_fields: int = 2) -> ListFile:
    """Read a TUM list file (``timestamp path [more fields]`` per line).

    Args:
        src: path or text stream.
        min_fields: fields required per line including the timestamp (2 for ``rgb.txt``,
            4 for ``associations.txt``).

    Raises:
        DatasetError: on a line with too few fields or a non-numeric timestamp.
    """
    name, lines = _open(src)
    ts, cols, nums = [], [], []
    what = "'timestamp path'" if min_fields == 2 else f"{min_fields} fields 't_a path_a t_b path_b'"
    for k, fields in _data_lines(lines):
        try:
            if len(fields) < min_fields:
                raise ValueError
            t = float(fields[0])
        except ValueError:
            raise DatasetError(f"{name}:{k}: expected {what}, got {' '.join(fields)!r}") from None
        ts.append(t)
        cols.append(fields[1:])
        nums.append(k)
    return ListFile(name, np.asarray(ts, dtype=np.float64), cols, nums)


def read_tum_trajectory(src: PathOrStream) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, camera-to-world).

    Rows are sorted by time; duplicate timestamps keep the first row.

    Returns:
        Trajectory with ``(N,)`` timestamps and ``(N, 4, 4)`` poses ``T_wc``.

    Raises:
        DatasetError: ``"<file>:<line>: expected 8 numbers ..."`` for a malformed line, or a
            zero quaternion.
    """
    name, lines = _open(src)
    rows, nums = [], []
    for k, fields in _data_lines(lines):
        try:
            if len(fields) != 8:
                raise ValueError
            vals = [float(x) for x in fields]
            if not np.all(np.isfinite(vals)):
                raise ValueError
        except ValueError:
            raise DatasetError(
                f"{name}:{k}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {' '.join(fields)!r}"
            ) from None
        if np.linalg.norm(vals[4:]) < 1e-12:
            raise DatasetError(f"{name}:{k}: zero quaternion; expected a unit quaternion 'qx qy qz qw'")
        rows.append(vals)
        nums.append(k)
    if not rows:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    arr = np.asarray(rows)
    order = np.argsort(arr[:, 0], kind="stable")
    arr = arr[order]
    keep = np.concatenate([[True], np.diff(arr[:, 0]) > 0])
    arr = arr[keep]
    return Trajectory(arr[:, 0], pose_from_tq(arr[:, 1:4], arr[:, 4:8]))


def _fmt(v: float, spec: str | None) -> str:
    return repr(float(v)) if spec is None else format(float(v), spec)


def format_tum_trajectory(
    traj: Trajectory, comments: Iterable[str] = (), time_format: str | None = None, value_format: str | None = None
) -> str:
    """TUM text of a trajectory: ``timestamp tx ty tz qx qy qz qw`` per line (``qw ≥ 0``).

    Args:
        traj: ``(N,)`` timestamps (seconds) and ``(N, 4, 4)`` ``T_wc`` (translation in metres).
        comments: header lines written as ``# <line>`` before the ``# timestamp tx ty …`` line.
        time_format, value_format: :func:`format` specs (e.g. ``".6f"``) of the timestamp and
            of the seven pose numbers; ``None``: full float precision (``repr`` round-trips exactly).
    """
    q = rot_to_quat(traj.poses[:, :3, :3]) if len(traj) else np.zeros((0, 4))
    out = [f"# {c}" for c in comments] + ["# timestamp tx ty tz qx qy qz qw"]
    for t, T, qq in zip(traj.timestamps, traj.poses, q):
        out.append(" ".join([_fmt(t, time_format)] + [_fmt(v, value_format) for v in (*T[:3, 3], *qq)]))
    return "\n".join(out) + "\n"


def write_tum_trajectory(
    dst: PathOrStream, traj: Trajectory, comments: Iterable[str] = (), time_format: str | None = None,
    value_format: str | None = None,
) -> None:
    """Write a trajectory in TUM format (:func:`format_tum_trajectory`); atomic for paths
    (temporary file, then rename), written as is to a stream."""
    text = format_tum_trajectory(traj, comments, time_format, value_format)
    if not isinstance(dst, (str, os.PathLike)):
        dst.write(text)
        return
    atomic_write_text(dst, text)


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_dt: float = MAX_DT, offset: float = 0.0) -> list[tuple[int, int]]:
    """Greedy unique nearest-timestamp association (TUM benchmark ``associate.py``).

    All pairs within the window (:func:`stamps_match` on ``a − (b + offset)``) are sorted by
    their difference and taken greedily, each element used at most once. The package's one
    greedy association: RGB ↔ depth in the TUM-layout loader, and ``association="unique"`` of the
    ATE (:func:`mutualslam_cli.metrics.trajectory.associate_indices`).

    Args:
        ts_a: ``(N,)`` timestamps of the first stream (seconds).
        ts_b: ``(M,)`` timestamps of the second stream.
        max_dt: tolerance in seconds (inclusive, :func:`stamps_match`).
        offset: added to ``ts_b`` before matching.

    Returns:
        Index pairs ``(i, j)`` sorted by ``ts_a[i]``.
    """
    a = np.asarray(ts_a, dtype=np.float64).reshape(-1)
    b = np.asarray(ts_b, dtype=np.float64).reshape(-1) + offset
    if len(a) == 0 or len(b) == 0:
        return []
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    cand: list[tuple[float, int, int]] = []
    for i, t in enumerate(a):
        lo = np.searchsorted(bs, t - max_dt, side="left")
        hi = np.searchsorted(bs, t + max_dt, side="right")
        for k in range(lo, hi):
            d = abs(t - bs[k])
            if stamps_match(d, max_dt):
                cand.append((d, i, int(order_b[k])))
    cand.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in cand:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j))
    pairs.sort(key=lambda p: (a[p[0]], p[0]))
    return pairs


def poses_at(gt: Trajectory, times: np.ndarray, max_gap: float = MAX_GT_GAP) -> list[np.ndarray | None]:
    """GT poses at arbitrary times by interpolation between the bracketing samples.

    Translation is interpolated linearly and rotation by slerp
    (:func:`mutualslam_cli.geometry.interpolate_pose`). A time equal to a sample (within
    1e-9 s) returns that sample. Outside the GT span, or when either bracketing sample is
    farther than ``max_gap`` seconds, the result is ``None``.

    Args:
        gt: trajectory with strictly increasing timestamps.
        times: ``(K,)`` query times (seconds).
        max_gap: see :data:`MAX_GT_GAP`.

    Returns:
        ``K`` entries, each a ``(4, 4)`` ``T_wc`` or ``None``.
    """
    ts = gt.timestamps
    out: list[np.ndarray | None] = []
    for t in np.asarray(times, dtype=np.float64).reshape(-1):
        if len(ts) == 0:
            out.append(None)
            continue
        j = int(np.searchsorted(ts, t, side="left"))
        if j < len(ts) and abs(ts[j] - t) <= 1e-9:
            out.append(gt.poses[j].copy())
            continue
        if j > 0 and abs(ts[j - 1] - t) <= 1e-9:
            out.append(gt.poses[j - 1].copy())
            continue
        if j == 0 or j >= len(ts):
            out.append(None)
            continue
        t0, t1 = ts[j - 1], ts[j]
        if t - t0 > max_gap or t1 - t > max_gap:
            out.append(None)
            continue
        out.append(interpolate_pose(gt.poses[j - 1], gt.poses[j], (t - t0) / (t1 - t0)))
    return out


"""The map files of a run (``map_vo.ply``, ``map_culled.ply``, ``map_ba.ply``): binary PLY
written with open3d, each point coloured by its depth error against GT.

Colour mapping (:func:`error_colours`): ``d = log z − log z*`` of each point in its host keyframe
minus the mean of ``d`` over the map's points with GT depth (a monocular map's unknown scale is a
constant in ``d``; the RMS of what is left is the map's e_si), linear from blue (≤ −0.5: too near)
through grey (0) to red (≥ +0.5: too far); light grey where there is no GT depth. The raw ``d``
rides along as the scalar vertex property ``log_depth_error`` (NaN without GT).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np

from mutualslam_cli.atomic import atomic_write_text, atomic_write_with
from mutualslam_cli.errors import DatasetError, ShapeError

#: |log z − log z*| (after removing the map's mean) at which the error colours saturate.
ERROR_SATURATION = 0.5
#: RGB in [0, 1] of a point too near (d − mean ≤ −saturation), right (0), too far (≥ +saturation),
#: and without GT depth.
ERROR_NEAR = (0.13, 0.40, 0.80)
ERROR_ZERO = (0.62, 0.62, 0.62)
ERROR_FAR = (0.80, 0.13, 0.13)
NO_GT = (0.86, 0.86, 0.86)


def open3d() -> ModuleType:
    """The ``open3d`` module, imported on first use (heavy: ~1 s), untyped: its pybind stubs miss the defaults
    of ``core.Tensor(array, dtype=, device=)`` and type paths as ``os.PathLike`` where a ``str`` is taken."""
    import open3d as o3d

    return o3d


def error_colours(log_errors: np.ndarray, saturation: float = ERROR_SATURATION) -> np.ndarray:
    """Diverging colours of per-point log-depth errors, as written into the map PLYs.

    ``d_i − mean(d)`` (the mean over the points with GT removes the monocular map's log scale;
    the RMS of what is left is the map's e_si) is mapped linearly from blue (:data:`ERROR_NEAR`,
    ``≤ −saturation``: the point is too near) through grey (:data:`ERROR_ZERO`, 0) to red
    (:data:`ERROR_FAR`, ``≥ +saturation``: too far); points without GT depth (NaN) are light
    grey (:data:`NO_GT`).

    Args:
        log_errors: ``(P,)`` ``log z − log z*`` (:func:`~mutualslam_cli.stages.evaluation.map_log_depth_errors`).
        saturation: ``|d − mean(d)|`` (log units) at which the colour is fully blue or red.
    Returns:
        ``(P, 3)`` float64 RGB in [0, 1].
    """
    d = np.asarray(log_errors, dtype=float).reshape(-1)
    out = np.tile(np.asarray(NO_GT), (len(d), 1))
    ok = np.isfinite(d)
    if ok.any():
        t = np.clip((d[ok] - d[ok].mean()) / saturation, -1.0, 1.0)[:, None]
        zero, near, far = np.asarray(ERROR_ZERO), np.asarray(ERROR_NEAR), np.asarray(ERROR_FAR)
        out[ok] = np.where(t < 0, zero - t * (near - zero), zero + t * (far - zero))
    return out


def write_ply(path: Path, points: np.ndarray, log_errors: np.ndarray | None = None) -> None:
    """Binary PLY of a map written with open3d (readable by open3d, MeshLab, CloudCompare), atomically.

    Vertex properties: ``x y z`` (double, map units), ``red green blue`` (uchar,
    :func:`error_colours` of ``log_errors``; :data:`NO_GT` grey for every point when
    ``log_errors`` is None) and, when ``log_errors`` is given, ``log_depth_error`` (float:
    ``log z − log z*`` in the host keyframe, NaN where there is no GT depth). An empty map is
    written as a header-only ASCII PLY (open3d refuses to write zero points).

    Args:
        points: ``(P, 3)`` world positions.
        log_errors: optional ``(P,)`` per-point ``log z − log z*``.
    """
    o3d = open3d()  # heavy (1 s): only when a map is written

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if log_errors is not None and len(log_errors) != len(points):
        raise ShapeError(f"write_ply: {len(log_errors)} errors for {len(points)} points")
    if len(points) == 0:
        extra = "property float log_depth_error\n" if log_errors is not None else ""
        atomic_write_text(path, "ply\nformat ascii 1.0\nelement vertex 0\nproperty double x\nproperty double y\n"
                          "property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                          f"{extra}end_header\n")
        return
    colours = error_colours(np.full(len(points), np.nan) if log_errors is None else log_errors)
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    pc.point.colors = o3d.core.Tensor(np.round(colours * 255).astype(np.uint8))
    if log_errors is not None:
        pc.point.log_depth_error = o3d.core.Tensor(np.asarray(log_errors, np.float32).reshape(-1, 1))
    atomic_write_with(path, lambda name: o3d.t.io.write_point_cloud(name, pc), "point cloud (open3d)")


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A map PLY written by :func:`write_ply` (or the older xyz-only ASCII ones).

    Returns:
        ``(points (P, 3) float64, colours (P, 3) float64 in [0, 1] or None, log_errors (P,) or None)``.

    Raises:
        DatasetError: the file is missing or not a PLY point cloud.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4096).split(b"end_header", 1)[0].decode("ascii", "replace")
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the map ({e.strerror})") from None
    n = next((ln.split()[2] for ln in head.splitlines() if ln.startswith("element vertex")), None)
    if not head.startswith("ply") or n is None or not n.isdigit():
        raise DatasetError(f"{path}: not a PLY point cloud (expected a 'ply' header with 'element vertex N')")
    if int(n) == 0:
        return np.zeros((0, 3)), None, None
    o3d = open3d()

    pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or len(pc.point.positions) != int(n):
        raise DatasetError(f"{path}: open3d read no points (expected {n} vertices with x y z)")
    pts = pc.point.positions.numpy().astype(np.float64)
    col = pc.point.colors.numpy() if "colors" in pc.point else None
    if col is not None:
        col = col.astype(np.float64) / (255.0 if col.dtype == np.uint8 else 1.0)
    err = pc.point.log_depth_error.numpy().reshape(-1).astype(np.float64) if "log_depth_error" in pc.point else None
    return pts, col, err

"""Trajectory and map of a run held against GT: the ATE of keyframes and of every tracked frame,
each map point's log-depth error in its host keyframe, the map's e_si, and the summary keys they fill.

Used by the stages that make a trajectory or a map (front end, BA)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import MslamError
from mutualslam_cli.metrics import trajectory as tm
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.vo.camera import distort_points
from mutualslam_cli.vo.result import VOResult


def evaluate_trajectory(seq: Sequence, vo: VOResult, max_dt: float = MAX_DT) -> dict[str, object]:
    """Sim(3)-aligned ATE of keyframes and of all tracked frames against the stored GT.

    Re-initialised front ends (several segments) are aligned per segment (each has its own scale);
    the result then says ``per_segment: True``.

    Returns:
        ``{"kf": AteResult|None, "all": AteResult|None, "notes": {...}}``.
    """
    out: dict[str, object] = {"kf": None, "all": None, "notes": {}}
    notes: dict[str, str] = out["notes"]  # type: ignore[assignment]
    if seq.gt is None or len(seq.gt) == 0:
        notes["trajectory"] = "sequence has no GT poses"
        return out
    kf = vo.traj_kf
    kf_seg = np.array([k.segment for k in vo.keyframes])
    tracked = vo.frame_segment >= 0
    all_seg = vo.frame_segment[tracked] if len(vo.frame_segment) == len(seq) else None
    for key, traj, seg in (("kf", kf, kf_seg), ("all", vo.traj_all, all_seg)):
        if len(traj) < 3:
            notes[key] = f"only {len(traj)} poses"
            continue
        try:
            if seg is not None and len(seg) == len(traj) and len(np.unique(seg)) > 1:
                out[key] = tm.ate_segments(seq.gt, traj, seg, max_dt=max_dt)
            else:
                out[key] = tm.ate(seq.gt, traj, align="sim3", max_dt=max_dt)
        except MslamError as e:
            notes[key] = str(e)
    return out


def _lookup_gt_depth(seq: Sequence, frame_index: int, pixels: np.ndarray) -> np.ndarray:
    """GT depth (m) at pinhole ``pixels`` ``(N, 2)`` of a frame; NaN where missing."""
    depth = seq.load_depth(frame_index)
    if depth is None:
        return np.full(len(pixels), np.nan)
    pix = distort_points(pixels, seq.intrinsics)  # GT depth images are in the raw (distorted) image
    out = lookup_nearest(depth, pix)
    out[out <= 0] = np.nan
    return out


def map_log_depth_errors(seq: Sequence, vo: VOResult, keep: np.ndarray | None = None) -> np.ndarray:
    """Signed log-depth error of each map point in its host keyframe: ``d_i = log z_i − log z_i*``.

    ``z_i`` is the point's depth in its host keyframe (map units: a monocular map carries its own
    log scale in every ``d_i``), ``z_i*`` the GT depth at the host pixel (m).

    Args:
        keep: optional boolean mask over ``vo.points`` (e.g. after culling).
    Returns:
        ``(P,)`` float64, one value per (kept) point in ``vo.points`` order (the order of
        :meth:`VOResult.points_world`); NaN where the host frame has no GT depth at the pixel.
    """
    pts = vo.points if keep is None else vo.points.subset(keep)
    out = np.full(len(pts), np.nan)
    for kf in vo.keyframes:
        m = pts.host == kf.id
        if not np.any(m):
            continue
        gt = _lookup_gt_depth(seq, kf.frame_index, pts.pixel[m])
        with np.errstate(divide="ignore", invalid="ignore"):
            d = -np.log(pts.inv_depth[m]) - np.log(gt)  # log(1/ρ) − log z*
        d[~np.isfinite(gt) | ~(pts.inv_depth[m] > 0)] = np.nan
        out[m] = d
    return out


def esi_of_log_errors(d: np.ndarray) -> tuple[float, int]:
    """e_si of per-point log errors ``d`` ``(P,)`` (NaN = no GT): the population standard deviation
    of the finite ones, :func:`~mutualslam_cli.metrics.depth.esi`'s formula.

    Returns:
        ``(e_si, n_finite)``; e_si is NaN when no value is finite.
    """
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return float("nan"), 0
    return float(np.sqrt(np.mean((d - d.mean()) ** 2))), int(d.size)


def map_esi(seq: Sequence, vo: VOResult, keep: np.ndarray | None = None) -> tuple[float, int]:
    """e_si of map-point depths in their host keyframe against GT depth at the host pixel
    (:func:`map_log_depth_errors` then :func:`esi_of_log_errors`).

    Args:
        keep: optional boolean mask over ``vo.points`` (e.g. after culling).
    Returns:
        ``(e_si, n_points_with_gt)``; e_si is NaN when no point has GT depth.
    """
    return esi_of_log_errors(map_log_depth_errors(seq, vo, keep))


def set_ate(summary: Summary, traj: dict[str, Any], names: dict[str, str]) -> None:
    """RMSE of :func:`~mutualslam_cli.stages.evaluation.evaluate_trajectory`'s ``kf``/``all`` under ``names``."""
    for key, name in names.items():
        r = traj[key]
        if r is None:
            summary.absent(name, traj["notes"].get(key, traj["notes"].get("trajectory", "not computed")))
        else:
            summary.set(name, float(r.rmse))
            if getattr(r, "note", None):  # re-initialised VO: each segment aligned on its own
                summary.notes[name] = r.note

"""Trajectory and map of a run held against GT: the ATE of keyframes and of every tracked frame,
each map point's log-depth error in its host keyframe, the map's e_si (their summary keys:
:func:`mutualslam_cli.stages.ate_keys.set_ate`).

Used by the stages that make a trajectory or a map (front end, BA)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import MslamError
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics import trajectory as tm
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.types import Trajectory
from mutualslam_cli.vo.camera import distort_points


def evaluate_trajectory(seq: Sequence, vo: VOResult, max_dt: float = MAX_DT) -> dict[str, Any]:
    """ATE of the keyframes and of all tracked frames against the stored GT.

    The headline is one Sim(3) over the whole trajectory (evo's ``-as``, as ORB-SLAM3, DPVO and
    DROID-SLAM report it): a front end that restarted in segments, each at the origin with its own
    scale, pays for it there. When there are several segments, each aligned on its own is kept as
    a secondary figure (``kf_per_segment``, ``all_per_segment``).

    Returns:
        ``{"kf": AteResult|None, "all": AteResult|None, "kf_per_segment": SegmentedAteResult|None,
        "all_per_segment": …, "segments": int, "notes": {key: why a value is None}}``.
    """
    out: dict[str, Any] = {"kf": None, "all": None, "kf_per_segment": None, "all_per_segment": None,
                           "notes": {}}
    notes: dict[str, str] = out["notes"]
    kf_seg = np.array([k.segment for k in vo.keyframes])
    out["segments"] = len(np.unique(kf_seg))
    if seq.gt is None or len(seq.gt) == 0:
        notes["trajectory"] = "sequence has no GT poses"
        return out
    tracked = vo.frame_segment >= 0
    all_seg = vo.frame_segment[tracked] if len(vo.frame_segment) == len(seq) else None
    for key, traj, seg in (("kf", vo.traj_kf, kf_seg), ("all", vo.traj_all, all_seg)):
        if len(traj) < 3:
            notes[key] = notes[f"{key}_per_segment"] = f"only {len(traj)} poses"
            continue
        try:
            out[key] = tm.ate(seq.gt, traj, align="sim3", max_dt=max_dt)
        except MslamError as e:
            notes[key] = str(e)
        if seg is None or len(seg) != len(traj) or len(np.unique(seg)) < 2:
            notes[f"{key}_per_segment"] = "one segment: the single alignment is the only one"
            continue
        try:
            out[f"{key}_per_segment"] = tm.ate_segments(seq.gt, traj, seg, max_dt=max_dt)
        except MslamError as e:
            notes[f"{key}_per_segment"] = str(e)
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


def esi_of_log_errors(d: np.ndarray, units: np.ndarray | None = None) -> tuple[float, int]:
    """e_si of per-point log errors ``d`` ``(P,)`` (NaN = no GT): the population standard deviation
    of the finite ones, :func:`~mutualslam_cli.metrics.depth.esi`'s formula — with ``units`` ``(P,)``
    (each point's map unit, :func:`point_units`) about each unit's own mean, since segments not joined
    by a bridge each have their own scale, which e_si must not count as error.

    Returns:
        ``(e_si, n_finite)``; e_si is NaN when no value is finite.
    """
    d = np.asarray(d, dtype=float)
    ok = np.isfinite(d)
    if not ok.any():
        return float("nan"), 0
    u = np.zeros(len(d), np.int64) if units is None else np.asarray(units)
    _, inv = np.unique(u[ok], return_inverse=True)
    means = np.bincount(inv, weights=d[ok]) / np.bincount(inv)
    return float(np.sqrt(np.mean((d[ok] - means[inv]) ** 2))), int(ok.sum())


def point_units(vo: VOResult, units: dict[int, int] | None = None) -> np.ndarray:
    """``(P,)`` the map unit of each point: its host keyframe's segment, or ``units[segment]`` (segments a
    bridge or a merge joined share one, :meth:`~mutualslam_cli.map.result.VOResult.unit_of_segment`)."""
    seg = {k.id: k.segment for k in vo.keyframes}
    out = np.array([seg.get(int(h), -1) for h in vo.points.host], np.int64)
    return out if units is None else np.array([units.get(int(s), int(s)) for s in out], np.int64)


def common_frames_ate(seq: Sequence, maps: dict[str, VOResult | None], max_dt: float = MAX_DT,
                      keyframes: bool = False) -> tuple[dict[str, float | None], int, str | None]:
    """ATE RMSE (one Sim(3) each) of the frames *every* given map tracked, so each column of a credit table
    (front end, bridged, after BA, …) is scored on the same frames; ``keyframes``: of the keyframes every map
    has (their ``traj_kf``) instead of every tracked frame.

    Returns:
        ``({name: rmse or None for a None map}, n_frames, why)``: ``why`` says why nothing could be scored.
    """
    have = {k: v for k, v in maps.items() if v is not None}
    out: dict[str, float | None] = {k: None for k in maps}
    if seq.gt is None or len(seq.gt) == 0:
        return out, 0, "sequence has no GT poses"
    if not have:
        return out, 0, "no trajectory"
    trajs = {k: v.traj_kf if keyframes else v.traj_all for k, v in have.items()}
    common = set.intersection(*(set(np.round(t.timestamps, 6).tolist()) for t in trajs.values()))
    if len(common) < 3:
        return out, len(common), f"only {len(common)} {'keyframes' if keyframes else 'frames'} in every column"
    keep = np.array(sorted(common))
    for k, t in trajs.items():
        m = np.isin(np.round(t.timestamps, 6), keep)
        try:
            out[k] = float(tm.ate(seq.gt, Trajectory(t.timestamps[m], t.poses[m]),
                                  align="sim3", max_dt=max_dt).rmse)
        except MslamError as e:
            return {k: None for k in maps}, len(keep), str(e)
    return out, len(keep), None


def map_esi(seq: Sequence, vo: VOResult, keep: np.ndarray | None = None) -> tuple[float, int]:
    """e_si of map-point depths in their host keyframe against GT depth at the host pixel
    (:func:`map_log_depth_errors` then :func:`esi_of_log_errors`).

    Args:
        keep: optional boolean mask over ``vo.points`` (e.g. after culling).
    Returns:
        ``(e_si, n_points_with_gt)``; e_si is NaN when no point has GT depth.
    """
    return esi_of_log_errors(map_log_depth_errors(seq, vo, keep))

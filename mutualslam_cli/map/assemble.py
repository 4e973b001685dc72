"""Assembly of the front end's state into a :class:`VOResult` (DESIGN §4).

Knows the map, the per-frame records and a :class:`RunStats`, not the front end itself: the
front end (:mod:`~mutualslam_cli.vo.frontend`) imports this module, never the other way round.
"""

from __future__ import annotations

from collections.abc import Sequence as Seq
from dataclasses import dataclass
from itertools import combinations
from typing import TypedDict

import numpy as np

from mutualslam_cli.geometry import pinhole
from mutualslam_cli.map.records import Relocalised
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.map.store import Map
from mutualslam_cli.types import FrameRef, Intrinsics, Trajectory

LOSS_REASONS = ("too_few_tracks", "failed_alignment", "failed_init")
"""Why frames went untracked: KLT kept fewer usable tracks (map points, settled seeds) than ``vo.min_tracked``;
the tracks left agreed on no pose; no segment could be initialised (at the start, or once the relocalisation
window after a loss had passed)."""


class WindowStats(TypedDict, total=False):
    """One windowed BA's figures (:attr:`FrontEndStats.ba_stats`): the initial and final robust cost of
    :func:`~mutualslam_cli.vo.local_ba.solve` (``cost0``, ``cost``; ``iters`` only when there was nothing to solve),
    then the mapper's ``solve_ms``, the window's keyframe ``kf``, its ``points`` and ``obs`` (observations)."""

    cost0: float
    cost: float
    iters: int
    solve_ms: float
    kf: int
    points: int
    obs: int


@dataclass(frozen=True)
class RunStats:
    """What the front end counted and timed over one run (becomes ``VOResult.meta``).

    Attributes:
        segment: index of the last tracking segment (-1: never initialised).
        init_methods: how each segment was initialised, in order.
        timing: seconds per stage, summed over all frames.
        total_s: wall time of the whole run.
        reprojected: map points re-attached by re-projection (reused: of them, points from outside the newest
            keyframes, ``vo.reuse_map``).
        old_share: mean over tracked frames of the share of their tracked map points first seen more than
            :data:`~mutualslam_cli.vo.frontend.OLD_AGE_KFS` keyframes before the newest (``None``: none tracked).
        scale_check: the network's scale check (:meth:`~mutualslam_cli.vo.scale_check.ScaleCheck.summary`), ``None``
            when the front end ran without the network.
        ba_stats: one dict per windowed BA (``points``, ``solve_ms``, …).
        ba_threaded: whether the windowed BA ran on a worker thread.
        relocalisations: one :class:`~mutualslam_cli.map.records.Relocalised` per accepted relocalisation.
        reloc_rejected: candidate poses the relocalisation's verification refuted.
        losses: ``(frame, reason, why)`` of each tracking loss.
        init_wait: frames after a loss during which relocalisation is tried before a new segment may start
            (``vo.reloc_frames``; 0: relocalisation off).
        rescued: frames whose weak pose was rescued, by how (:mod:`~mutualslam_cli.vo.rescue`).
    """

    segment: int
    init_methods: Seq[str]
    timing: dict[str, float]
    total_s: float
    reprojected: int
    ba_stats: Seq[WindowStats]
    ba_threaded: bool
    relocalisations: Seq[Relocalised] = ()
    reloc_rejected: int = 0
    reused: int = 0
    fused: int = 0
    old_share: float | None = None
    scale_check: dict[str, float | int | None] | None = None
    losses: Seq[tuple[int, str, str]] = ()
    init_wait: int = 0
    rescued: dict[str, int] | None = None


def _gaps(frame_seg: np.ndarray) -> list[list[int]]:
    """Untracked stretches ``[first, last]`` (inclusive frame indices)."""
    out, start = [], None
    for i, s in enumerate(frame_seg):
        if s < 0 and start is None:
            start = i
        elif s >= 0 and start is not None:
            out.append([start, i - 1])
            start = None
    if start is not None:
        out.append([start, len(frame_seg) - 1])
    return out


def frames_lost(frame_seg: np.ndarray, losses: Seq[tuple[int, str, str]], init_wait: int) -> dict[str, int]:
    """Untracked frames by :data:`LOSS_REASONS`: a stretch that starts at a loss counts as that loss's reason
    for its first ``init_wait + 1`` frames (the loss's own and those relocalisation was tried on), the rest
    and a stretch before the first segment as ``failed_init``."""
    why = {f: r for f, r, _ in losses}
    out = dict.fromkeys(LOSS_REASONS, 0)
    for a, b in _gaps(frame_seg):
        n = b - a + 1
        head = min(n, init_wait + 1) if a in why else 0
        if head:
            out[why[a]] += head
        out["failed_init"] += n - head
    return out


def build_result(m: Map, frames: Seq[FrameRef], frame_rel: dict[int, tuple[int, np.ndarray]],
                 frame_seg: np.ndarray, intr: Intrinsics, stats: RunStats, covisibility: bool = True,
                 units: dict[int, int] | None = None) -> VOResult:
    """Final keyframe poses, frame poses re-anchored on them, map points and covisibility.

    Args:
        m: the front end's map (keyframes, points, observations).
        frames: the sequence's frames (for their timestamps).
        frame_rel: tracked frame index → (reference keyframe, its ``T_kf,c``).
        frame_seg: ``(N,)`` tracking segment of every frame, -1 where untracked.
        intr: the sequence's (possibly distorted) intrinsics; the result is in their pinhole camera.
        stats: counters and timings of the run.
        covisibility: count the points each keyframe pair shares (``False``: an empty graph; a mid-run
            snapshot for a bridge or a BA does not read it).
        units: ``{segment: map unit}`` of the segments a bridge or a merge joined (:attr:`VOResult.units`).
    """
    kfs = [Keyframe(k, m.kf_frame[k], m.kf_time[k], m.kf_T_wc[k].copy(), m.kf_segment[k])
           for k in range(len(m.kf_frame))]
    idx = sorted(frame_rel)
    ts = np.array([frames[i].timestamp for i in idx])
    poses = np.stack([m.kf_T_wc[frame_rel[i][0]] @ frame_rel[i][1] for i in idx]) if idx else np.zeros((0, 4, 4))
    frame_seg = frame_seg.copy()
    n = len(m.host)
    obs_k = [np.array(sorted(m.obs[p]), np.int64) for p in range(n)]
    obs_px = [np.array([m.obs[p][k] for k in obs_k[p]], np.float64).reshape(-1, 2) for p in range(n)]
    pts = MapPoints(np.arange(n, dtype=np.int64), np.array(m.host, np.int64).reshape(-1),
                    np.array(m.px_h, np.float64).reshape(-1, 2), np.array(m.rho, np.float64).reshape(-1),
                    np.array(m.sigma, np.float64).reshape(-1), obs_k, obs_px)
    keep = (pts.inv_depth > 0) & np.isfinite(pts.inv_depth)  # removed points have NaN; ids stay the map's
    if not keep.all():
        pts = pts.subset(keep)
    covis: dict[int, dict[int, int]] = {k: {} for k in range(len(kfs))}
    for o in pts.observations if covisibility else ():
        for a, b in combinations(o.tolist(), 2):
            covis[a][b] = covis[a].get(b, 0) + 1
            covis[b][a] = covis[b].get(a, 0) + 1
    n_frames = len(frame_seg)
    ba_runs = stats.ba_stats
    total_s = stats.total_s
    timing = {k: 1000.0 * v / max(n_frames, 1) for k, v in stats.timing.items()}
    meta = {
        "mode": "svo",
        "n_reinit": max(len(stats.init_methods) - 1, 0),
        "segments": len(stats.init_methods),
        "relocalisations": [r.to_json() for r in stats.relocalisations],
        "reloc_rejected": stats.reloc_rejected,
        "losses": [{"frame": int(f), "reason": r, "why": w} for f, r, w in stats.losses],
        "frames_lost": frames_lost(frame_seg, stats.losses, stats.init_wait),
        "rescued": dict(stats.rescued or {}),
        "gaps": _gaps(frame_seg),
        "segment_starts": [{"segment": int(sg), "frame": int(i), "timestamp": float(frames[i].timestamp)}
                           for sg in sorted(set(frame_seg[frame_seg >= 0].tolist()))
                           for i in [int(np.flatnonzero(frame_seg == sg)[0])]],
        "init_methods": list(stats.init_methods),
        "timing": timing,
        "timing_unit": "ms per frame (mean over all frames)",
        "fps": n_frames / total_s if total_s > 0 else float("nan"),
        "time_s": total_s,
        "reprojected": stats.reprojected,
        "reused": stats.reused,
        "fused": stats.fused,
        "old_share": stats.old_share,
        "scale_check": stats.scale_check,
        "local_ba": {"runs": len(ba_runs),
                     "mean_points": float(np.mean([s["points"] for s in ba_runs])) if ba_runs else 0.0,
                     "mean_solve_ms": float(np.mean([s["solve_ms"] for s in ba_runs])) if ba_runs else 0.0,
                     "threaded": stats.ba_threaded},
    }
    return VOResult(kfs, pts, pinhole(intr), Trajectory(ts, poses), frame_seg, covis, meta, dict(units or {}))

"""The front-end stage of a run: :func:`start_stage` opens the front end the adaptation follows and computes the
front end on its own; :func:`run_stage` writes its outputs once the run has gone through the sequence.

Hindsight labels (and CoMoDa) run the front end to the end in :func:`start_stage`; causal labels step it on the
adaptation loop's clock (:mod:`~mutualslam_cli.vo.source`), so the network's depth can reach it, while the front end
on its own comes from the per-sequence journal cache. :func:`run_stage` writes ``traj_kf.txt``, ``traj_all.txt``,
``map_vo.ply`` and the ``vo.*`` keys, from the front end's own map with each segment in its own unit.
:func:`run_frontend` runs the front end alone to the end, through the per-sequence journal cache
(:mod:`~mutualslam_cli.vo.journal_cache`): what ``mslam ablate`` prepares for its jobs, and ``mslam fuse`` reads.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.assemble import LOSS_REASONS
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.slam import (
    esi_of_log_errors,
    evaluate_trajectory,
    map_log_depth_errors,
    point_units,
)
from mutualslam_cli.online.credit import front_end_alone, segment_starts
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.stages.ate_keys import set_ate
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.loop_recall import RELOC_KEYS, summarise_relocalisations
from mutualslam_cli.types import Progress
from mutualslam_cli.vo.faults import inject_outliers
from mutualslam_cli.vo.rescue import RESCUES
from mutualslam_cli.vo.source import FrontEndSource

log = logging.getLogger(__name__)


def run_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                 progress: Progress | None = None) -> tuple[VOResult, bool]:
    """The front end selected by ``cfg.vo.mode`` on its own, to the end (from the journal cache when it has it).

    Returns:
        ``(vo_result, from_cache)``: ``from_cache`` when every frame came from the cached journal.
    """
    source = FrontEndSource(seq, cfg, cache_dir, progress)
    try:
        source.run_all()
        return source.result(), source.replayed == len(seq)
    finally:
        source.close()


def load_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                  progress: Progress | None = None) -> tuple[VOResult, bool, np.ndarray]:
    """The front end on its own as a hindsight run uses it: :func:`run_frontend`, then ``vo.inject_outliers``.

    Returns:
        ``(vo, from_cache, injected)``: ``injected`` holds the ids of the corrupted map points.
    """
    vo, cached = run_frontend(seq, cfg, cache_dir, progress)
    vo, injected = inject_outliers(vo, cfg.vo.inject_outliers, cfg.seed)
    return vo, cached, injected


@dataclass
class FrontEndRun:
    """The front end as the adaptation stage gets it (:func:`start_stage`).

    Attributes:
        source: the event source Algorithm 1 follows (causal: live, not yet advanced; else at its end). Whoever
            adapts closes it.
        alone: the front end on its own (no bridge, no BA), each segment in its own unit: Table 4's "vo" column.
        starts: frames where ``alone``'s segments start (where the "bridged" credit plans its bridges).
        injected: ids of map points corrupted by ``vo.inject_outliers`` (hindsight only).
        started: :func:`time.perf_counter` when the stage began; alone_s: seconds spent on ``alone`` apart from
            ``source`` (causal runs).
    """

    source: FrontEndSource
    alone: VOResult
    starts: set[int]
    injected: np.ndarray
    started: float
    alone_s: float


def start_stage(run: RunContext) -> FrontEndRun:
    """The front end for the adaptation: its source (causal labels: live, the network may reach it; hindsight and
    ``comoda``: run to the end first, ``vo.inject_outliers`` applied) and the front end on its own."""
    seq, cfg = run.seq, run.cfg
    t = time.perf_counter()
    causal = cfg.adapt.labels == "causal" and cfg.adapt.scheme != "comoda"
    source = FrontEndSource(seq, cfg, run.cache / "vo", run.progress, live_feedback=causal)
    try:
        injected = np.zeros(0, np.int64)
        if not causal:  # hindsight (or comoda): the front end on its own, to the end, first
            source.run_all()
            if cfg.vo.inject_outliers:  # the test knob corrupts the finished map (hindsight only)
                injected = source.inject_outliers(cfg.vo.inject_outliers, cfg.seed)
            return FrontEndRun(source, source.result(), segment_starts(source.state), injected, t, 0.0)
        # causal: the front end on its own from the journal cache, which it fills
        alone, starts = front_end_alone(seq, cfg, run.cache / "vo")
        return FrontEndRun(source, alone, starts, injected, t, time.perf_counter() - t)
    except BaseException:
        source.close()
        raise


@dataclass
class FrontEnd:
    """What the front-end stage hands on.

    Attributes:
        vo: the front end's map, each segment in its own unit (with the injected outliers, if any).
        cached: every frame came from the journal cache; replayed: frames that did.
        injected: ids of map points corrupted by ``vo.inject_outliers``.
        map_errors: ``(P,)`` log-depth error of each map point in its host keyframe against GT
            (:func:`~mutualslam_cli.metrics.slam.map_log_depth_errors`; NaN without GT).
        points_with_gt: map points with GT depth at their host pixel.
    """

    vo: VOResult
    cached: bool
    injected: np.ndarray
    map_errors: np.ndarray
    points_with_gt: int
    replayed: int = 0


def run_stage(run: RunContext, fe: FrontEndRun) -> FrontEnd:
    """The front end's outputs, once the adaptation has taken its source to the end: ``traj_kf.txt``,
    ``traj_all.txt``, ``map_vo.ply`` and the keys ``vo.*``, ``timing.vo_fps``, ``map.points.vo``, ``map.esi.vo``
    (each segment in its own unit) and ``trajectory.ate_rmse_m.{vo,all_frames}``, of the front end on its own."""
    seq, cfg, summary = run.seq, run.cfg, run.summary
    vo, replayed, injected = fe.alone, fe.source.replayed, fe.injected
    write_trajectories(run.folder, vo.traj_kf, vo.traj_all)
    err = map_log_depth_errors(seq, vo)  # per point log z − log z*: the map's colours and its e_si
    write_ply(run.folder / "map_vo.ply", vo.points_world(), err)
    esi, n_gt = esi_of_log_errors(err, point_units(vo))  # each segment's own unit
    mode = cfg.vo.mode
    summary.set("vo.keyframes", len(vo.keyframes))
    summary.set("vo.tracked_fraction", vo.tracked_fraction)
    if mode != "svo":
        summary.absent("timing.vo_fps", f"oracle front end (--vo {mode}): no tracking to time")
    else:
        vo_time_s = float(vo.meta.get("time_s", run.timings.get("frontend", 0.0)))
        summary.set("timing.vo_fps", len(seq) / vo_time_s if vo_time_s > 0 else None)
    summary.set("map.points.vo", len(vo.points))
    set_ate(summary, evaluate_trajectory(seq, vo, cfg.eval.ate_max_dt), {"kf": "vo", "all": "all_frames"})
    if mode != "svo":
        summary.notes["trajectory.ate_rmse_m.vo"] = "oracle front end: keyframe poses are GT poses"
    summary.set("map.esi.vo", esi, "no map point has GT depth at its host pixel")
    summary.set("vo.segments", len({k.segment for k in vo.keyframes}))
    if mode == "svo":
        summary.set("vo.relocalisations", len(vo.meta.get("relocalisations", [])))
        summary.set("vo.relocalisations_rejected", int(vo.meta.get("reloc_rejected", 0)))
        summarise_relocalisations(summary, seq, vo, cfg.eval.ate_max_dt)
        summary.set("vo.losses", len(vo.meta.get("losses", [])))
        for reason, n in vo.meta.get("frames_lost", {}).items():
            summary.set(f"vo.frames_lost.{reason}", int(n))
        for how in RESCUES:
            summary.set(f"vo.rescued.{how}", int(vo.meta.get("rescued", {}).get(how, 0)))
        summary.set("vo.points_reused", int(vo.meta.get("reused", 0)))
        summary.set("vo.points_fused", int(vo.meta.get("fused", 0)))
        share = vo.meta.get("old_share")
        summary.set("vo.old_share", None if share is None else 100.0 * float(share), "no frame tracked a map point")
    else:
        for key in ("vo.relocalisations", "vo.relocalisations_rejected", "vo.points_reused", "vo.points_fused",
                    "vo.old_share", *RELOC_KEYS, "vo.losses", *(f"vo.frames_lost.{r}" for r in LOSS_REASONS),
                    *(f"vo.rescued.{h}" for h in RESCUES)):
            summary.absent(key, f"oracle front end (--vo {mode}): GT poses, nothing to relocalise")
    summary.set("vo.from_cache", replayed == len(seq))
    summary.set("vo.frames_from_cache", replayed)
    summary.set("vo.mode", mode)
    return FrontEnd(vo, replayed == len(seq), injected, err, n_gt, replayed)


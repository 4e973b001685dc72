"""The adaptation stage's summary keys: Algorithm 1's validations (``adaptation.l_val.*``), the bridges
(``vo.bridges``, ``trajectory.*.bridged``), the merges (``vo.merges``) and loops (``loop.*``) of the back end it
drove, the regulariser's strength (``adaptation.reg.*``) and the fine-tuning's cost (``timing.finetune_*``,
``adaptation.steps``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.adapt.step_info import StepLog
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.backend.bridges import Bridge
from mutualslam_cli.backend.loop_closer import LoopCloser
from mutualslam_cli.backend.merge import SegmentMerger
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.slam import evaluate_trajectory
from mutualslam_cli.online.rows import KeyframeRow
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.ate_keys import set_ate
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.loop_recall import POSE_KEYS, RECALL_KEYS

#: The keys of :func:`l_val_stats` (``adaptation.l_val.*`` in ``summary.json``).
L_VAL_KEYS = ("validations", "min", "median", "longest_below_tau", "map_median_depth")


def l_val_stats(rows: list[KeyframeRow], tau: float, vo: VOResult) -> dict[str, float | None]:
    """Algorithm 1's validations from the keyframe rows: ``validations`` (with an L_val), ``min``,
    ``median`` (L_val, Eq. 9, inverse map units), ``longest_below_tau`` (most consecutive ones below τ)
    and ``map_median_depth`` (median depth of the map points in their hosts, map units). The front end
    sets the median depth of its first map to 1, as SVO does, so τ means here what it means in the
    paper as long as that unit holds; ``L_val × map_median_depth`` is the scale-free form."""
    vals = [float(r.info.l_val) for r in rows if r.info is not None and r.is_validation and r.info.l_val is not None
            and np.isfinite(float(r.info.l_val))]
    run = best = 0
    for v in vals:
        run = run + 1 if v < tau else 0
        best = max(best, run)
    depth = float(np.median(1.0 / vo.points.inv_depth)) if len(vo.points) else None
    return {"validations": len(vals), "min": min(vals) if vals else None,
            "median": float(np.median(vals)) if vals else None, "longest_below_tau": best,
            "map_median_depth": depth}


def summarise_bridges(run: RunContext, joined: VOResult, bridges: list[Bridge] | None,
                      credit: list[Bridge] | None = None) -> None:
    """``vo.bridges`` and, when a segment was bridged, ``traj_{kf,all}_bridged.txt`` and
    ``trajectory.ate_rmse_m.bridged`` / ``all_frames_bridged``: the front end on its own joined by bridges
    planned on its own map and nothing else (no BA: Table 4 credits each part; :mod:`~mutualslam_cli.online.credit`),
    one Sim(3) as every headline ATE. ``bridges``: the bridges the run made, ``None`` when no keyframe loop ran
    (scheme ``comoda``); ``credit``: the front end's own (``vo.bridges_credit`` counts those joined)."""
    keys = [f"trajectory.{group}.{leaf}" for group in ("ate_rmse_m", "ate_rmse_m_per_segment")
            for leaf in ("bridged", "all_frames_bridged")]
    if bridges is None:
        why = "scheme 'comoda' does not run the keyframe loop that bridges segments"
        for key in ("vo.bridges", "vo.bridges_credit", *keys):
            run.summary.absent(key, why)
        return
    run.summary.set("vo.bridges", len(bridges))
    run.summary.set("vo.bridges_credit", sum(not b.refused for b in credit or []))
    if not any(not b.refused for b in credit or []):
        why = ("no segment to bridge" if len({k.segment for k in joined.keyframes}) < 2 else
               "no bridge could be made (vo.bridge_segments=false, or no depth ratio on a side of a gap)")
        for key in keys:
            run.summary.absent(key, why)
        return
    write_trajectories(run.folder, joined.traj_kf, joined.traj_all, suffix="_bridged")
    set_ate(run.summary, evaluate_trajectory(run.seq, joined, run.cfg.eval.ate_max_dt),
            {"kf": "bridged", "all": "all_frames_bridged"})


#: The keys of :func:`summarise_strength` (``adaptation.reg.*``).
STRENGTH_KEYS = ("shrink.mean", "shrink.median", "importance.mean")


def summarise_strength(summary: Summary, adapter: OnlineAdapter | None) -> None:
    """``adaptation.reg.shrink.{mean,median}``: the share of each batch's Adam displacement the
    regulariser's proximal step took back, over every step (0: inert, 1: frozen;
    :mod:`~mutualslam_cli.adapt.regularizers`), and ``adaptation.reg.importance.mean``: the mean of
    ``c·w`` over the parameters at the end (the penalty's curvature per unit of squared displacement)."""
    reg = adapter.regularizer if adapter is not None else None
    if reg is None:
        for k in STRENGTH_KEYS:
            summary.absent(f"adaptation.reg.{k}", "the scheme has no regulariser")
        return
    why = ("adapt.reg_mode = 'penalty': the penalty enters Adam's gradient, there is no proximal step"
           if reg.mode == "penalty" else "no proximal step was taken")
    shrink = np.asarray(reg.shrinks, dtype=float)
    summary.set("adaptation.reg.shrink.mean", float(shrink.mean()) if shrink.size else None, why)
    summary.set("adaptation.reg.shrink.median", float(np.median(shrink)) if shrink.size else None, why)
    n = sum(w.numel() for w in reg.weights)
    summary.set("adaptation.reg.importance.mean",
                reg.coef * float(sum(float(w.sum()) for w in reg.weights)) / n if n else None,
                "the network has no trainable parameter")


def summarise_finetuning(summary: Summary, scheme: str, adapter: OnlineAdapter | None,
                         kf_rows: list[KeyframeRow]) -> None:
    """``timing.finetune_ms`` (median per optimiser step), ``timing.finetune_kf_ms`` (per keyframe, the steps
    included) and of it ``timing.finetune_batch_ms`` (assembling the batch) and ``timing.finetune_consolidate_ms``
    (the regulariser's end of batch: EWC's per-keyframe Fisher, MAS's importance), their sums over the run
    ``timing.finetune_steps_s`` and ``timing.finetune_consolidate_s`` and ``timing.consolidate_vs_step`` (median
    consolidation per median step), ``timing.l_val_s`` (Algorithm 1's validations), ``adaptation.keyframes_trained``,
    ``adaptation.steps`` and, for scheme ``luo``, ``adaptation.luo_keyframes_with_partner`` (training keyframes
    that found a simulated stereo partner)."""
    why = "scheme 'none': no fine-tuning" if scheme == "none" else "no keyframe was trained on"
    for key, ms in (("finetune_ms", "step_ms"), ("finetune_kf_ms", "finetune_ms"), ("finetune_batch_ms", "batch_ms"),
                    ("finetune_consolidate_ms", "consolidate_ms")):
        values = getattr(adapter, ms) if adapter is not None else []
        summary.set(f"timing.{key}", float(np.median(values)) if values else None, why)
    # the run's cost in optimiser steps and what the regulariser's consolidation adds (DESIGN §10: a run costs
    # its steps + at most 25 %); consolidate_vs_step: median consolidation (EWC's Fisher) per median step
    for key, ms in (("finetune_steps_s", "step_ms"), ("finetune_consolidate_s", "consolidate_ms")):
        values = getattr(adapter, ms) if adapter is not None else []
        summary.set(f"timing.{key}", float(np.sum(values)) / 1000.0 if values else None, why)
    # a validation tick is its L_val
    val = [float(r.info.ms or 0.0) for r in kf_rows if r.info is not None and r.is_validation]
    summary.set("timing.l_val_s", sum(val) / 1000.0 if val else None, "no validation keyframe")
    steps, cons = (getattr(adapter, k) if adapter is not None else [] for k in ("step_ms", "consolidate_ms"))
    summary.set("timing.consolidate_vs_step", float(np.median(cons) / np.median(steps)) if steps and cons else None,
                why)
    summary.set("adaptation.keyframes_trained", sum(r.trained for r in kf_rows))
    summary.set("adaptation.steps", int(sum(r.n_steps for r in kf_rows)))
    if scheme == "luo":
        training = [r for r in kf_rows if not r.is_validation]
        summary.set("adaptation.luo_keyframes_with_partner", sum(r.info is not None and bool(r.info.sources)
                                                                 for r in training))
        summary.set("adaptation.training_keyframes", len(training))


def summarise_merges(summary: Summary, merger: SegmentMerger) -> None:
    """``vo.merges`` and ``vo.merge_queries``; each merge in ``notes``."""
    summary.set("vo.merges", len(merger.merges))
    summary.set("vo.merge_queries", merger.tried)
    if merger.merges:
        summary.notes["vo.merges"] = "; ".join(
            f"segment {g.segment} onto {g.onto} at keyframe {g.query} (scale {g.loop.scale:.3f}, "
            f"{g.loop.inliers} inliers)" for g in merger.merges)


def summarise_loops(summary: Summary, closer: LoopCloser) -> None:
    """``loop.{candidates,accepted,rejected}``; the rejections by reason in ``notes``."""
    d = closer.detector
    summary.set("loop.candidates", d.tried)
    summary.set("loop.accepted", len(closer.loops))
    summary.set("loop.rejected", int(sum(d.rejected.values())))
    if d.rejected:
        summary.notes["loop.rejected"] = "; ".join(f"{why}: {n}" for why, n in sorted(d.rejected.items()))


def summarise_no_loops(summary: Summary, why: str) -> None:
    """The ``loop.*`` keys of a run without loop closure (``loop.recall.*`` too), null with ``why``."""
    for k in ("loop.candidates", "loop.accepted", "loop.rejected", *RECALL_KEYS, *POSE_KEYS):
        summary.absent(k, why)


def summarise_live_reuse(summary: Summary, live: VOResult, mode: str) -> None:
    """``vo.live.{points_reused,points_fused,old_share}``: map reuse by the run's front end — the one the back end
    handed its loops, merges and BAs to (the ``vo.*`` keys are the front end's on its own) — and
    ``vo.live.map_units``: the map units its segments ended in (1: one map; a bridge or a merge joins two)."""
    keys = ("points_reused", "points_fused", "old_share", "map_units")
    if mode != "svo" or not live.meta:
        for k in keys:
            summary.absent(f"vo.live.{k}", f"oracle front end (--vo {mode}) or no live front end (hindsight labels)")
        return
    share = live.meta.get("old_share")
    summary.set("vo.live.points_reused", int(live.meta.get("reused", 0)))
    summary.set("vo.live.points_fused", int(live.meta.get("fused", 0)))
    summary.set("vo.live.old_share", None if share is None else 100.0 * float(share), "no frame tracked a map point")
    summary.set("vo.live.map_units", len(set(live.unit_of_segment().values())))


#: ``timing.step_ms.*``: the distribution of the optimiser steps' wall times (:meth:`StepLog.stats`).
STEP_STATS = ("median", "p90", "p99", "max")


def summarise_steps(run: RunContext, steps: StepLog | None, scheme: str) -> None:
    """``steps.csv`` (one row per optimiser step: its keyframe, ms, batch and the work done since the step before;
    :class:`~mutualslam_cli.adapt.step_info.StepLog`) and the keys ``timing.step_ms.{median,p90,p99,max}`` and
    ``timing.steps_over_median`` (the steps' sum over steps × median: 1.0 without a stall)."""
    stats = steps.stats() if steps is not None else {}
    why = ("scheme 'comoda' updates per frame (frames.csv)" if scheme == "comoda" else
           "no optimiser step" if steps is not None else f"scheme {scheme!r} does not train")
    for k in STEP_STATS:
        run.summary.set(f"timing.step_ms.{k}", stats.get(k), why)
    run.summary.set("timing.steps_over_median", stats.get("sum_over_median"), why)
    if steps is not None and steps.steps:
        atomic_write_text(run.folder / "steps.csv", pd.DataFrame(steps.rows()).to_csv(index=False))

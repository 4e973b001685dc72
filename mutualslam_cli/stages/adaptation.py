"""The adaptation stage of a run, one function per method: :func:`run_algorithm1` (Algorithm 1 over the front
end's events, :class:`~mutualslam_cli.online.loop.OnlineLoop`, module :mod:`mutualslam_cli.online`) or
:func:`run_comoda` (every frame through the CoMoDa-style adapter, :mod:`~mutualslam_cli.stages.comoda`); then
:func:`finish_stage` writes what both write (``keyframes.csv``, the bridged credit, the stage times). Each hands on
:class:`Adapted`.
"""

from __future__ import annotations

import copy
import time
from contextlib import closing
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.backend.bridges import Bridge
from mutualslam_cli.backend.records import LoopRecord, MergeRecord
from mutualslam_cli.backend.refine import MapBA
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.online.credit import WeightsAt, credit_bridges
from mutualslam_cli.online.loop import OnlineLoop
from mutualslam_cli.online.rows import KeyframeRow, keyframes_table
from mutualslam_cli.online.scores import OnlineScorer, eval_frames
from mutualslam_cli.stages import comoda, loop_recall
from mutualslam_cli.stages.adaptation_summary import (
    L_VAL_KEYS,
    l_val_stats,
    summarise_bridges,
    summarise_finetuning,
    summarise_live_reuse,
    summarise_loops,
    summarise_merges,
    summarise_no_loops,
    summarise_steps,
    summarise_strength,
)
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.frontend import FrontEndRun
from mutualslam_cli.vo.source import FrontEndSource


@dataclass
class Adapted:
    """What the adaptation stage hands on.

    Attributes:
        net: the final network (for scheme ``none`` the pre-trained one, unchanged).
        adapter: the keyframe adapter (its replay buffer and L_val per keyframe), ``None`` for
            schemes ``none`` and ``comoda``.
        map: the loop's map at the end (bridged segments; the BAs Algorithm 1 requested in it).
        frontend: the front end on its own — no bridge, no BA: each segment in its own unit (the cache's;
            causal runs ask it before the loop, since the network's side changes theirs).
        bridged: ``frontend`` joined by bridges planned on its own map, and nothing else (Table 4's "bridged"
            column: :mod:`~mutualslam_cli.online.credit`).
        source: the front end's event source (cache use, replayed frames).
        injected: ids of map points corrupted by ``vo.inject_outliers``.
        requested: how many times Algorithm 1 requested global BA.
        bridges: one record per bridge made (:class:`~mutualslam_cli.backend.bridges.Bridge`); refused: per bridge
            refused; loops: per loop closed (:mod:`~mutualslam_cli.backend.loop_closer`); credit: the bridges of
            ``bridged``, planned on ``frontend``'s own map.
        l_val: Algorithm 1's validations against τ (:func:`l_val_stats`; empty without the loop).
        online: the ``online_*`` per-frame scores of the model of each frame's time
            (:mod:`~mutualslam_cli.online.scores`); ``None`` when not computed.
        keyframe_rows: one ``keyframes.csv`` row per keyframe (empty for ``comoda``).
        frontend_s: seconds of front-end work done after the loop (the bridged credit); online_s: of the online
            scores (refresh_s of it: new weights into the OpenVINO predictor).
    """

    net: DepthNet
    adapter: OnlineAdapter | None
    map: VOResult
    frontend: VOResult
    bridged: VOResult | None
    source: FrontEndSource
    injected: np.ndarray
    requested: int
    bridges: list[Bridge] | None = None
    refused: list[Bridge] = field(default_factory=list)
    loops: list[LoopRecord] = field(default_factory=list)
    merges: list[MergeRecord] = field(default_factory=list)
    credit: list[Bridge] = field(default_factory=list)
    l_val: dict[str, float | None] = field(default_factory=dict)
    online: pd.DataFrame | None = None
    keyframe_rows: list[KeyframeRow] = field(default_factory=list)
    frontend_s: float = 0.0
    online_s: float = 0.0
    refresh_s: float = 0.0

    def why_no_request(self, tau: float, patience: int) -> str:
        """Why Algorithm 1 never requested global BA, in its terms (L_val vs τ over ``patience`` validations)."""
        v = self.l_val
        if not v.get("validations"):
            return "Algorithm 1 never validated (no validation keyframe with sparse points)"
        return (f"Algorithm 1 never requested global BA: L_val < τ = {tau:g} in {v['longest_below_tau']} "
                f"validation(s) in a row at most, {patience} needed (min L_val {v['min']:.3g} over "
                f"{v['validations']} validations)")


def run_algorithm1(run: RunContext, fe: FrontEndRun, net0: DepthNet, fast: bool, ba: MapBA | None = None) -> Adapted:
    """Algorithm 1 over the front end's events: a copy of ``net0`` adapted keyframe by keyframe
    (:class:`~mutualslam_cli.online.loop.OnlineLoop`; causal labels drive the front end live), with culling + global
    BA at its requests (``ba``), then the front end alone joined by bridges planned on its own map (Table 4's
    "bridged" credit). Writes the keys ``adaptation.*``, ``vo.bridges_refused``, ``vo.merges``, ``loop.*``,
    ``timing.finetune_*``; closes the front end's source."""
    cfg, summary, seq = run.cfg, run.summary, run.seq
    source = fe.source
    with closing(source):  # the journal cache is complete once the source closes: the credit below reads it
        scorer = (OnlineScorer(seq, eval_frames(seq, cfg.eval.stride), cfg, fast)
                  if cfg.eval.online and seq.has_depth and cfg.adapt.scheme != "none" else None)
        loop = OnlineLoop(run, source, copy.deepcopy(net0), fast, ba, scorer)
        loop.weights_at = WeightsAt(fe.starts if cfg.vo.bridge_segments else set())
        loop.run_loop()
        final = source.result()
        summarise_live_reuse(summary, final, cfg.vo.mode)
        rows, adapter, kf_rows = loop.rows, loop.adapter, loop.keyframe_rows()
        last = loop.trained_kf if loop.clock is not None else final.keyframes[-1].id if final.keyframes else -1
        online = scorer.finish(loop.net, last) if scorer else None
        shared = scorer.eval_predictor(loop.net) if scorer else None
        if shared is not None:  # the evaluation's OpenVINO predictor: the scorer's, not a second conversion
            run.predictors[("adapted", id(loop.net))] = shared
        adapted = Adapted(net=loop.net, adapter=adapter, map=final, frontend=fe.alone, bridged=None, source=source,
                          injected=fe.injected, requested=sum(r.run_global_ba for r in rows), bridges=loop.bridges,
                          refused=loop.refused, l_val=l_val_stats(rows, cfg.adapt.tau_val, final), online=online,
                          keyframe_rows=kf_rows)
        adapted.online_s = scorer.seconds if scorer is not None else 0.0
        adapted.refresh_s = scorer.refresh_seconds if scorer is not None else 0.0
        summary.set("vo.bridges_refused", len(loop.refused))
        summary.set("adaptation.keyframes_other_unit", len(loop.other_unit))
        if loop.refused:
            summary.notes["vo.bridges_refused"] = "; ".join(f"segment {b.segment}: {b.refused}" for b in loop.refused)
        for k, v in adapted.l_val.items():
            summary.set(f"adaptation.l_val.{k}", v, "no validation keyframe had an L_val")
        if loop.merger is not None:
            summarise_merges(summary, loop.merger)
            adapted.merges = loop.merger.merges
        else:
            for key in ("vo.merges", "vo.merge_queries"):
                summary.absent(key, "vo.merge_segments=false or an oracle front end")
        if loop.closer is not None:
            summarise_loops(summary, loop.closer)
            adapted.loops = loop.closer.loops
            loop_recall.run_stage(run, loop.closer, final)  # against GT, after the run
        else:
            summarise_no_loops(summary, "loop.enabled=false (the paper: no loop closure)")
        summarise_finetuning(summary, cfg.adapt.scheme, adapter, rows)
        summarise_strength(summary, adapter)
        for key in (comoda.POSENET_ATE_KEY, comoda.POSE_NETWORK_KEY):
            summary.absent(key, f"scheme {cfg.adapt.scheme!r} has no pose network (only 'comoda')")
    t_credit = time.perf_counter()  # the front end alone joined by bridges planned on its own map (Table 4)
    adapted.bridged, adapted.credit = credit_bridges(seq, cfg, run.cache / "vo", loop.net, fast, loop.weights_at)
    adapted.frontend_s = time.perf_counter() - t_credit
    return adapted


def run_comoda(run: RunContext, fe: FrontEndRun, net0: DepthNet, fast: bool) -> Adapted:
    """The CoMoDa-style baseline: a copy of ``net0`` adapted on every frame with its own pose network, no
    keyframes (:mod:`~mutualslam_cli.stages.comoda`); the front end alone is its map. Closes the front end's
    source."""
    summary = run.summary
    with closing(fe.source):
        net = comoda.run_stage(run, copy.deepcopy(net0), fast)
        for k in L_VAL_KEYS:
            summary.absent(f"adaptation.l_val.{k}", "scheme 'comoda' has no Algorithm 1")
        summarise_strength(summary, None)
    return Adapted(net=net, adapter=None, map=fe.alone, frontend=fe.alone, bridged=fe.alone, source=fe.source,
                   injected=fe.injected, requested=0)


def finish_stage(run: RunContext, fe: FrontEndRun, adapted: Adapted) -> None:
    """What both adaptations write: ``keyframes.csv``, ``vo.bridges``/the bridged ATE, ``vo.scale_check.*``,
    ``adaptation.labels``, ``timing.online_*``; and the time since the front end started, booked by stage — the
    BAs Algorithm 1 triggered to ``ba``, the front end's (its source, the front end alone, the bridged credit) to
    ``frontend``, the online scores to ``evaluation``, the rest to ``adaptation``."""
    cfg, summary = run.cfg, run.summary
    fe_s = fe.source.seconds + fe.alone_s + adapted.frontend_s
    # Algorithm 1's BAs inside the loop, on every keyframe (also the loop closures' of keyframes it did not tick)
    ba_s = float(sum(r.seconds.get("ba_s", 0.0) for r in adapted.keyframe_rows))
    run.add_time("frontend", fe_s)
    run.add_time("adaptation", time.perf_counter() - fe.started - ba_s - adapted.online_s - fe_s)
    run.add_time("ba", ba_s)
    run.add_time("evaluation", adapted.online_s)  # the online scores are evaluation, done inside the loop
    summary.set("timing.online_scoring_s", adapted.online_s or None,
                "no online scores (eval.online false, scheme none or comoda, or no GT depth)")
    summary.set("timing.online_refresh_s", adapted.refresh_s or None,  # of it: new weights into OpenVINO
                "no online scores through OpenVINO (the torch path, eval.online false, or no GT depth)")
    if adapted.keyframe_rows:
        atomic_write_text(run.folder / "keyframes.csv", keyframes_table(adapted.keyframe_rows).to_csv(index=False))
    summarise_steps(run, adapted.adapter.step_log if adapted.adapter is not None else None, cfg.adapt.scheme)
    assert adapted.bridged is not None  # comoda: the front end's own map; else run_algorithm1's credit
    summarise_bridges(run, adapted.bridged, adapted.bridges, adapted.credit)
    check = adapted.map.meta.get("scale_check") if adapted.map is not None else None
    for k in ("checks", "drift_max", "drift_min"):  # the network's view of the map's scale, keyframe by keyframe
        summary.set(f"vo.scale_check.{k}", check.get(k) if check else None,
                    "the front end did not ask the network (vo.depth_seeds and vo.scale_prior off, or not causal)")
    # what the labels could know: an oracle front end re-triangulates with later observations, whatever the mode
    labels = "oracle" if cfg.vo.mode != "svo" else cfg.adapt.labels if cfg.adapt.scheme != "comoda" else "hindsight"
    summary.set("adaptation.labels", labels)

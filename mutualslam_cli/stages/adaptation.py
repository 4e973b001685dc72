"""The adaptation stage of a run (:func:`run_stage`): the front end's keyframes through Algorithm 1
(DESIGN §1, §5), or every frame through the CoMoDa-style adapter (:mod:`~mutualslam_cli.stages.comoda`).

With a ``global_ba`` step this is the *mutual* loop (paper §III-A, §III-C): when Algorithm 1
requests global BA after keyframe t, the step culls and refines the map of keyframes ≤ t with the
current network, and the refined keyframe poses and sparse depths replace those of every stored
keyframe (:meth:`~mutualslam_cli.adapt.online.OnlineAdapter.update_poses`,
:meth:`~mutualslam_cli.adapt.online.OnlineAdapter.update_sparse`), so later batches' sparse loss
and photometric warps use them. Keyframes arriving later are read from the refined map, whose
later poses followed the correction (:func:`mutualslam_cli.ba.global_ba.run_global_ba`).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample
from mutualslam_cli.adapt.depthnet import predict_depth, prepare
from mutualslam_cli.adapt.inputs import keyframe_images, scale_pixels
from mutualslam_cli.adapt.online import OnlineAdapter, StepInfo
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages import comoda
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.online_eval import OnlineScorer, eval_frames
from mutualslam_cli.stages.frontend import FrontEnd
from mutualslam_cli.stages.slam_metrics import evaluate_trajectory, set_ate
from mutualslam_cli.types import Progress
from mutualslam_cli.vo.result import Keyframe, VOResult
from mutualslam_cli.vo.segments import bridge_segment

DepthOf = Callable[[int], np.ndarray]
"""``depth_of(kf_id)``: ``(h, w)`` depth of the current network at network resolution, map units."""

GlobalBA = Callable[[VOResult, int, DepthOf, Mapping[int, float]], VOResult]
"""``global_ba(vo, kf_id, depth_of, val_loss) -> vo'``: culling + global BA of keyframes ≤ ``kf_id``
of the loop's map ``vo`` with the current network (``val_loss``: L_val per stored keyframe);
returns the loop's new map (culled points dropped, later keyframes following the correction)."""


def depth_predictor(net: torch.nn.Module, load: Callable[[int], torch.Tensor], fast: bool,
                    buffer: KeyframeBuffer | None = None) -> DepthOf:
    """:data:`DepthOf` of ``net`` for keyframe images from ``buffer`` when stored, else ``load(kf_id)``."""

    def depth_of(kf_id: int) -> np.ndarray:
        img = buffer.get(kf_id).image if buffer is not None and kf_id in buffer else load(kf_id)
        return predict_depth(net, img[None], fast)[0]

    return depth_of


def run_adaptation(seq: Sequence, vo: VOResult, net: torch.nn.Module, cfg: RunConfig, fast: bool,
                   progress: Progress | None = None, global_ba: GlobalBA | None = None,
                   scorer: OnlineScorer | None = None,
                   ) -> tuple[torch.nn.Module, list[dict[str, Any]], OnlineAdapter | None, VOResult]:
    """Feed the keyframes, in order, through Algorithm 1 with the configured scheme.

    Each keyframe is given at network resolution (``cfg.net.width × height``, undistorted) with
    the map points it observes as sparse depth (map units), from the loop's current map.

    Args:
        global_ba: run when Algorithm 1 requests global BA (module docstring); ``None``: the
            request is only recorded (``run_global_ba`` column).
        scorer: scores the frames before each keyframe with the network of their time
            (:mod:`~mutualslam_cli.stages.online_eval`); the caller finishes it.

    A keyframe that starts a new tracking segment first joins it to the map before it, in its
    unit, with the current network's depth (``vo.bridge_segments``, :mod:`~mutualslam_cli.vo.segments`).

    Returns:
        ``(adapted_net, per_keyframe_rows, adapter, map)``: ``map`` is the loop's map at the end
        (``vo`` itself unless a bridge or a BA moved it; ``meta["bridges"]`` lists the bridges);
        rows of BA keyframes have ``ba_s`` (seconds of the trigger: L_val, culling, BA, feedback).
        For scheme ``none`` the network is returned unchanged with no rows and ``adapter`` is ``None``.
    """
    w, h = cfg.net.width, cfg.net.height
    K_net = torch.from_numpy(vo.intrinsics.scaled(w, h).K()).float()
    net = prepare(net, fast)
    load = keyframe_images(seq, vo, w, h)
    held = [vo, vo.points_world()]  # the loop's map and its world points; a BA or a bridge replaces both
    bridges: list[dict[str, Any]] = []
    seen: set[int] = set()

    def bridge(kf: Keyframe, depth_of: DepthOf) -> None:
        """Join a new segment to the map before it, at the first keyframe of the segment."""
        if seen and kf.segment not in seen and cfg.vo.bridge_segments:
            out = bridge_segment(held[0], kf.id, depth_of, seq.load_gray, seq.intrinsics, held[1])
            if out is not None:
                held[:] = [out[0], out[0].points_world()]
                bridges.append(vars(out[1]))
        seen.add(kf.segment)

    if cfg.adapt.scheme == "none":  # no training, but the unit still crosses the gaps (pre-trained depth)
        for kf in vo.keyframes:
            bridge(kf, depth_predictor(net, load, fast))
        return net, [], None, _with_bridges(held[0], bridges)
    ba_s: dict[int, float] = {}

    def sparse(kf_id: int) -> tuple[torch.Tensor, torch.Tensor]:
        uv, d = held[0].sparse_depth(kf_id, held[1])
        return torch.from_numpy(scale_pixels(uv, vo.intrinsics, w, h)).float(), torch.from_numpy(d).float()

    def on_global_ba(info: StepInfo) -> None:
        assert global_ba is not None
        t = time.perf_counter()
        first = max(0, info.kf_id - cfg.ba.window + 1) if cfg.ba.window else 0  # the keyframes the BA refines
        ids = [k.id for k in held[0].keyframes[first:info.kf_id + 1]]
        new = global_ba(held[0], info.kf_id, depth_predictor(adapter.net, load, fast, adapter.buffer),
                        adapter.per_keyframe_val_loss(ids))
        held[:] = [new, new.points_world()]
        adapter.update_poses({k: new.keyframes[k].pose for k in ids})
        adapter.update_sparse({k: sparse(k) for k in ids})
        ba_s[info.kf_id] = time.perf_counter() - t

    adapter = OnlineAdapter(net, cfg.adapt, K_net, seed=cfg.seed, fast=fast,
                            on_global_ba=on_global_ba if global_ba is not None else None,
                            val_scope=cfg.adapt.val_scope, reg_mode=cfg.adapt.reg_mode)
    rows = []
    t0 = time.perf_counter()
    budget = realtime_steps(seq, vo, cfg) if cfg.adapt.schedule == "realtime" else None
    for kf in vo.keyframes:
        bridge(kf, depth_predictor(adapter.net, load, fast, adapter.buffer))
        uv, d = sparse(kf.id)
        sample = KeyframeSample(kf_id=kf.id, image=load(kf.id), K=K_net, pose=held[0].keyframes[kf.id].pose,
                                uv=uv, depth=d, segment=kf.segment)
        if scorer is not None:  # frames before this keyframe: the model after the previous one
            scorer.score_until(adapter.net, kf.frame_index, kf.id - 1)
        row = step_row(adapter.add_keyframe(sample, None if budget is None else budget[kf.id]))
        row["n_sparse"] = len(d)
        if kf.id in ba_s:
            row["ba_s"] = ba_s[kf.id]
        rows.append(row)
        if progress:
            progress("adapt", {"done": kf.id + 1, "total": len(vo.keyframes), **row,
                               "elapsed_s": time.perf_counter() - t0})
    return adapter.net, rows, adapter, _with_bridges(held[0], bridges)


def realtime_steps(seq: Sequence, vo: VOResult, cfg: RunConfig) -> list[int]:
    """Steps per keyframe of ``adapt.schedule = realtime``: ``⌊Δt / step_cost⌋`` capped at ``max_steps``, Δt the
    sequence time from the keyframe to the next one (the last: to the sequence's last frame). The paper's
    fine-tuning runs beside the SLAM thread, so a keyframe is trained on until the next one arrives."""
    a = cfg.adapt
    times = [seq.seconds(k.frame_index) for k in vo.keyframes] + [seq.seconds(len(seq) - 1)]
    return [int(min(a.max_steps, max(0.0, 1000.0 * (t1 - t0) // a.step_cost_ms))) for t0, t1 in zip(times, times[1:])]


def _with_bridges(vo: VOResult, bridges: list[dict[str, Any]]) -> VOResult:
    """``vo`` with the segments it bridged listed under ``meta["bridges"]``."""
    return replace(vo, meta={**vo.meta, "bridges": bridges})


def step_row(info: StepInfo) -> dict[str, Any]:
    """A flat CSV row from the adapter's step info (loss parts as ``loss_<part>`` columns)."""
    row: dict[str, Any] = {}
    for k, v in dict(vars(info)).items():
        if isinstance(v, dict):
            row.update({f"{k}_{p}": x for p, x in v.items()})
        elif isinstance(v, (list, tuple)):
            row[k] = " ".join(map(str, v))
        else:
            row[k] = v.value if hasattr(v, "value") else v
    return row


# ----------------------------------------------------------------------------- the stage


@dataclass
class Adapted:
    """What the adaptation stage hands on.

    Attributes:
        net: the final network (for scheme ``none`` the pre-trained one, unchanged).
        adapter: the keyframe adapter (its replay buffer and L_val per keyframe), ``None`` for
            schemes ``none`` and ``comoda``.
        map: the loop's map at the end: the front end's, or after the BAs Algorithm 1 requested.
        requested: how many times Algorithm 1 requested global BA.
        l_val: Algorithm 1's validations against τ (:func:`l_val_stats`; empty without the loop).
        online: the ``online_*`` per-frame scores of the model of each frame's time
            (:mod:`~mutualslam_cli.stages.online_eval`); ``None`` when not computed.
    """

    net: torch.nn.Module
    adapter: OnlineAdapter | None
    map: VOResult
    requested: int
    l_val: dict[str, Any] = field(default_factory=dict)
    online: pd.DataFrame | None = None

    def why_no_request(self, tau: float, patience: int) -> str:
        """Why Algorithm 1 never requested global BA, in its terms (L_val vs τ over ``patience`` validations)."""
        v = self.l_val
        if not v.get("validations"):
            return "Algorithm 1 never validated (no validation keyframe with sparse points)"
        return (f"Algorithm 1 never requested global BA: L_val < τ = {tau:g} in {v['longest_below_tau']} "
                f"validation(s) in a row at most, {patience} needed (min L_val {v['min']:.3g} over "
                f"{v['validations']} validations)")


#: The keys of :func:`l_val_stats` (``adaptation.l_val.*`` in ``summary.json``).
L_VAL_KEYS = ("validations", "min", "median", "longest_below_tau", "map_median_depth")


def l_val_stats(rows: list[dict[str, Any]], tau: float, vo: VOResult) -> dict[str, Any]:
    """Algorithm 1's validations from the keyframe rows: ``validations`` (with an L_val), ``min``,
    ``median`` (L_val, Eq. 9, inverse map units), ``longest_below_tau`` (most consecutive ones below τ)
    and ``map_median_depth`` (median depth of the map points in their hosts, map units). The front end
    sets the median depth of its first map to 1, as SVO does, so τ means here what it means in the
    paper as long as that unit holds; ``L_val × map_median_depth`` is the scale-free form."""
    vals = [float(r["l_val"]) for r in rows if r.get("is_validation") and r.get("l_val") is not None
            and np.isfinite(float(r["l_val"]))]
    run = best = 0
    for v in vals:
        run = run + 1 if v < tau else 0
        best = max(best, run)
    depth = float(np.median(1.0 / vo.points.inv_depth)) if len(vo.points) else None
    return {"validations": len(vals), "min": min(vals) if vals else None,
            "median": float(np.median(vals)) if vals else None, "longest_below_tau": best,
            "map_median_depth": depth}


def run_stage(run: RunContext, fe: FrontEnd, net0: torch.nn.Module, fast: bool,
              global_ba: GlobalBA | None = None) -> Adapted:
    """Adapt a copy of ``net0`` online: ``keyframes.csv`` and the keys ``timing.finetune_ms``,
    ``timing.finetune_kf_ms`` and ``adaptation.*`` (scheme ``comoda``: its own outputs).

    The time of the BAs Algorithm 1 triggered (``global_ba``) is booked to the ``ba`` stage, the rest
    to ``adaptation``."""
    cfg, summary = run.cfg, run.summary
    t = time.perf_counter()
    if cfg.adapt.scheme == "comoda":  # every frame, its own pose network, no keyframes
        net = comoda.run_stage(run, copy.deepcopy(net0), fast)
        adapted, rows, online_s = Adapted(net, None, fe.vo, 0), [], 0.0
        for k in L_VAL_KEYS:
            summary.absent(f"adaptation.l_val.{k}", "scheme 'comoda' has no Algorithm 1")
        _summarise_strength(summary, None)
    else:
        scorer = (OnlineScorer(run.seq, eval_frames(run.seq, cfg.eval.stride), cfg, fast)
                  if cfg.eval.online and run.seq.has_depth and cfg.adapt.scheme != "none" else None)
        net, rows, adapter, loop_map = run_adaptation(run.seq, fe.vo, copy.deepcopy(net0), cfg, fast, run.progress,
                                                      global_ba, scorer)
        online = scorer.finish(net, len(fe.vo.keyframes) - 1) if scorer is not None else None
        adapted = Adapted(net, adapter, loop_map, sum(bool(r.get("run_global_ba")) for r in rows),
                          l_val_stats(rows, cfg.adapt.tau_val, loop_map), online)
        online_s = scorer.seconds if scorer is not None else 0.0
        why = "no validation keyframe had an L_val"
        for k, v in adapted.l_val.items():
            summary.set(f"adaptation.l_val.{k}", v, why)
        _summarise(summary, cfg.adapt.scheme, adapter, rows)
        _summarise_strength(summary, adapter)
        for key in (comoda.POSENET_ATE_KEY, comoda.POSE_NETWORK_KEY):
            summary.absent(key, f"scheme {cfg.adapt.scheme!r} has no pose network (only 'comoda')")
    ba_s = float(sum(r.get("ba_s", 0.0) for r in rows))  # Algorithm 1's BAs, inside the loop
    run.add_time("adaptation", time.perf_counter() - t - ba_s - online_s)
    run.add_time("ba", ba_s)
    run.add_time("evaluation", online_s)  # the online scores are evaluation, done inside the loop
    if rows:
        atomic_write_text(run.folder / "keyframes.csv", pd.DataFrame(rows).to_csv(index=False))
    _summarise_bridges(run, adapted.map, cfg.adapt.scheme == "comoda")
    return adapted


def _summarise_bridges(run: RunContext, loop_map: VOResult, comoda_scheme: bool) -> None:
    """``vo.bridges`` and, when a segment was bridged, ``traj_{kf,all}_bridged.txt`` and
    ``trajectory.ate_rmse_m.bridged`` / ``all_frames_bridged``: the adaptation loop's map (bridged
    segments; Algorithm 1's BAs included) before the final BA, one Sim(3) as every headline ATE."""
    keys = [f"trajectory.{group}.{leaf}" for group in ("ate_rmse_m", "ate_rmse_m_per_segment")
            for leaf in ("bridged", "all_frames_bridged")]
    if comoda_scheme:
        why = "scheme 'comoda' does not run the keyframe loop that bridges segments"
        for key in ("vo.bridges", *keys):
            run.summary.absent(key, why)
        return
    bridges = loop_map.meta.get("bridges", [])
    run.summary.set("vo.bridges", len(bridges))
    if not bridges:
        why = ("no segment to bridge" if len({k.segment for k in loop_map.keyframes}) < 2 else
               "no bridge could be made (vo.bridge_segments=false, or no depth ratio on a side of a gap)")
        for key in keys:
            run.summary.absent(key, why)
        return
    write_trajectories(run.folder, loop_map.traj_kf, loop_map.traj_all, suffix="_bridged")
    set_ate(run.summary, evaluate_trajectory(run.seq, loop_map, run.cfg.eval.ate_max_dt),
            {"kf": "bridged", "all": "all_frames_bridged"})


#: The keys of :func:`_summarise_strength` (``adaptation.reg.*``).
STRENGTH_KEYS = ("shrink.mean", "shrink.median", "importance.mean")


def _summarise_strength(summary: Summary, adapter: OnlineAdapter | None) -> None:
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


def _summarise(summary: Summary, scheme: str, adapter: OnlineAdapter | None, kf_rows: list[dict[str, Any]]) -> None:
    """``timing.finetune_ms`` (median per optimiser step), ``timing.finetune_kf_ms`` (per keyframe, the steps
    included) and of it ``timing.finetune_batch_ms`` (assembling the batch) and ``timing.finetune_consolidate_ms``
    (the regulariser's end of batch: EWC's per-keyframe Fisher, MAS's importance), ``adaptation.keyframes_trained``,
    ``adaptation.steps`` and, for scheme ``luo``, ``adaptation.luo_keyframes_with_partner`` (training keyframes
    that found a simulated stereo partner)."""
    why = "scheme 'none': no fine-tuning" if scheme == "none" else "no keyframe was trained on"
    for key, ms in (("finetune_ms", "step_ms"), ("finetune_kf_ms", "finetune_ms"), ("finetune_batch_ms", "batch_ms"),
                    ("finetune_consolidate_ms", "consolidate_ms")):
        values = getattr(adapter, ms) if adapter is not None else []
        summary.set(f"timing.{key}", float(np.median(values)) if values else None, why)
    summary.set("adaptation.keyframes_trained", sum(bool(r.get("trained")) for r in kf_rows))
    summary.set("adaptation.steps", int(sum(int(r.get("steps") or 0) for r in kf_rows)))
    if scheme == "luo":
        training = [r for r in kf_rows if not r.get("is_validation")]
        summary.set("adaptation.luo_keyframes_with_partner", sum(bool(str(r.get("sources") or "").strip())
                                                                 for r in training))
        summary.set("adaptation.training_keyframes", len(training))

"""One sequence, one scheme (DESIGN §1): front end → adaptation → culling + BA → evaluation → files.

:func:`run_sequence` is what ``mslam run`` calls; every stage is a plain function too, so other
tools can call them without the CLI. Progress goes to an optional callback
``progress(stage, info)`` and to :mod:`logging`.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import pandas as pd
import torch
from threadpoolctl import threadpool_limits

from mutualslam_cli.adapt.inputs import load_network, use_fast_path
from mutualslam_cli.adapt.weights import save_monodepth2
from mutualslam_cli.allocator import retain_freed_memory
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.ba.culling import inject_outliers
from mutualslam_cli.config import RunConfig, to_dict, with_overrides
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import (
    is_complete,
    manifest,
    read_summary,
    run_dir,
    write_json,
    write_trajectories,
    write_yaml,
)
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Progress, run_adaptation, summarise_adaptation
from mutualslam_cli.stages.ba import (
    BALog,
    final_ba,
    make_ba_step,
    no_culling_reason,
    summarise_ba_absent,
    summarise_outliers,
    write_ba_results,
)
from mutualslam_cli.stages.comoda import POSENET_ATE_KEY, run_comoda_stage
from mutualslam_cli.stages.dense import add_stage_time, run_dense
from mutualslam_cli.stages.evaluation import (
    esi_of_log_errors,
    evaluate_models,
    evaluate_trajectory,
    map_log_depth_errors,
    summarise_depth,
)
from mutualslam_cli.stages.frontend import run_frontend, summarise_frontend

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """What :func:`run_sequence` returns.

    Attributes:
        folder: the result folder.
        summary: the ``summary.json`` content (nested dict).
        skipped: True when the run was already complete and nothing was recomputed.
    """

    folder: Path
    summary: dict[str, Any]
    skipped: bool = False
    timings: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- the run


def run_sequence(sequence: str | Path | Sequence, cfg: RunConfig, out: str | Path | None = None,
                 command: list[str] | None = None, force: bool = False,
                 progress: Progress | None = None, registry: Path | None = None) -> RunResult:
    """Run one sequence with one scheme and write ``<out>/<seq>/<scheme>/seed<k>/`` (DESIGN §8).

    Args:
        sequence: a ``datasets.yaml`` name, a folder, or a loaded :class:`Sequence`.
        cfg: resolved configuration.
        out: results root (default ``cfg.out``).
        command: the command line, recorded in ``manifest.json``.
        force: recompute even when the run is complete.
        progress: ``progress(stage, info)`` with stages ``load``, ``vo``, ``adapt``, ``eval``, ``dense``.
        registry: an alternative ``datasets.yaml``.

    Returns:
        :class:`RunResult`. A complete run (``summary.json`` present) is returned as is unless
        ``force``.

    Raises:
        ResultsLocked: another process works in the same run folder (:mod:`~mutualslam_cli.results.lock`).
    """
    t_start = time.perf_counter()
    torch.manual_seed(cfg.seed)
    retain_freed_memory()  # image-sized buffers reuse pages (VO, warps, evaluation)
    # Results follow the thread count (reductions sum in another order), so the count is resolved
    # here, used alike by torch, OpenCV and BLAS, and recorded in config.yaml like any setting.
    cfg = with_overrides(cfg, threads=cfg.threads if cfg.threads > 0 else torch.get_num_threads())
    torch.set_num_threads(cfg.threads)
    cv2.setNumThreads(cfg.threads)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(
        sequence, data_root=cfg.data.data_root, registry_path=registry,
        max_frames=cfg.data.max_frames, stride=cfg.data.stride)
    timings["load_s"] = time.perf_counter() - t
    out_root = Path(out if out is not None else cfg.out)
    folder = run_dir(out_root, seq.name, cfg.adapt.scheme, cfg.seed)
    if is_complete(folder) and not force:
        log.info("%s is complete; skipping (use --force to recompute)", folder)
        return RunResult(folder, read_summary(folder), skipped=True)
    with hold_lock(folder, "mslam run"), threadpool_limits(limits=cfg.threads, user_api="blas"):
        # (a second process on this folder stops at the lock, having touched nothing)
        return _run_locked(seq, cfg, folder, out_root, command, force, progress, timings, t_start)


def _run_locked(seq: Sequence, cfg: RunConfig, folder: Path, out_root: Path, command: list[str] | None,
                force: bool, progress: Progress | None, timings: dict[str, float], t_start: float) -> RunResult:
    """The work of :func:`run_sequence` in its run folder, under the folder's lock."""
    if is_complete(folder) and not force:  # completed by the previous holder just before we locked
        return RunResult(folder, read_summary(folder), skipped=True)
    write_yaml(folder / "config.yaml", to_dict(cfg))
    summary = Summary()

    # Front end (cached per sequence + VO config: every scheme reuses it), trajectory and map.
    t = time.perf_counter()
    vo, cached = run_frontend(seq, cfg, cache_dir=out_root / "_cache" / "vo", progress=progress)
    timings["vo_s"] = time.perf_counter() - t
    vo, injected = inject_outliers(vo, cfg.vo.inject_outliers, cfg.seed)  # test knob, off by default
    write_trajectories(folder, vo.traj_kf, vo.traj_all)
    err_vo = map_log_depth_errors(seq, vo)  # per point log z − log z*: the map's colours and its e_si
    write_ply(folder / "map_vo.ply", vo.points_world(), err_vo)
    esi_vo, n_gt = esi_of_log_errors(err_vo)
    summarise_frontend(summary, keyframes=len(vo.keyframes), tracked_fraction=vo.tracked_fraction,
                           map_points=len(vo.points), vo_mode=cfg.vo.mode, frames=len(seq),
                           vo_time_s=float(vo.meta.get("time_s", timings["vo_s"])),
                           traj=evaluate_trajectory(seq, vo, cfg.eval.ate_max_dt), map_esi=esi_vo)

    # Network: pre-trained model, then online adaptation.
    fast = use_fast_path(cfg)
    net0 = load_network(cfg, fast)
    record = BALog()  # the mutual loop: culling + global BA at Algorithm 1's requests feed back into training
    step = make_ba_step(seq, vo, cfg, record) if cfg.ba.enabled else None
    t = time.perf_counter()
    if cfg.adapt.scheme == "comoda":  # the CoMoDa-style baseline: every frame, its own pose network, no keyframes
        net, kf_rows, adapter, loop_map = run_comoda_stage(seq, copy.deepcopy(net0), cfg, fast, folder, summary,
                                                           progress, out_root / "_cache" / "comoda"), [], None, vo
    else:
        net, kf_rows, adapter, loop_map = run_adaptation(seq, vo, copy.deepcopy(net0), cfg, fast, progress, step)
        summarise_adaptation(summary, cfg.adapt.scheme, adapter.step_ms if adapter else [],
                                 adapter.finetune_ms if adapter else [], kf_rows)
        summary.absent(POSENET_ATE_KEY, f"scheme {cfg.adapt.scheme!r} has no pose network (only 'comoda')")
    timings["adapt_s"] = time.perf_counter() - t
    if kf_rows:
        atomic_write_text(folder / "keyframes.csv", pd.DataFrame(kf_rows).to_csv(index=False))

    # Final culling + global BA over every keyframe: the after-BA trajectory and map.
    requested = sum(bool(r.get("run_global_ba")) for r in kf_rows)
    ba_trigger_s = float(sum(r.get("ba_s", 0.0) for r in kf_rows))  # Algorithm 1's BAs, inside adaptation
    if step is None:
        summarise_ba_absent(summary, "disabled (ba.enabled=false)", requested)
    else:
        t = time.perf_counter()
        vo_ba = final_ba(seq, vo, loop_map, net, adapter, cfg, fast, step)
        timings["ba_final_s"] = time.perf_counter() - t
        write_ba_results(folder, summary, seq, vo, err_vo, vo_ba, cfg, record, requested,
                         ba_trigger_s + timings["ba_final_s"])
    if len(injected):
        culled = record.culled_mask(vo.points.ids) if no_culling_reason(cfg) is None else None
        summarise_outliers(summary, vo.points.ids, injected, culled)

    # Depth evaluation with the pre-trained and the final model on every frame with GT depth.
    t = time.perf_counter()
    cb = (lambda d, n: progress("eval", {"done": d, "total": n})) if progress else None
    table, ms = evaluate_models(seq, net0, None if cfg.adapt.scheme == "none" else net, cfg, fast,
                                {k.frame_index for k in vo.keyframes}, out_root / "_cache" / "pretrained", cb)
    timings["eval_s"] = time.perf_counter() - t
    if len(table):
        atomic_write_text(folder / "per_frame.csv", table.to_csv(index=False))
    summarise_depth(summary, table, ms, cfg.adapt.scheme)
    if cfg.eval.save_weights and cfg.adapt.scheme != "none":
        save_monodepth2(net, folder / "weights", cfg.net.height, cfg.net.width)

    # Dense reconstruction of both models' depth, scored against GT depth fused with GT poses (issue 13).
    if cfg.dense.enabled:
        t = time.perf_counter()
        run_dense(folder, seq, vo, {"pretrained": net0, "adapted": None if cfg.adapt.scheme == "none" else net},
                  cfg, fast, summary, progress)
        timings["dense_s"] = time.perf_counter() - t

    timings["total_s"] = time.perf_counter() - t_start
    summarise_stages(summary, timings, ba_trigger_s, cached)
    add_stage_time(summary, timings)
    summary.set("vo.from_cache", cached)
    summary.set("sequence.name", seq.name)
    summary.set("sequence.frames", len(seq))
    summary.set("depth.eval_stride", cfg.eval.stride)  # every k-th frame with GT depth was evaluated
    summary.set("scheme", cfg.adapt.scheme)
    summary.set("seed", cfg.seed)
    summary.set("vo.mode", cfg.vo.mode)
    summary.set("depth.fast_path", fast)
    write_json(folder / "manifest.json", manifest(command, cfg.seed, timings, {
        "sequence": {"name": seq.name, "root": str(seq.root), "frames": len(seq), "meta": seq.meta,
                     "intrinsics": seq.intrinsics.as_list()},
        "vo_meta": {k: v for k, v in vo.meta.items() if isinstance(v, (int, float, str, bool, dict, list))},
        "map_points_with_gt": n_gt,
        "ba_runs": record.runs,
    }))
    s = summary.to_dict()
    write_json(folder / "summary.json", s)  # last: marks the run complete
    return RunResult(folder, s, timings=timings)


# ----------------------------------------------------------------------------- summary keys


def summarise_stages(summary: Summary, timings: dict[str, float], ba_trigger_s: float, vo_cached: bool) -> None:
    """``timing.total_s`` and the run's wall time split by stage, ``timing.stage_s.*`` (seconds).

    ``frontend`` (VO or oracle; a cached front end costs only its loading), ``adaptation`` (online
    fine-tuning without the BA it triggered), ``ba`` (every culling + global BA: Algorithm 1's
    requests and the final one), ``evaluation`` (depth of every frame with GT by both models),
    ``other`` (the rest: loading the sequence and the network, trajectory and map metrics, writing
    files). The five add up to ``total_s``.
    """
    ba = ba_trigger_s + timings.get("ba_final_s", 0.0)
    parts = {"frontend": timings.get("vo_s", 0.0), "adaptation": timings.get("adapt_s", 0.0) - ba_trigger_s,
             "ba": ba, "evaluation": timings.get("eval_s", 0.0)}
    parts["other"] = timings["total_s"] - sum(parts.values())
    summary.set("timing.total_s", timings["total_s"])
    for k, v in parts.items():
        summary.set(f"timing.stage_s.{k}", float(v))
    if vo_cached:
        summary.notes["timing.stage_s.frontend"] = "front end loaded from the cache"

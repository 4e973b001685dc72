"""One sequence, one scheme (DESIGN §1): front end → adaptation → culling + BA → evaluation → files.

:func:`run_sequence` is what ``mslam run`` calls; every stage is a plain function too, so other
tools can call them without the CLI. Progress goes to an optional callback
``progress(stage, info)`` and to :mod:`logging`.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import pickle
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping

import cv2
import numpy as np
import pandas as pd
import torch

from mutualslam_cli import results as res
from mutualslam_cli.adapt.inputs import keyframe_images, load_network, use_fast_path
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.adapt.stage import GlobalBA, Progress, depth_predictor, run_adaptation
from mutualslam_cli.ba.culling import inject_outliers
from mutualslam_cli.ba.global_ba import run_global_ba
from mutualslam_cli.adapt.weights import save_monodepth2
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.evaluation import esi_of_log_errors, evaluate_models, evaluate_trajectory, map_log_depth_errors
from mutualslam_cli.heap import retain_freed_memory
from mutualslam_cli.vo.camera import Undistorter
from mutualslam_cli.vo.frontend import FRONTEND_VERSION, run_vo
from mutualslam_cli.vo.oracle import run_oracle
from mutualslam_cli.vo.pose_oracle import run_pose_oracle
from mutualslam_cli.vo.output import VOResult

log = logging.getLogger(__name__)

#: Version of the oracle front ends in their cache key (2: ``gt`` = pose oracle, ``gt-depth`` = depth oracle).
ORACLE_VERSION = 2

#: Global BA image resolution, relative to the VO camera. Half: an LM iteration costs the same at
#: any resolution (it scales with points × targets), the images take 4× less memory (300 TUM
#: keyframes: 92 MB instead of 370 MB), the area-averaged images widen the convergence basin, and
#: on tum_fr1_xyz (16 keyframes, 659 points, GT depth as the CNN) it gave keyframe ATE 13.2 mm and
#: map e_si 0.113 where full resolution gave 13.9 mm and 0.118, in about the same time (0.5 s on an
#: idle core). Not the network resolution: 640×192 squeezes a 4:3 image vertically by 2.5.
BA_SCALE = 0.5


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


# ----------------------------------------------------------------------------- front end


def vo_cache_key(seq: Sequence, cfg: RunConfig) -> str:
    """Cache key of a front-end result: sequence identity + front-end and data config + seed."""
    ident = {
        "root": str(Path(seq.root).resolve()), "n": len(seq),
        "first": seq.frames[0].timestamp if len(seq) else None,
        "last": seq.frames[-1].timestamp if len(seq) else None,
        "vo": {k: v for k, v in to_dict(cfg.vo).items() if k != "inject_outliers"},
        "data": {"max_frames": cfg.data.max_frames, "stride": cfg.data.stride},
        "seed": cfg.seed, "intr": seq.intrinsics.as_list(), "version": FRONTEND_VERSION,
    }
    if cfg.vo.mode != "svo":  # "gt" was the depth oracle before version 2 of the oracles
        ident["oracle_version"] = ORACLE_VERSION
    return hashlib.sha1(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                 progress: Progress | None = None) -> tuple[VOResult, bool]:
    """Run (or load from cache) the front end selected by ``cfg.vo.mode``.

    Returns:
        ``(vo_result, from_cache)``.
    """
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{seq.name}-{cfg.vo.mode}-{vo_cache_key(seq, cfg)}.pkl"
        if path.is_file():
            try:
                with open(path, "rb") as f:
                    vo = pickle.load(f)
                log.info("front end loaded from cache %s", path)
                return vo, True
            except Exception as e:  # noqa: BLE001 - a corrupt cache entry is recomputed
                log.warning("ignoring unreadable VO cache %s (%s)", path, e)
    cb = (lambda info: progress("vo", info)) if progress else None
    if cfg.vo.mode == "gt":  # pose oracle: our VO's tracks (cached like any svo run) re-triangulated with GT poses
        svo, _ = run_frontend(seq, replace(cfg, vo=replace(cfg.vo, mode="svo")), cache_dir, progress)
        vo = run_pose_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb, vo=svo)
    elif cfg.vo.mode == "gt-depth":
        vo = run_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb)
    else:
        vo = run_vo(seq, cfg.vo, seed=cfg.seed, progress=cb)
    if path is not None:
        res.atomic_write_bytes(path, pickle.dumps(vo, protocol=pickle.HIGHEST_PROTOCOL))
    return vo, False


# ----------------------------------------------------------------------------- culling + global BA


def ba_images(seq: Sequence, vo: VOResult, scale: float = BA_SCALE) -> Callable[[int], np.ndarray]:
    """``kf_id → (H, W)`` float32 grey in [0, 1] of the keyframes, undistorted, at ``scale`` × the
    VO camera (area resampling; cached for the run)."""
    und = Undistorter(seq.intrinsics)
    size = (round(vo.intrinsics.width * scale), round(vo.intrinsics.height * scale))
    cache: dict[int, np.ndarray] = {}

    def load(kf_id: int) -> np.ndarray:
        if kf_id not in cache:
            grey = cv2.cvtColor(und.image(seq.load_rgb(vo.keyframes[kf_id].frame_index)), cv2.COLOR_RGB2GRAY)
            cache[kf_id] = cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        return cache[kf_id]

    return load


@dataclass
class BALog:
    """What the culling + BA runs of one run did: each run's ``stats`` (triggers, then the final
    one) and the ids of every culled map point."""

    runs: list[dict[str, Any]] = field(default_factory=list)
    culled: set[int] = field(default_factory=set)


def make_ba_step(seq: Sequence, vo: VOResult, cfg: RunConfig, record: BALog) -> GlobalBA:
    """The :data:`~mutualslam_cli.adapt.stage.GlobalBA` step of a run (culling unless
    ``ba.culling=false`` or scheme ``none``), recording into ``record``."""
    images = ba_images(seq, vo)
    cull = cfg.ba.culling and cfg.adapt.scheme != "none"

    def step(v: VOResult, kf_id: int, depth_of: Callable[[int], np.ndarray],
             val_loss: Mapping[int, float]) -> VOResult:
        r = run_global_ba(v, images, depth_of, val_loss, cfg.ba, cull=cull, upto=kf_id)
        record.culled.update(v.points.ids[~r.keep].tolist())
        record.runs.append({"kf_id": kf_id, **{k: x for k, x in r.stats.items() if k != "costs"}})
        log.info("global BA after keyframe %d: %d culled, %d refined (%d unrefined), cost %.4g -> %.4g, %.2f s",
                 kf_id, r.stats["n_culled"], r.stats["n_refined"], r.stats["n_unrefined"], r.stats["cost0"],
                 r.stats["cost"], r.stats["seconds"])
        return r.kept()

    return step


def final_ba(seq: Sequence, vo: VOResult, loop_map: VOResult, net: torch.nn.Module,
             adapter: OnlineAdapter | None, cfg: RunConfig, fast: bool, step: GlobalBA) -> VOResult:
    """The final culling + BA of the loop's map over every keyframe with the final network
    (L_val of every stored keyframe; none for scheme ``none``)."""
    load = keyframe_images(seq, vo, cfg.net.width, cfg.net.height)
    depth_of = depth_predictor(net, load, fast, adapter.buffer if adapter is not None else None)
    val_loss = adapter.per_keyframe_val_loss() if adapter is not None else {}
    return step(loop_map, len(loop_map.keyframes) - 1, depth_of, val_loss)


def write_ba_results(folder: Path, summary: res.Summary, seq: Sequence, vo: VOResult, vo_ba: VOResult,
                     cfg: RunConfig, record: BALog, requested: int, ba_s: float) -> None:
    """``map_culled.ply`` (the front end's map without the culled points), ``map_ba.ply`` (both coloured
    by error), ``traj_{kf,all}_ba.txt`` and the BA part of the summary (:func:`results.summarise_ba`)."""
    keep = ~np.isin(vo.points.ids, np.fromiter(record.culled, np.int64, len(record.culled)))
    no_culling = ("disabled (ba.culling=false): BA without culling" if not cfg.ba.culling else
                  "scheme 'none': no adapted network to cull with" if cfg.adapt.scheme == "none" else None)
    err, err_ba = map_log_depth_errors(seq, vo), map_log_depth_errors(seq, vo_ba)
    if no_culling is None:
        res.write_ply(folder / "map_culled.ply", vo.points_world()[keep], err[keep])
    res.write_ply(folder / "map_ba.ply", vo_ba.points_world(), err_ba)
    res.write_trajectories(folder, vo_ba.traj_kf, vo_ba.traj_all, suffix="_ba")
    res.summarise_ba(summary, traj=evaluate_trajectory(seq, vo_ba, cfg.eval.ate_max_dt),
                     points_culled=int(keep.sum()), esi_culled=esi_of_log_errors(err[keep])[0],
                     points_ba=len(vo_ba.points), esi_ba=esi_of_log_errors(err_ba)[0], ba_s=ba_s,
                     runs=record.runs, requested=requested, no_culling=no_culling)


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
        progress: ``progress(stage, info)`` with stages ``load``, ``vo``, ``adapt``, ``eval``.
        registry: an alternative ``datasets.yaml``.

    Returns:
        :class:`RunResult`. A complete run (``summary.json`` present) is returned as is unless
        ``force``.
    """
    t_start = time.perf_counter()
    torch.manual_seed(cfg.seed)
    retain_freed_memory()  # image-sized buffers reuse pages (VO, warps, evaluation)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
        cv2.setNumThreads(cfg.threads)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(
        sequence, data_root=cfg.data.data_root, registry_path=registry,
        max_frames=cfg.data.max_frames, stride=cfg.data.stride)
    timings["load_s"] = time.perf_counter() - t
    out_root = Path(out if out is not None else cfg.out)
    folder = res.run_dir(out_root, seq.name, cfg.adapt.scheme, cfg.seed)
    if res.is_complete(folder) and not force:
        log.info("%s is complete; skipping (use --force to recompute)", folder)
        return RunResult(folder, res.read_summary(folder), skipped=True)
    folder.mkdir(parents=True, exist_ok=True)
    res.write_yaml(folder / "config.yaml", to_dict(cfg))
    summary = res.Summary()

    # Front end (cached per sequence + VO config: every scheme reuses it), trajectory and map.
    t = time.perf_counter()
    vo, cached = run_frontend(seq, cfg, cache_dir=out_root / "_cache" / "vo", progress=progress)
    timings["vo_s"] = time.perf_counter() - t
    vo, injected = inject_outliers(vo, cfg.vo.inject_outliers, cfg.seed)  # test knob, off by default
    res.write_trajectories(folder, vo.traj_kf, vo.traj_all)
    err_vo = map_log_depth_errors(seq, vo)  # per point log z − log z*: the map's colours and its e_si
    res.write_ply(folder / "map_vo.ply", vo.points_world(), err_vo)
    esi_vo, n_gt = esi_of_log_errors(err_vo)
    res.summarise_frontend(summary, keyframes=len(vo.keyframes), tracked_fraction=vo.tracked_fraction,
                           map_points=len(vo.points), vo_mode=cfg.vo.mode, frames=len(seq),
                           vo_time_s=float(vo.meta.get("time_s", timings["vo_s"])),
                           traj=evaluate_trajectory(seq, vo, cfg.eval.ate_max_dt), map_esi=esi_vo)

    # Network: pre-trained model, then online adaptation.
    net0 = load_network(cfg)
    fast = use_fast_path(cfg)
    record = BALog()  # the mutual loop: culling + global BA at Algorithm 1's requests feed back into training
    step = make_ba_step(seq, vo, cfg, record) if cfg.ba.enabled else None
    t = time.perf_counter()
    net, kf_rows, adapter, loop_map = run_adaptation(seq, vo, copy.deepcopy(net0), cfg, fast, progress, step)
    timings["adapt_s"] = time.perf_counter() - t
    res.summarise_adaptation(summary, cfg.adapt.scheme, adapter.step_ms if adapter else [],
                             adapter.finetune_ms if adapter else [])
    if kf_rows:
        res.atomic_write_text(folder / "keyframes.csv", pd.DataFrame(kf_rows).to_csv(index=False))

    # Final culling + global BA over every keyframe: the after-BA trajectory and map.
    requested = sum(bool(r.get("run_global_ba")) for r in kf_rows)
    if step is None:
        res.summarise_ba_absent(summary, "disabled (ba.enabled=false)", requested)
    else:
        t = time.perf_counter()
        vo_ba = final_ba(seq, vo, loop_map, net, adapter, cfg, fast, step)
        timings["ba_final_s"] = time.perf_counter() - t
        trigger_s = float(sum(r.get("ba_s", 0.0) for r in kf_rows))
        write_ba_results(folder, summary, seq, vo, vo_ba, cfg, record, requested, trigger_s + timings["ba_final_s"])
    if len(injected):
        culls = step is not None and cfg.ba.culling and cfg.adapt.scheme != "none"
        res.summarise_outliers(summary, vo.points.ids, injected, record.culled if culls else None)

    # Depth evaluation with the pre-trained and the final model on every frame with GT depth.
    t = time.perf_counter()
    cb = (lambda d, n: progress("eval", {"done": d, "total": n})) if progress else None
    table, ms = evaluate_models(seq, net0, None if cfg.adapt.scheme == "none" else net, cfg, fast,
                                {k.frame_index for k in vo.keyframes}, out_root / "_cache" / "pretrained", cb)
    timings["eval_s"] = time.perf_counter() - t
    if len(table):
        res.atomic_write_text(folder / "per_frame.csv", table.to_csv(index=False))
    res.summarise_depth(summary, table, ms, cfg.adapt.scheme)
    if cfg.eval.save_weights and cfg.adapt.scheme != "none":
        save_monodepth2(net, folder / "weights", cfg.net.height, cfg.net.width)

    timings["total_s"] = time.perf_counter() - t_start
    summary.set("timing.total_s", timings["total_s"])
    summary.set("vo.from_cache", cached)
    summary.set("sequence.name", seq.name)
    summary.set("sequence.frames", len(seq))
    summary.set("scheme", cfg.adapt.scheme)
    summary.set("seed", cfg.seed)
    summary.set("vo.mode", cfg.vo.mode)
    summary.set("depth.fast_path", fast)
    res.write_json(folder / "manifest.json", res.manifest(command, cfg.seed, timings, {
        "sequence": {"name": seq.name, "root": str(seq.root), "frames": len(seq), "meta": seq.meta,
                     "intrinsics": seq.intrinsics.as_list()},
        "vo_meta": {k: v for k, v in vo.meta.items() if isinstance(v, (int, float, str, bool, dict, list))},
        "map_points_with_gt": n_gt,
        "ba_runs": record.runs,
    }))
    s = summary.to_dict()
    res.write_json(folder / "summary.json", s)  # last: marks the run complete
    return RunResult(folder, s, timings=timings)

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
from typing import Any, Callable

import cv2
import numpy as np
import torch

from mutualslam_cli import results as res
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.evaluation import EVAL_VERSION, depth_means, evaluate_depth, evaluate_trajectory, map_esi
from mutualslam_cli.heap import retain_freed_memory
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import Undistorter
from mutualslam_cli.vo.frontend import FRONTEND_VERSION, run_vo
from mutualslam_cli.vo.oracle import run_oracle
from mutualslam_cli.vo.pose_oracle import run_pose_oracle
from mutualslam_cli.vo.output import VOResult

log = logging.getLogger(__name__)

#: Version of the oracle front ends in their cache key (2: ``gt`` = pose oracle, ``gt-depth`` = depth oracle).
ORACLE_VERSION = 2

Progress = Callable[[str, dict[str, Any]], None]


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
        "vo": to_dict(cfg.vo), "data": {"max_frames": cfg.data.max_frames, "stride": cfg.data.stride},
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


# ----------------------------------------------------------------------------- network input


def to_net_image(rgb: np.ndarray, width: int, height: int) -> torch.Tensor:
    """``(H, W, 3)`` uint8 → ``(3, height, width)`` float32 in [0, 1] (area resampling)."""
    small = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(small).permute(2, 0, 1).float().div_(255.0)


def scale_pixels(uv: np.ndarray, src: Intrinsics, width: int, height: int) -> np.ndarray:
    """Pixels at ``src`` resolution → pixels at ``width × height`` (pixel-centre convention)."""
    s = np.array([width / src.width, height / src.height])
    return (uv + 0.5) * s - 0.5


def keyframe_images(seq: Sequence, vo: VOResult, width: int, height: int) -> Callable[[int], torch.Tensor]:
    """A loader of keyframe images at network resolution, undistorted to ``vo.intrinsics``.

    The same :class:`~mutualslam_cli.vo.camera.Undistorter` geometry as the evaluation's
    (:func:`mutualslam_cli.evaluation.evaluate_depth`).
    """
    und = Undistorter(seq.intrinsics)

    def load(kf_id: int) -> torch.Tensor:
        return to_net_image(und.image(seq.load_rgb(vo.keyframes[kf_id].frame_index)), width, height)

    return load


def make_predictor(net: torch.nn.Module, cfg: RunConfig, fast: bool) -> Callable[[np.ndarray], np.ndarray]:
    """Predictor for evaluation: RGB frame (pinhole geometry) → depth at network resolution (float32, map units)."""
    from mutualslam_cli.adapt.depthnet import predict_depth

    def predict(rgb: np.ndarray) -> np.ndarray:
        x = to_net_image(rgb, cfg.net.width, cfg.net.height)[None]
        return predict_depth(net, x, fast=fast)[0]

    return predict


def load_network(cfg: RunConfig) -> torch.nn.Module:
    """The pre-trained model: ``net.weights`` (Monodepth2 files) or the ``mslam pretrain`` default."""
    from mutualslam_cli.adapt import weights

    kw = {"min_depth": cfg.net.min_depth, "max_depth": cfg.net.max_depth}
    if cfg.net.weights:
        return weights.load_monodepth2(Path(cfg.net.weights), **kw)
    return weights.load_default(**kw)


def use_fast_path(cfg: RunConfig) -> bool:
    """Resolve ``net.fast`` (auto → bf16 where the CPU supports it)."""
    from mutualslam_cli.adapt.depthnet import fast_path_supported

    return cfg.net.fast == "on" or (cfg.net.fast == "auto" and fast_path_supported())


# ----------------------------------------------------------------------------- adaptation


def run_adaptation(seq: Sequence, vo: VOResult, net: torch.nn.Module, cfg: RunConfig, fast: bool,
                   progress: Progress | None = None) -> tuple[torch.nn.Module, list[dict[str, Any]], Any]:
    """Feed the keyframes through Algorithm 1 with the configured scheme.

    Returns:
        ``(adapted_net, per_keyframe_rows, adapter)``; for scheme ``none`` the network is returned
        unchanged with no rows and ``adapter`` is ``None``.
    """
    from mutualslam_cli.adapt.buffer import KeyframeSample
    from mutualslam_cli.adapt.online import OnlineAdapter

    if cfg.adapt.scheme == "none":
        return net, [], None
    w, h = cfg.net.width, cfg.net.height
    K_net = torch.from_numpy(vo.intrinsics.scaled(w, h).K()).float()
    ba_triggers: list[int] = []
    from mutualslam_cli.adapt.depthnet import prepare

    net = prepare(net, fast)
    adapter = OnlineAdapter(net, cfg.adapt, K_net, seed=cfg.seed, fast=fast,
                            on_global_ba=lambda *a, **k: ba_triggers.append(len(ba_triggers)),
                            val_scope=cfg.adapt.val_scope, reg_mode=cfg.adapt.reg_mode)
    load = keyframe_images(seq, vo, w, h)
    pw = vo.points_world()
    rows = []
    t0 = time.perf_counter()
    for kf in vo.keyframes:
        uv, d = vo.sparse_depth(kf.id, pw)
        sample = KeyframeSample(
            kf_id=kf.id, image=load(kf.id), K=K_net, pose=kf.pose,
            uv=torch.from_numpy(scale_pixels(uv, vo.intrinsics, w, h)).float(),
            depth=torch.from_numpy(d).float(),
        )
        info = adapter.add_keyframe(sample)
        row = _step_row(info)
        row["n_sparse"] = len(d)
        rows.append(row)
        if progress:
            progress("adapt", {"done": kf.id + 1, "total": len(vo.keyframes), **row,
                               "elapsed_s": time.perf_counter() - t0})
    return adapter.net if hasattr(adapter, "net") else net, rows, adapter


def _step_row(info: Any) -> dict[str, Any]:
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


def _model_digest(net: torch.nn.Module) -> str:
    h = hashlib.sha1()
    for k, v in net.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def evaluate_models(seq: Sequence, net0: torch.nn.Module, net: torch.nn.Module | None, cfg: RunConfig, fast: bool,
                    kf_frames: set[int], cache_dir: Path | None = None,
                    progress: Callable[[int, int], None] | None = None) -> tuple[Any, dict[str, float]]:
    """Depth evaluation of the pre-trained model and (unless ``None``) the adapted one.

    The pre-trained model's rows do not depend on the scheme, so they are cached per sequence,
    model weights and evaluation settings and reused by every scheme's run.

    Returns:
        ``(per_frame_table, median_ms_per_prediction)``.
    """
    import pandas as pd

    key = hashlib.sha1(json.dumps({
        "model": _model_digest(net0), "net": to_dict(cfg.net), "eval": to_dict(cfg.eval), "fast": fast,
        "version": EVAL_VERSION,
        "root": str(Path(seq.root).resolve()), "frames": [f.timestamp for f in seq.frames],
    }, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = Path(cache_dir) / f"{seq.name}-{key}.csv" if cache_dir is not None else None
    cached = pd.read_csv(path) if path is not None and path.is_file() else None
    predictors = {}
    if cached is None:
        predictors["pretrained"] = make_predictor(net0, cfg, fast)
    if net is not None:
        predictors["adapted"] = make_predictor(net, cfg, fast)
    if not predictors:  # scheme none with a cached pre-trained evaluation
        table, ms = cached.copy(), {}
    else:
        table, ms = evaluate_depth(seq, predictors, cfg, kf_frames, progress)
    if cached is None and path is not None and len(table):
        cols = ["frame", "timestamp", "n_valid"] + [c for c in table.columns if c.startswith("pretrained_")]
        res.atomic_write_text(path, table[cols].to_csv(index=False))
    elif cached is not None and predictors:
        table = cached.merge(table.drop(columns=["timestamp", "n_valid"]), on="frame", how="left")
    table["is_keyframe"] = table["frame"].isin(kf_frames)
    return table, ms


# ----------------------------------------------------------------------------- the run


def _write_trajectories(folder: Path, vo: VOResult) -> None:
    import io

    for name, traj in (("traj_kf.txt", vo.traj_kf), ("traj_all.txt", vo.traj_all)):
        buf = io.StringIO()
        write_tum_trajectory(buf, traj)
        res.atomic_write_text(folder / name, buf.getvalue())


def _write_ply(path: Path, points: np.ndarray) -> None:
    """ASCII PLY of ``(P, 3)`` points (readable by open3d, MeshLab, CloudCompare)."""
    head = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
    body = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in points)
    res.atomic_write_text(path, head + body + ("\n" if len(points) else ""))


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

    # Front end (cached per sequence + VO config: every scheme reuses it).
    t = time.perf_counter()
    vo, cached = run_frontend(seq, cfg, cache_dir=out_root / "_cache" / "vo", progress=progress)
    timings["vo_s"] = time.perf_counter() - t
    vo_time = float(vo.meta.get("time_s", timings["vo_s"]))
    _write_trajectories(folder, vo)
    summary.set("vo.keyframes", len(vo.keyframes))
    summary.set("vo.tracked_fraction", vo.tracked_fraction)
    if cfg.vo.mode != "svo":
        summary.absent("timing.vo_fps", f"oracle front end (--vo {cfg.vo.mode}): no tracking to time")
    else:
        summary.set("timing.vo_fps", len(seq) / vo_time if vo_time > 0 else None)
    summary.set("map.points.vo", len(vo.points))
    pw = vo.points_world()
    _write_ply(folder / "map_vo.ply", pw)

    # Trajectory accuracy without BA.
    traj = evaluate_trajectory(seq, vo, cfg.eval.ate_max_dt)
    for key, name in (("kf", "trajectory.ate_rmse_m.vo"), ("all", "trajectory.ate_rmse_m.all_frames")):
        r = traj[key]
        if r is None:
            summary.absent(name, traj["notes"].get(key, traj["notes"].get("trajectory", "not computed")))  # type: ignore[union-attr]
        else:
            summary.set(name, float(r.rmse))
            if getattr(r, "note", None):  # re-initialised VO: each segment aligned on its own
                summary.notes[name] = r.note
    if cfg.vo.mode != "svo":
        summary.notes["trajectory.ate_rmse_m.vo"] = "oracle front end: keyframe poses are GT poses"
    esi_vo, n_gt = map_esi(seq, vo)
    summary.set("map.esi.vo", esi_vo, "no map point has GT depth at its host pixel")

    # Network: pre-trained model, then online adaptation.
    net0 = load_network(cfg)
    fast = use_fast_path(cfg)
    net = copy.deepcopy(net0)
    t = time.perf_counter()
    net, kf_rows, adapter = run_adaptation(seq, vo, net, cfg, fast, progress)
    timings["adapt_s"] = time.perf_counter() - t
    why = "scheme 'none': no fine-tuning" if cfg.adapt.scheme == "none" else "no keyframe was trained on"
    step_ms = list(getattr(adapter, "step_ms", []) or [])
    kf_ms = list(getattr(adapter, "finetune_ms", []) or [])
    summary.set("timing.finetune_ms", float(np.median(step_ms)) if step_ms else None, why)  # one optimiser step
    summary.set("timing.finetune_kf_ms", float(np.median(kf_ms)) if kf_ms else None, why)  # all steps of a keyframe
    if kf_rows:
        import pandas as pd

        res.atomic_write_text(folder / "keyframes.csv", pd.DataFrame(kf_rows).to_csv(index=False))

    # Global photometric BA with map-point culling: not available in this version.
    n_trig = sum(bool(r.get("run_global_ba")) for r in kf_rows)
    reason = ("global photometric BA with map-point culling is not implemented yet "
              f"(Algorithm 1 requested it {n_trig} time(s))")
    for key in ("trajectory.ate_rmse_m.ba", "map.points.culled", "map.points.ba", "map.esi.culled",
                "map.esi.ba", "timing.ba_s"):
        summary.absent(key, reason)

    # Depth evaluation with the pre-trained and the final model on every frame with GT depth.
    t = time.perf_counter()
    kf_frames = {k.frame_index for k in vo.keyframes}
    cb = (lambda d, n: progress("eval", {"done": d, "total": n})) if progress else None
    table, ms = evaluate_models(seq, net0, None if cfg.adapt.scheme == "none" else net, cfg, fast, kf_frames,
                                out_root / "_cache" / "pretrained", cb)
    evaluated = {k for k in ("pretrained", "adapted") if f"{k}_pcd_lsq" in table}
    timings["eval_s"] = time.perf_counter() - t
    summary.set("timing.depth_ms", ms.get("adapted", ms.get("pretrained")))
    if len(table):
        res.atomic_write_text(folder / "per_frame.csv", table.to_csv(index=False))
    for model in ("pretrained", "adapted"):
        src = model if model in evaluated else "pretrained"
        # all frames (the paper's figure) and frames the adaptation never saw (not keyframes)
        for group, rows, why in (("", table, "no frame with valid GT depth"),
                                 ("_nonkf", table[~table["is_keyframe"]] if len(table) else table,
                                  "no non-keyframe with valid GT depth")):
            for key, val in depth_means(rows, src, group).items():
                summary.set(f"depth.{key}.{model}", val, why)
    if cfg.adapt.scheme == "none":
        summary.notes["depth.pcd.lsq.adapted"] = "scheme 'none': the adapted model is the pre-trained model"
    summary.set("depth.frames_evaluated", int(len(table)))
    if cfg.eval.save_weights and cfg.adapt.scheme != "none":
        from mutualslam_cli.adapt.weights import save_monodepth2

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
    }))
    s = summary.to_dict()
    res.write_json(folder / "summary.json", s)  # last: marks the run complete
    return RunResult(folder, s, timings=timings)

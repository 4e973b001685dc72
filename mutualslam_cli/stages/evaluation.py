"""The depth evaluation stage (DESIGN §7, :func:`run_stage`): the pre-trained and the adapted model
on every frame with GT depth, ``per_frame.csv`` and the ``depth.*`` keys.

The pre-trained model's rows do not depend on the scheme: they are cached per sequence, weights,
evaluation settings and (off the CPU) device (``<results>/_cache/pretrained``) and reused by every
scheme's run. A run builds each model's predictor once (:func:`predictors_for` with the run's memo):
the evaluation's serve the depth export after it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from mutualslam_cli.adapt.inference import resolve_runtime
from mutualslam_cli.adapt.inputs import make_predictor
from mutualslam_cli.adapt.weights import FC_KEYS, save_monodepth2
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.device import describe_device, module_device
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.metrics.ratios import pcd_from_sketch
from mutualslam_cli.online.scores import eval_frames
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Adapted
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.forgetting import summarise_forgetting
from mutualslam_cli.stages.frontend import FrontEnd
from mutualslam_cli.types import Predictor
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)

#: Version of the depth evaluation's protocol (in the pre-trained evaluation's cache key).
#: 2: frames and GT depth are undistorted to the pinhole camera the network is trained in.
#: 3: the sequence's least-squares scale (``pcd_seq_lsq``) and the sums it is made of.
EVAL_VERSION = 3
#: ``eval.*`` settings the pre-trained model's rows do not depend on: left out of their cache key, so runs that
#: differ only in these (``configs/paper.yaml`` scores online, ``configs/fast.yaml`` does not) share the rows.
EVAL_KEYS_NOT_IN_ROWS = ("online", "export_frames", "save_weights", "ate_max_dt")
#: Frames decoded at once in :func:`evaluate_depth`; each model then predicts all of them in turn.
_GROUP = 16
#: Frames the int8 evaluation runtime calibrates its activation ranges on.
CALIBRATION_FRAMES = 8



def eval_batch(cfg: RunConfig, device: torch.device) -> int:
    """``eval.batch``, 0 resolved: 8 frames per forward pass on a GPU, 1 on the CPU (:class:`EvalConfig`)."""
    return cfg.eval.batch or (8 if device.type == "cuda" else 1)


def evaluate_depth(seq: Sequence, predictors: dict[str, Predictor], cfg: RunConfig,
                   keyframe_frames: set[int] | None = None,
                   progress: Callable[[int, int], None] | None = None,
                   batch: int | None = None) -> tuple[pd.DataFrame, dict[str, float]]:
    """Evaluate each model on every ``eval.stride``-th frame that has GT depth.

    Frames and their GT depth are first brought to the pinhole camera the network is trained in
    (:class:`~mutualslam_cli.vo.camera.Undistorter`: the same geometry as the training keyframes;
    without lens distortion this changes nothing).

    Args:
        seq: the sequence (frames streamed one at a time).
        predictors: model name (``pretrained``, ``adapted``) → depth predictor (given pinhole frames).
        cfg: run config (``eval.pcd_threshold``, ``eval.max_depth``, ``eval.stride``).
        keyframe_frames: frame indices that are keyframes (flagged in the table).
        progress: called with ``(done, total)``.
        batch: frames per forward pass (default: ``eval.batch``, 0 meaning 1).

    Returns:
        ``per_frame`` table (one row per evaluated frame: ``frame``, ``timestamp``, ``is_keyframe``,
        ``<model>_pcd_{lsq,median,none,seq_lsq}`` in percent (``seq_lsq``: one least-squares scale
        for all evaluated frames, :mod:`~mutualslam_cli.metrics.depth`), ``<model>_esi``,
        ``<model>_abs_rel``, ``<model>_scale_{lsq,median,seq_lsq}``, ``<model>_sum_{pg,pp}``,
        ``n_valid``, and ``<model>_pcd_lsq_running``), and the median
        prediction time in ms per frame and model (each batch's time over its frames).
    """
    frames = eval_frames(seq, cfg.eval.stride)
    rows = []
    times: dict[str, list[float]] = {k: [] for k in predictors}
    sketches: dict[str, list[np.ndarray | None]] = {k: [] for k in predictors}
    und = Undistorter(seq.intrinsics)
    bs = max(1, batch if batch is not None else cfg.eval.batch)
    group = bs * max(1, _GROUP // bs)
    for start in range(0, len(frames), group):
        # decode a group of frames once, then run one model over all of them before the next:
        # alternating two models frame by frame evicts each one's weights from the CPU caches
        chunk = frames[start:start + group]
        rgbs = [und.image(seq.load_rgb(i)) for i in chunk]
        preds: dict[str, list[np.ndarray]] = {}
        for name, predict in predictors.items():
            preds[name] = []
            for b0 in range(0, len(chunk), bs):  # one forward pass per batch of frames
                t0 = time.perf_counter()
                preds[name].extend(predict(rgbs[b0:b0 + bs]))
                times[name].append((time.perf_counter() - t0) * 1e3 / len(rgbs[b0:b0 + bs]))  # per frame
        for j, i in enumerate(chunk):
            raw_gt = seq.load_depth(i)
            assert raw_gt is not None  # eval_frames: frames with a depth image only
            gt = und.depth(raw_gt)
            row: dict[str, float | int | bool] = {"frame": i, "timestamp": seq.frames[i].timestamp,
                                                   "is_keyframe": bool(keyframe_frames and i in keyframe_frames)}
            for name in predictors:
                m = asdict(dm.depth_stats(preds[name][j], gt, max_depth=cfg.eval.max_depth,
                                          threshold=cfg.eval.pcd_threshold, sketch=True))
                sketches[name].append(m.pop("sketch"))
                row["n_valid"] = m["n_valid"]
                for key, val in m.items():
                    if key != "n_valid":
                        row[f"{name}_{key}"] = val
            rows.append(row)
        if progress:
            progress(start + len(chunk), len(frames))
    # no frame with GT depth (a recording without depth): an empty table with the key columns
    table = pd.DataFrame(rows) if rows else pd.DataFrame(columns=["frame", "timestamp", "is_keyframe", "n_valid"])
    for name in predictors:
        col = f"{name}_pcd_lsq"
        if col in table:
            # one least-squares scale for the whole sequence, then every frame scored under it
            s = dm.sequence_lsq_scale(table[f"{name}_sum_pg"], table[f"{name}_sum_pp"])
            table[f"{name}_pcd_seq_lsq"] = [pcd_from_sketch(k, s, cfg.eval.pcd_threshold) for k in sketches[name]]
            table[f"{name}_scale_seq_lsq"] = s
            table[f"{col}_running"] = dm.running_mean(table[col].to_numpy(dtype=float))
    ms = {k: float(np.median(v)) if v else float("nan") for k, v in times.items()}
    return table, ms


def calibration_frames(seq: Sequence, n: int = CALIBRATION_FRAMES) -> list[np.ndarray]:
    """``n`` frames spread evenly over the sequence (pinhole geometry): the int8 runtime's calibration.

    Inputs only, no labels, and independent of the VO, so a cached pre-trained evaluation stays valid.
    """
    und = Undistorter(seq.intrinsics)
    idx = np.unique(np.linspace(0, len(seq.frames) - 1, min(n, len(seq.frames))).round().astype(int))
    return [und.image(seq.load_rgb(int(i))) for i in idx]


def predictors_for(seq: Sequence, nets: dict[str, torch.nn.Module], cfg: RunConfig, fast: bool,
                   memo: dict[tuple[str, int], Predictor] | None = None) -> dict[str, Predictor]:
    """One batched predictor per model (:func:`~mutualslam_cli.adapt.inputs.make_predictor`), in the runtime the
    config resolves to on the model's device; the int8 runtime is calibrated on :func:`calibration_frames` of
    ``seq`` (read once).

    Args:
        memo: predictors built before, by ``(name, id(model))``; new ones are added (a run's memo lets the
            stages after the evaluation reuse its OpenVINO conversions; the models must not change meanwhile).
    """
    memo = {} if memo is None else memo
    todo = {name: net for name, net in nets.items() if (name, id(net)) not in memo}
    if todo:
        int8 = any(resolve_runtime(cfg.net.runtime, cfg.net.fast, module_device(net)) == "openvino-int8"
                   for net in todo.values())
        calib = calibration_frames(seq) if int8 else None
        memo.update({(name, id(net)): make_predictor(net, cfg.net, fast, calib) for name, net in todo.items()})
    return {name: memo[(name, id(net))] for name, net in nets.items()}


def model_digest(net: torch.nn.Module) -> str:
    """Short SHA-1 of a model's state dict (names and values): the identity of the weights its depth depends on.

    The encoder's ``fc`` is left out: depth never reads it, and a file without it (the default model's) leaves it
    at its random initialisation, which follows the run's seed — with it the pre-trained rows were cached per seed.
    """
    h = hashlib.sha1()
    for k, v in net.state_dict().items():  # on the CPU: the same digest whatever the device
        if k.removeprefix("encoder.") in FC_KEYS:  # DepthNet's keys: encoder.<the encoder file's key>
            continue
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def evaluate_models(seq: Sequence, net0: torch.nn.Module, net: torch.nn.Module | None, cfg: RunConfig, fast: bool,
                    kf_frames: set[int], cache_dir: Path | None = None,
                    progress: Callable[[int, int], None] | None = None,
                    memo: dict[tuple[str, int], Predictor] | None = None) -> tuple[pd.DataFrame, dict[str, float]]:
    """Depth evaluation of the pre-trained model and (unless ``None``) the adapted one.

    The pre-trained model's rows do not depend on the scheme, so they are cached per sequence,
    model weights, evaluation settings and device (a CUDA device's name is in the key; CPU keys are
    those of before devices existed) and reused by every scheme's run.

    Args:
        memo: the run's predictors (:func:`predictors_for`).

    Returns:
        ``(per_frame_table, median_ms_per_prediction)``; the table has an ``is_keyframe`` column.
    """
    device = module_device(net0)
    key = hashlib.sha1(json.dumps({
        "model": model_digest(net0), "net": to_dict(cfg.net), "fast": fast,
        "eval": {k: v for k, v in to_dict(cfg.eval).items() if k not in EVAL_KEYS_NOT_IN_ROWS},
        "runtime": resolve_runtime(cfg.net.runtime, cfg.net.fast, device),
        "version": EVAL_VERSION,
        "root": str(Path(seq.root).resolve()), "frames": [f.timestamp for f in seq.frames],
        **({} if device.type == "cpu" else {"device": describe_device(device)["device_name"]}),
    }, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = Path(cache_dir) / f"{seq.name}-{key}.csv" if cache_dir is not None else None
    cached = pd.read_csv(path) if path is not None and path.is_file() else None
    predictors = predictors_for(seq, {k: m for k, m in (("pretrained", net0 if cached is None else None),
                                                          ("adapted", net)) if m is not None}, cfg, fast, memo)
    ms: dict[str, float]
    if not predictors:  # scheme none with a cached pre-trained evaluation
        assert cached is not None  # net0 is left out only when its rows are cached
        table, ms = cached.copy(), {}
    else:
        table, ms = evaluate_depth(seq, predictors, cfg, kf_frames, progress, eval_batch(cfg, device))
    if cached is None and path is not None and len(table):
        cols = ["frame", "timestamp", "n_valid"] + [c for c in table.columns if c.startswith("pretrained_")]
        atomic_write_text(path, table[cols].to_csv(index=False))
    elif cached is not None and predictors:
        table = cached.merge(table.drop(columns=["timestamp", "n_valid"]), on="frame", how="left")
    table["is_keyframe"] = table["frame"].isin(kf_frames)
    # one column order whether the pre-trained rows were computed now or read from the cache
    head = [c for c in ("frame", "timestamp", "is_keyframe", "n_valid") if c in table]
    models = [c for m in ("pretrained_", "adapted_") for c in table.columns if c.startswith(m)]
    return table[head + models + [c for c in table.columns if c not in head and c not in models]], ms


# ----------------------------------------------------------------------------- the stage


def run_stage(run: RunContext, fe: FrontEnd, net0: torch.nn.Module, adapted: Adapted, fast: bool) -> None:
    """Both models on every ``eval.stride``-th frame with GT depth: ``per_frame.csv``, the keys
    ``timing.depth_ms`` and ``depth.*``, and ``weights/`` with ``eval.save_weights``."""
    cfg = run.cfg
    net = None if cfg.adapt.scheme == "none" else adapted.net
    with run.timed("evaluation"):
        table, ms = evaluate_models(run.seq, net0, net, cfg, fast, {k.frame_index for k in fe.vo.keyframes},
                                    run.cache / "pretrained",
                                    lambda d, n: run.report("eval", {"done": d, "total": n}), run.predictors)
    if adapted.online is not None and len(table):
        table = table.merge(adapted.online, on="frame", how="left")
        table["online_pcd_lsq_running"] = dm.running_mean(table["online_pcd_lsq"].to_numpy(dtype=float))
    if len(table):
        atomic_write_text(run.folder / "per_frame.csv", table.to_csv(index=False))
    no_depth = None if run.seq.has_depth else "the sequence has no depth images (no GT depth)"
    _summarise(run.summary, table, ms, cfg.adapt.scheme, no_depth)
    _summarise_online(run.summary, table, cfg, no_depth)
    summarise_forgetting(run.summary, table, len(run.seq), cfg.adapt.scheme, no_depth)
    run.summary.set("depth.eval_stride", cfg.eval.stride)  # every k-th frame with GT depth was evaluated
    run.summary.set("depth.fast_path", fast)
    if cfg.eval.save_weights and net is not None:
        save_monodepth2(net, run.folder / "weights", cfg.net.height, cfg.net.width)


def depth_means(table: pd.DataFrame, model: str, suffix: str = "") -> dict[str, float | None]:
    """Means over the rows of ``table`` of one model's per-frame depth metrics.

    Args:
        table: per-frame rows of :func:`mutualslam_cli.stages.evaluation.evaluate_depth` (or a selection).
        model: column prefix (``pretrained`` or ``adapted``).
        suffix: appended to the metric name (``_nonkf`` → ``pcd_nonkf.lsq``).

    Returns:
        ``{"pcd<suffix>.{lsq,median,seq_lsq}": %, "pcd_pooled<suffix>.{lsq,median,seq_lsq}": %,
        "esi<suffix>": log units}`` (frame means; ``pcd_pooled``: pooled over pixels); ``None``
        where no row has the value (no frame with valid GT depth).
    """
    def mean(col: str) -> float | None:
        return float(np.nanmean(table[col])) if col in table and table[col].notna().any() else None

    def pooled(col: str) -> float | None:
        v = dm.pooled_mean(table[col], table["n_valid"]) if col in table and len(table) else float("nan")
        return v if np.isfinite(v) else None

    out = {f"pcd{suffix}.{k}": mean(f"{model}_pcd_{k}") for k in ("lsq", "median", "seq_lsq")}
    out.update({f"pcd_pooled{suffix}.{k}": pooled(f"{model}_pcd_{k}") for k in ("lsq", "median", "seq_lsq")})
    out[f"esi{suffix}"] = mean(f"{model}_esi")
    return out


def _summarise(summary: Summary, table: pd.DataFrame, ms: dict[str, float], scheme: str,
               no_depth: str | None = None) -> None:
    """``timing.depth_ms`` and ``depth.{pcd,esi}[_nonkf].*.{pretrained,adapted}`` from the per-frame table.

    All frames (the paper's figure) and the frames the adaptation never saw (not keyframes). For
    scheme ``none`` the adapted values are the pre-trained model's.
    """
    summary.set("timing.depth_ms", ms.get("adapted", ms.get("pretrained")), no_depth or "not computed")
    evaluated = {k for k in ("pretrained", "adapted") if f"{k}_pcd_lsq" in table}
    for model in ("pretrained", "adapted"):
        src = model if model in evaluated else "pretrained"
        for group, rows, why in (("", table, no_depth or "no frame with valid GT depth"),
                                 ("_nonkf", table[~table["is_keyframe"]] if len(table) else table,
                                  no_depth or "no non-keyframe with valid GT depth")):
            for key, val in depth_means(rows, src, group).items():
                summary.set(f"depth.{key}.{model}", val, why)
    if scheme == "none":
        summary.notes["depth.pcd.lsq.adapted"] = "scheme 'none': the adapted model is the pre-trained model"
    summary.set("depth.frames_evaluated", len(table))


def _summarise_online(summary: Summary, table: pd.DataFrame, cfg: RunConfig, no_depth: str | None = None) -> None:
    """``depth.pcd_online[_nonkf].{lsq,median,seq_lsq}`` and ``depth.esi_online``: each frame scored with the
    model of its time (:mod:`~mutualslam_cli.online.scores`), means over frames."""
    if "online_pcd_lsq" in table:
        why = "no frame with valid GT depth"
        for group, rows in (("", table), ("_nonkf", table[~table["is_keyframe"]])):
            for k in ("lsq", "median", "seq_lsq"):
                col = rows[f"online_pcd_{k}"]
                summary.set(f"depth.pcd_online{group}.{k}", float(np.nanmean(col)) if col.notna().any() else None, why)
        esi = table["online_esi"]
        summary.set("depth.esi_online", float(np.nanmean(esi)) if esi.notna().any() else None, why)
        return
    why = (no_depth if no_depth else "eval.online = false" if not cfg.eval.online else
           f"scheme {cfg.adapt.scheme!r} has no keyframe loop to score online" if cfg.adapt.scheme in ("none", "comoda")
           else "no frame with GT depth")
    for group in ("", "_nonkf"):
        for k in ("lsq", "median", "seq_lsq"):
            summary.absent(f"depth.pcd_online{group}.{k}", why)
    summary.absent("depth.esi_online", why)

"""The evaluation stage (DESIGN §7): depth on every frame, trajectory, map.

Each function takes plain inputs (a sequence, a front-end result, models) and returns plain
tables/dicts; :mod:`mutualslam_cli.pipeline` calls them and writes the files.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import torch

from mutualslam_cli.adapt.inference import resolve_runtime
from mutualslam_cli.adapt.inputs import make_predictor
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.associate import MAX_DT
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import MslamError
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.metrics import trajectory as tm
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.vo.result import VOResult
from mutualslam_cli.vo.camera import Undistorter, distort_points

log = logging.getLogger(__name__)

#: Version of the depth evaluation's protocol (in the pre-trained evaluation's cache key).
#: 2: frames and GT depth are undistorted to the pinhole camera the network is trained in.
EVAL_VERSION = 2
#: Frames decoded at once in :func:`evaluate_depth`; each model then predicts all of them in turn.
_GROUP = 16
#: Frames the int8 evaluation runtime calibrates its activation ranges on.
CALIBRATION_FRAMES = 8

Predictor = Callable[[list[np.ndarray]], np.ndarray]
"""``B`` frames ``(H, W, 3)`` uint8 RGB (pinhole geometry) → ``(B, h, w)`` float32 depth at network resolution."""


def eval_frames(seq: Sequence, stride: int) -> list[int]:
    """Indices of the frames the depth evaluation scores: every ``stride``-th frame with GT depth."""
    return [i for i, f in enumerate(seq.frames) if f.depth_path is not None][:: max(1, stride)]


def evaluate_depth(seq: Sequence, predictors: dict[str, Predictor], cfg: RunConfig,
                   keyframe_frames: set[int] | None = None,
                   progress: Callable[[int, int], None] | None = None) -> tuple[pd.DataFrame, dict[str, float]]:
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

    Returns:
        ``per_frame`` table (one row per evaluated frame: ``frame``, ``timestamp``, ``is_keyframe``,
        ``<model>_pcd_{lsq,median,none}`` in percent, ``<model>_esi``, ``<model>_abs_rel``,
        ``<model>_scale_{lsq,median}``, ``n_valid``, and ``<model>_pcd_lsq_running``), and the median
        prediction time in ms per frame and model (each batch's time over its frames).
    """
    frames = eval_frames(seq, cfg.eval.stride)
    rows = []
    times: dict[str, list[float]] = {k: [] for k in predictors}
    und = Undistorter(seq.intrinsics)
    bs = max(1, cfg.eval.batch)
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
            gt = und.depth(seq.load_depth(i))
            row: dict[str, float | int | bool] = {"frame": i, "timestamp": seq.frames[i].timestamp,
                                                   "is_keyframe": bool(keyframe_frames and i in keyframe_frames)}
            for name in predictors:
                m = dm.depth_frame_metrics(preds[name][j], gt, max_depth=cfg.eval.max_depth,
                                           threshold=cfg.eval.pcd_threshold)
                row["n_valid"] = m["n_valid"]
                for key, val in m.items():
                    if key != "n_valid":
                        row[f"{name}_{key}"] = val
            rows.append(row)
        if progress:
            progress(start + len(chunk), len(frames))
    table = pd.DataFrame(rows)
    for name in predictors:
        col = f"{name}_pcd_lsq"
        if col in table:
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


def model_digest(net: torch.nn.Module) -> str:
    """Short SHA-1 of a model's state dict (names and values): the identity of its weights."""
    h = hashlib.sha1()
    for k, v in net.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def evaluate_models(seq: Sequence, net0: torch.nn.Module, net: torch.nn.Module | None, cfg: RunConfig, fast: bool,
                    kf_frames: set[int], cache_dir: Path | None = None,
                    progress: Callable[[int, int], None] | None = None) -> tuple[pd.DataFrame, dict[str, float]]:
    """Depth evaluation of the pre-trained model and (unless ``None``) the adapted one.

    The pre-trained model's rows do not depend on the scheme, so they are cached per sequence,
    model weights and evaluation settings and reused by every scheme's run.

    Returns:
        ``(per_frame_table, median_ms_per_prediction)``; the table has an ``is_keyframe`` column.
    """
    key = hashlib.sha1(json.dumps({
        "model": model_digest(net0), "net": to_dict(cfg.net), "eval": to_dict(cfg.eval), "fast": fast,
        "runtime": resolve_runtime(cfg.net.runtime, cfg.net.fast),
        "version": EVAL_VERSION,
        "root": str(Path(seq.root).resolve()), "frames": [f.timestamp for f in seq.frames],
    }, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = Path(cache_dir) / f"{seq.name}-{key}.csv" if cache_dir is not None else None
    cached = pd.read_csv(path) if path is not None and path.is_file() else None
    calib = calibration_frames(seq) if resolve_runtime(cfg.net.runtime, cfg.net.fast) == "openvino-int8" else None
    predictors = {}
    if cached is None:
        predictors["pretrained"] = make_predictor(net0, cfg, fast, calib)
    if net is not None:
        predictors["adapted"] = make_predictor(net, cfg, fast, calib)
    if not predictors:  # scheme none with a cached pre-trained evaluation
        table, ms = cached.copy(), {}
    else:
        table, ms = evaluate_depth(seq, predictors, cfg, kf_frames, progress)
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


def evaluate_trajectory(seq: Sequence, vo: VOResult, max_dt: float = MAX_DT) -> dict[str, object]:
    """Sim(3)-aligned ATE of keyframes and of all tracked frames against the stored GT.

    Re-initialised front ends (several segments) are aligned per segment (each has its own scale);
    the result then says ``per_segment: True``.

    Returns:
        ``{"kf": AteResult|None, "all": AteResult|None, "notes": {...}}``.
    """
    out: dict[str, object] = {"kf": None, "all": None, "notes": {}}
    notes: dict[str, str] = out["notes"]  # type: ignore[assignment]
    if seq.gt is None or len(seq.gt) == 0:
        notes["trajectory"] = "sequence has no GT poses"
        return out
    kf = vo.traj_kf
    kf_seg = np.array([k.segment for k in vo.keyframes])
    tracked = vo.frame_segment >= 0
    all_seg = vo.frame_segment[tracked] if len(vo.frame_segment) == len(seq) else None
    for key, traj, seg in (("kf", kf, kf_seg), ("all", vo.traj_all, all_seg)):
        if len(traj) < 3:
            notes[key] = f"only {len(traj)} poses"
            continue
        try:
            if seg is not None and len(seg) == len(traj) and len(np.unique(seg)) > 1:
                out[key] = tm.ate_segments(seq.gt, traj, seg, max_dt=max_dt)
            else:
                out[key] = tm.ate(seq.gt, traj, align="sim3", max_dt=max_dt)
        except MslamError as e:
            notes[key] = str(e)
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


def esi_of_log_errors(d: np.ndarray) -> tuple[float, int]:
    """e_si of per-point log errors ``d`` ``(P,)`` (NaN = no GT): the population standard deviation
    of the finite ones, :func:`~mutualslam_cli.metrics.depth.esi`'s formula.

    Returns:
        ``(e_si, n_finite)``; e_si is NaN when no value is finite.
    """
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return float("nan"), 0
    return float(np.sqrt(np.mean((d - d.mean()) ** 2))), int(d.size)


def map_esi(seq: Sequence, vo: VOResult, keep: np.ndarray | None = None) -> tuple[float, int]:
    """e_si of map-point depths in their host keyframe against GT depth at the host pixel
    (:func:`map_log_depth_errors` then :func:`esi_of_log_errors`).

    Args:
        keep: optional boolean mask over ``vo.points`` (e.g. after culling).
    Returns:
        ``(e_si, n_points_with_gt)``; e_si is NaN when no point has GT depth.
    """
    return esi_of_log_errors(map_log_depth_errors(seq, vo, keep))


# ----------------------------------------------------------------------------- summary keys


def set_ate(summary: Summary, traj: dict[str, Any], names: dict[str, str]) -> None:
    """RMSE of :func:`~mutualslam_cli.stages.evaluation.evaluate_trajectory`'s ``kf``/``all`` under ``names``."""
    for key, name in names.items():
        r = traj[key]
        if r is None:
            summary.absent(name, traj["notes"].get(key, traj["notes"].get("trajectory", "not computed")))
        else:
            summary.set(name, float(r.rmse))
            if getattr(r, "note", None):  # re-initialised VO: each segment aligned on its own
                summary.notes[name] = r.note


def depth_means(table: pd.DataFrame, model: str, suffix: str = "") -> dict[str, float | None]:
    """Means over the rows of ``table`` of one model's per-frame depth metrics.

    Args:
        table: per-frame rows of :func:`mutualslam_cli.stages.evaluation.evaluate_depth` (or a selection).
        model: column prefix (``pretrained`` or ``adapted``).
        suffix: appended to the metric name (``_nonkf`` → ``pcd_nonkf.lsq``).

    Returns:
        ``{"pcd<suffix>.lsq": %, "pcd<suffix>.median": %, "esi<suffix>": log units}``; ``None``
        where no row has the value (no frame with valid GT depth).
    """
    def mean(col: str) -> float | None:
        return float(np.nanmean(table[col])) if col in table and table[col].notna().any() else None

    return {f"pcd{suffix}.lsq": mean(f"{model}_pcd_lsq"), f"pcd{suffix}.median": mean(f"{model}_pcd_median"),
            f"esi{suffix}": mean(f"{model}_esi")}


def summarise_depth(summary: Summary, table: pd.DataFrame, ms: dict[str, float], scheme: str) -> None:
    """``timing.depth_ms`` and ``depth.{pcd,esi}[_nonkf].*.{pretrained,adapted}`` from the per-frame table.

    All frames (the paper's figure) and the frames the adaptation never saw (not keyframes). For
    scheme ``none`` the adapted values are the pre-trained model's.
    """
    summary.set("timing.depth_ms", ms.get("adapted", ms.get("pretrained")))
    evaluated = {k for k in ("pretrained", "adapted") if f"{k}_pcd_lsq" in table}
    for model in ("pretrained", "adapted"):
        src = model if model in evaluated else "pretrained"
        for group, rows, why in (("", table, "no frame with valid GT depth"),
                                 ("_nonkf", table[~table["is_keyframe"]] if len(table) else table,
                                  "no non-keyframe with valid GT depth")):
            for key, val in depth_means(rows, src, group).items():
                summary.set(f"depth.{key}.{model}", val, why)
    if scheme == "none":
        summary.notes["depth.pcd.lsq.adapted"] = "scheme 'none': the adapted model is the pre-trained model"
    summary.set("depth.frames_evaluated", int(len(table)))

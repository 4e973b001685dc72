"""Score another depth network's saved predictions exactly as ``mslam run`` scores ours.

:func:`eval_depth` (``mslam eval-depth``) scores the frames :func:`~mutualslam_cli.stages.evaluation.evaluate_depth`
scores (every ``eval.stride``-th frame with GT depth, after ``data.max_frames``/``data.stride``) with
the same :func:`~mutualslam_cli.metrics.depth.depth_frame_metrics` (PCD lsq / median / none, e_si).

**Files** and the **matching rule** of predictions to frames: :mod:`mutualslam_cli.datasets.predictions`.

**Resolution and geometry.** Predictions are of the raw RGB images: each is resized bilinearly to
the raw GT depth resolution, then remapped to the pinhole camera by the same
:class:`~mutualslam_cli.vo.camera.Undistorter` (nearest pixel) as the GT — where ``mslam run``
compares (without lens distortion nothing changes).

**Kinds.** ``depth`` as is and ``inverse`` as ``1/x`` (0 = no prediction; negative values are
errors); ``relative-inverse`` (MiDaS) aligned per frame by least-squares scale and shift in inverse
depth against ``1/GT``, then inverted (:func:`~mutualslam_cli.metrics.depth.align_inverse_depth`).
NaN or infinite values are errors.

**Result folder** ``<out>/<seq>/<NAME>/seed0/`` (NAME in the scheme's place, so no scheme's name):
``config.yaml`` (the resolved config: ``data``/``eval`` chose and scored the frames; the model's own
settings go to ``external.*`` in ``summary.json`` and the manifest, because
:func:`mutualslam_cli.report.collect` splits runs whose ``config.yaml`` keys differ), ``manifest.json``,
``per_frame.csv``, and last ``summary.json``. The scores sit where a run keeps its final model's
(``adapted_*`` columns, ``depth.*.adapted``); ``pretrained`` ones are null with a reason.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mutualslam_cli.adapt.schemes import SCHEMES
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.config import RunConfig, load_config, to_dict, with_overrides
from mutualslam_cli.datasets.predictions import match_predictions, prediction_files, read_prediction, rgb_name
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import ConfigError, DatasetError
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.online.scores import eval_frames
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.run_folder import is_complete, manifest, run_dir, write_json, write_yaml
from mutualslam_cli.results.staging import staged
from mutualslam_cli.results.summary import SUMMARY_KEYS, RunSummary, Summary, read_summary
from mutualslam_cli.results.writable import check_output_folder, write_errors
from mutualslam_cli.stages.evaluation import depth_means
from mutualslam_cli.vo.camera import Undistorter

KINDS: tuple[str, ...] = ("depth", "inverse", "relative-inverse")
MODEL = "adapted"
"""Column prefix / summary leaf of the scored model: where the report reads a run's final model."""


@dataclass
class ExternalResult:
    """What :func:`eval_depth` returns: the result folder, its ``summary.json`` and whether it was skipped."""

    folder: Path
    summary: RunSummary
    skipped: bool = False


# ----------------------------------------------------------------------------- reading files


def check_values(x: np.ndarray, kind: str, path: Path) -> None:
    """Non-finite values are errors for every kind; negative ones for ``depth`` and ``inverse``."""
    bad = int(np.count_nonzero(~np.isfinite(x)))
    if bad:
        raise DatasetError(f"{path}: {bad} of {x.size} values are NaN or infinite; a {kind} prediction must be "
                           "finite" + (" (0 = no prediction)" if kind != "relative-inverse" else ""))
    if kind != "relative-inverse" and (neg := int(np.count_nonzero(x < 0))):
        raise DatasetError(f"{path}: {neg} of {x.size} values are negative; a {kind} prediction must be >= 0 "
                           "(0 = no prediction; use --kind relative-inverse for outputs known up to scale and shift)")


# ----------------------------------------------------------------------------- matching files to frames


def to_depth(x: np.ndarray, kind: str, gt: np.ndarray, max_depth: float) -> tuple[np.ndarray, float, float]:
    """A prediction ``x`` ``(H, W)`` at GT resolution → ``(depth (H, W) metres or model units, s, t)``.

    ``s``, ``t``: the scale and shift of the ``relative-inverse`` alignment (NaN for other kinds).
    """
    if kind == "depth":
        return x, float("nan"), float("nan")
    if kind == "inverse":
        with np.errstate(divide="ignore"):
            return np.where(x > 0, 1.0 / x, 0.0), float("nan"), float("nan")  # 0 = no prediction
    return dm.align_inverse_depth(x, gt, max_depth)


def score_predictions(seq: Sequence, files: dict[int, Path], kind: str, cfg: RunConfig, scale: float = 1.0,
                      npz_key: str | None = None,
                      progress: Callable[[int, int], None] | None = None) -> pd.DataFrame:
    """Per-frame metrics of matched predictions: one row per frame (frame order) with ``frame``,
    ``timestamp``, ``is_keyframe`` (False), ``n_valid``, ``adapted_{pcd_lsq,pcd_median,pcd_none}`` (%),
    ``adapted_{esi,abs_rel,scale_lsq,scale_median}``, ``adapted_align_{scale,shift}`` (relative-inverse),
    ``prediction`` (file name), ``adapted_pcd_lsq_running`` — ``per_frame.csv``'s layout.

    Raises :class:`DatasetError` for a file that cannot be read, holds bad values, or has another size
    than the first frame's (or the image's size transposed)."""
    und = Undistorter(seq.intrinsics)
    frames = sorted(files)
    rows: list[dict] = []
    first: tuple[tuple[int, int], Path] | None = None
    for n, i in enumerate(frames):
        path = files[i]
        x = read_prediction(path, scale, npz_key)
        if first is None:
            first = (x.shape, path)
            w, h = seq.intrinsics.width, seq.intrinsics.height
            if x.shape == (w, h) and w != h:
                raise DatasetError(f"{path} (frame {i}, {rgb_name(seq, i)}): prediction is {x.shape[0]}×{x.shape[1]} "
                                   f"(rows×columns), the image {h}×{w}: stored transposed?")
        elif x.shape != first[0]:
            raise DatasetError(f"{path} (frame {i}, {rgb_name(seq, i)}): prediction is {x.shape[0]}×{x.shape[1]} "
                               f"but {first[1].name} is {first[0][0]}×{first[0][1]}; every frame must be predicted "
                               "at one size")
        check_values(x, kind, path)
        raw = seq.load_depth(i)
        if raw is None:  # eval_frames keeps frames with a depth file only
            raise DatasetError(f"frame {i} ({rgb_name(seq, i)}): no GT depth to score against")
        x = und.depth(dm.resize_to(x, raw.shape))  # the raw image's resolution, then its pinhole geometry
        gt = und.depth(raw)
        depth, s, t = to_depth(x, kind, gt, cfg.eval.max_depth)
        m = dm.depth_frame_metrics(depth, gt, max_depth=cfg.eval.max_depth, threshold=cfg.eval.pcd_threshold)
        row: dict = {"frame": i, "timestamp": seq.frames[i].timestamp, "is_keyframe": False, "n_valid": m["n_valid"]}
        row.update({f"{MODEL}_{k}": v for k, v in m.items() if k != "n_valid"})
        if kind == "relative-inverse":
            row.update({f"{MODEL}_align_scale": s, f"{MODEL}_align_shift": t})
        row["prediction"] = path.name
        rows.append(row)
        if progress:
            progress(n + 1, len(frames))
    table = pd.DataFrame(rows)
    if len(table):
        table[f"{MODEL}_pcd_lsq_running"] = dm.running_mean(table[f"{MODEL}_pcd_lsq"].to_numpy(dtype=float))
    return table


# ----------------------------------------------------------------------------- the result folder


def check_name(name: str) -> None:
    """NAME must be a plain folder name and no scheme's (it takes a scheme's place); else :class:`ConfigError`."""
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", name or ""):
        raise ConfigError(f"--name {name!r}: expected letters, digits and . _ + - (a folder name)")
    if name in SCHEMES or name in ("pretrained", "adapted"):
        raise ConfigError(f"--name {name!r} is the name of one of our models; choose another (e.g. midas-{name})")


def eval_depth(sequence: str | Path | Sequence, predictions: str | Path, name: str, kind: str = "depth",
               cfg: RunConfig | None = None, scale: float = 1.0, out: str | Path | None = None,
               ext: str | None = None, npz_key: str | None = None, command: list[str] | None = None,
               force: bool = False, progress: Callable[[int, int], None] | None = None,
               registry: Path | None = None) -> ExternalResult:
    """Score a folder of predictions and write ``<out>/<seq>/<name>/seed0/`` (module docstring).

    Args:
        sequence: a ``datasets.yaml`` name, a folder, or a loaded :class:`Sequence`.
        predictions: the folder of per-frame files; ``name``: the model (the report's scheme column).
        kind: ``depth`` | ``inverse`` | ``relative-inverse``; ``scale`` multiplies every stored value.
        cfg: resolved config (``data.*`` picks the frames, ``eval.*`` scores them); default config if None.
        out: results root (default ``cfg.out``); ``ext``: the format to read; ``npz_key``: the array in ``.npz``.
        command: recorded in ``manifest.json``; ``force``: rescore a complete result;
        progress: ``progress(done, total)`` per frame; ``registry``: another ``datasets.yaml``.

    Raises:
        ConfigError: bad ``name``, ``kind``, ``scale`` or ``ext``.
        DatasetError: from :func:`prediction_files`, :func:`match_predictions`, :func:`score_predictions`.
        ResultsLocked: another process works in the result folder.
    """
    t0 = time.perf_counter()
    check_name(name)
    if kind not in KINDS:
        raise ConfigError(f"--kind {kind!r}: expected one of {', '.join(KINDS)}")
    if not (np.isfinite(scale) and scale > 0):
        raise ConfigError(f"--scale {scale!r}: expected a positive number")
    cfg = cfg if cfg is not None else load_config()
    cfg = with_overrides(cfg, adapt={"scheme": "none"}, seed=0)  # what the written config says: no adaptation
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(
        sequence, data_root=cfg.data.data_root, registry_path=registry,
        max_frames=cfg.data.max_frames, stride=cfg.data.stride)
    root = check_output_folder(out if out is not None else cfg.out)  # a file, read-only: before any work
    folder = run_dir(root, seq.name, name, 0)
    if is_complete(folder) and not force:
        return ExternalResult(folder, read_summary(folder), skipped=True)
    frames = eval_frames(seq, cfg.eval.stride)
    if not frames:
        raise DatasetError(f"{seq.root}: no frame has GT depth; nothing to score")
    files = match_predictions(seq, frames, prediction_files(predictions, ext))  # every file found before any work
    kept = "the previous result in it is as it was" if is_complete(folder) else "nothing of it was kept"
    # the folder changes only when the scoring completes (results/staging.py): a failed --force keeps the old one
    with write_errors(root, kept), hold_lock(folder, "mslam eval-depth", beside=True), staged(folder) as stage, \
            write_errors(root, kept):
        table = score_predictions(seq, files, kind, cfg, scale, npz_key, progress)
        info = {"model": name, "kind": kind, "scale": scale, "predictions": str(Path(predictions).resolve()),
                "ext": files[frames[0]].suffix.lstrip("."), "npz_key": npz_key,
                "alignment": "per-frame least-squares scale and shift in inverse depth (MiDaS)"
                if kind == "relative-inverse" else "none"}
        write_yaml(stage / "config.yaml", to_dict(cfg))
        atomic_write_text(stage / "per_frame.csv", table.to_csv(index=False))
        summary = _summary(table, seq, name, info, cfg)
        timings = {"total_s": time.perf_counter() - t0}
        write_json(stage / "manifest.json", manifest(command, 0, timings, {
            "sequence": {"name": seq.name, "root": str(seq.root), "frames": len(seq), "meta": seq.meta,
                         "intrinsics": seq.intrinsics.as_list()},
            "external": info}))
        data = summary.to_dict()
        write_json(stage / "summary.json", data)  # last: marks the result complete
    return ExternalResult(folder, RunSummary.parse(data, str(folder / "summary.json")))


def _summary(table: pd.DataFrame, seq: Sequence, name: str, info: dict, cfg: RunConfig) -> Summary:
    """``summary.json`` of an external model: its scores as ``depth.*.adapted``, everything else null with a reason."""
    s = Summary()
    why = "no frame with valid GT depth"
    for key, val in depth_means(table, MODEL).items():
        s.set(f"depth.{key}.{MODEL}", val, why)
        s.absent(f"depth.{key}.pretrained", f"external model {name!r}: not adapted, so no pre-trained/adapted pair; "
                 f"its scores are depth.{key}.adapted")
    for key in ("pcd.seq_lsq", "pcd_pooled.seq_lsq", "pcd_nonkf.seq_lsq", "pcd_pooled_nonkf.seq_lsq"):
        if f"{MODEL}_pcd_seq_lsq" not in table:
            s.absent(f"depth.{key}.{MODEL}", "external models are scored with per-frame scales only")
    none = table[f"{MODEL}_pcd_none"]
    s.set(f"depth.pcd.none.{MODEL}", float(none.mean()) if none.notna().any() else None, why)
    for key in SUMMARY_KEYS:
        if key.startswith("depth.pcd_nonkf") or key.startswith("depth.esi_nonkf"):
            s.absent(key, "external model: not adapted, so no keyframes to leave out (every frame is unseen: "
                          "see depth.pcd / depth.esi)")
        elif not key.startswith("depth."):
            s.absent(key, "mslam eval-depth scores depth predictions only (no front end, map, BA or timing)")
    if 0 < (bad := int(table[f"{MODEL}_pcd_lsq"].isna().sum())) < len(table):
        s.notes[f"depth.pcd.lsq.{MODEL}"] = (f"{bad} of {len(table)} frames have no score (no valid pixel, or no "
                                             "scale-and-shift fit) and are left out of the means")
    s.set("depth.frames_evaluated", len(table))
    s.set("depth.eval_stride", cfg.eval.stride)
    for k, v in info.items():
        if v is not None:
            s.set(f"external.{k}", v)
    s.set("sequence.name", seq.name)
    s.set("sequence.frames", len(seq))
    s.set("scheme", name)
    s.set("seed", 0)
    return s

"""Score another depth network's saved predictions exactly as ``mslam run`` scores ours (issue 12).

:func:`eval_depth` (``mslam eval-depth``) scores the frames :func:`~mutualslam_cli.stages.evaluation.evaluate_depth`
scores (every ``eval.stride``-th frame with GT depth, after ``data.max_frames``/``data.stride``) with
the same :func:`~mutualslam_cli.metrics.depth.depth_frame_metrics` (PCD lsq / median / none, e_si).

**Files**, one per frame in ``PRED_DIR`` (not recursive): ``.npy``; ``.npz`` (its only array or
``npz_key``); 16-bit single-channel ``.png``; ``.pfm`` as MiDaS writes it (``Pf``, ``width height``,
a scale whose sign is the byte order — negative little-endian — and whose magnitude MiDaS's reader
ignores, then float32 rows from the image's **bottom** row up). Maps ``(H, W)``, ``(1, H, W)`` or
``(H, W, 1)``; every value × ``scale``. A folder with several formats (MiDaS writes a ``.pfm`` and a
``.png`` per frame) needs ``ext``.

**Matching rule.** A file belongs to a frame when its name without the extension is the frame's RGB
file stem, or that stem + ``-`` + anything (MiDaS 3.1: ``<stem>-<model_type>.pfm``), or a decimal
number (alone or before a ``-``) within :data:`MATCH_DT` of the frame's timestamp
(``1305031102.175304.npy``; ICL-NUIM's timestamps are frame numbers: ``0.npy``). Each scored frame
needs exactly one file: none or several is an error naming the frame, its RGB file and the names
looked for (or found). Files of frames not scored are ignored.

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
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.config import RunConfig, load_config, to_dict, with_overrides
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import ConfigError, DatasetError
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.run_folder import is_complete, manifest, read_summary, run_dir, write_json, write_yaml
from mutualslam_cli.results.summary import SUMMARY_KEYS, Summary
from mutualslam_cli.stages.evaluation import depth_means, eval_frames
from mutualslam_cli.vo.camera import Undistorter

KINDS: tuple[str, ...] = ("depth", "inverse", "relative-inverse")
EXTENSIONS: tuple[str, ...] = ("npy", "npz", "png", "pfm")
MATCH_DT = 1e-4
"""Seconds within which a file named by a number matches a frame's timestamp (frames are ≥ 10 ms apart)."""
MODEL = "adapted"
"""Column prefix / summary leaf of the scored model: where the report reads a run's final model."""
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


@dataclass
class ExternalResult:
    """What :func:`eval_depth` returns: the result folder, its ``summary.json`` and whether it was skipped."""

    folder: Path
    summary: dict
    skipped: bool = False


# ----------------------------------------------------------------------------- reading files


def read_pfm(path: str | Path) -> np.ndarray:
    """A PFM file (as MiDaS's ``write_pfm`` writes it) → ``(H, W)`` (``Pf``) or ``(H, W, 3)`` (``PF``)
    float32, top row first. Raises :class:`DatasetError` for a bad header or a wrong number of bytes."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.readline().strip()
        if magic not in (b"Pf", b"PF"):
            raise DatasetError(f"{path}: not a PFM file (first line {magic[:20]!r}; expected 'Pf' or 'PF')")
        dims = f.readline().split()
        if len(dims) == 1:  # some writers put the height on a line of its own
            dims += f.readline().split()
        try:
            w, h = (int(v) for v in dims)
            scale = float(f.readline())
            if w <= 0 or h <= 0 or scale == 0:
                raise ValueError
        except ValueError:
            raise DatasetError(f"{path}: malformed PFM header (expected 'width height' then a non-zero scale, "
                               "negative for little-endian)") from None
        data = f.read()
    c = 3 if magic == b"PF" else 1
    need = w * h * c * 4
    if len(data) != need:
        raise DatasetError(f"{path}: {len(data)} bytes of samples, expected {need} ({w}×{h}×{c} float32)")
    a = np.frombuffer(data, dtype="<f4" if scale < 0 else ">f4").reshape((h, w, 3) if c == 3 else (h, w))
    return np.flipud(a)  # PFM rows run from the bottom of the image up


def read_prediction(path: str | Path, scale: float = 1.0, npz_key: str | None = None) -> np.ndarray:
    """One prediction file → ``(H, W)`` float64 map, every value × ``scale``.

    Raises :class:`DatasetError`: unreadable, unknown extension, ``.npz`` without one array (or
    ``npz_key``), PNG not 16-bit single-channel, not numbers, or not one map."""
    path = Path(path)
    ext = path.suffix.lower().lstrip(".")
    try:
        if ext == "npy":
            a = np.load(path, allow_pickle=False)
        elif ext == "npz":
            with np.load(path, allow_pickle=False) as z:
                keys = list(z.files)
                key = npz_key if npz_key is not None else (keys[0] if len(keys) == 1 else None)
                if key not in keys:
                    want = f"no array {npz_key!r}" if npz_key is not None else f"{len(keys)} arrays"
                    raise DatasetError(f"{path}: {want} (it holds {', '.join(keys) or 'none'}); "
                                       "name the prediction's array with --key")
                a = z[key]
        elif ext == "png":
            a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if a is None:
                raise DatasetError(f"{path}: cannot read PNG")
            if a.dtype != np.uint16 or a.ndim != 2:
                ch = 1 if a.ndim == 2 else a.shape[2]
                raise DatasetError(f"{path}: PNG is {a.dtype} with {ch} channel(s); expected a 16-bit "
                                   "single-channel PNG (values × --scale); for MiDaS use its .pfm files")
        elif ext == "pfm":
            a = read_pfm(path)
        else:
            raise DatasetError(f"{path}: unknown prediction format '.{ext}'; expected one of "
                               f"{', '.join('.' + e for e in EXTENSIONS)}")
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: cannot read ({e})") from None
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise DatasetError(f"{path}: holds {a.dtype} values; expected numbers (a depth or inverse-depth map)")
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    while a.ndim > 2 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise DatasetError(f"{path}: shape {a.shape}; expected one map (H, W), (1, H, W) or (H, W, 1)")
    return a.astype(np.float64) * scale


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


def prediction_files(folder: str | Path, ext: str | None = None) -> list[Path]:
    """The prediction files of ``folder`` in one format (``ext``, or the only one present).

    Raises :class:`ConfigError` for an unknown ``ext``, :class:`DatasetError` for no folder, no
    prediction file, or several formats and no ``ext``."""
    folder = Path(folder)
    if ext is not None and ext.lower().lstrip(".") not in EXTENSIONS:
        raise ConfigError(f"--ext {ext!r}: expected one of {', '.join(EXTENSIONS)}")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such predictions folder")
    every = [p for p in sorted(folder.iterdir()) if p.is_file() and not p.name.startswith(".")]
    files = [p for p in every if p.suffix.lower().lstrip(".") in EXTENSIONS]
    found = Counter(p.suffix.lower().lstrip(".") for p in files)
    if ext is not None:
        files = [p for p in files if p.suffix.lower().lstrip(".") == ext.lower().lstrip(".")]
    elif len(found) > 1:
        kinds = ", ".join(f"{n} .{e}" for e, n in sorted(found.items()))
        raise DatasetError(f"{folder}: holds predictions in several formats ({kinds}); choose one with --ext "
                           "(MiDaS: --ext pfm, its .png files are renderings of the same maps)")
    if not files:
        other = Counter(p.suffix.lower() or "(none)" for p in every)
        seen = ", ".join(f"{n} {e}" for e, n in sorted(other.items())) or "nothing"
        raise DatasetError(f"{folder}: no prediction files {'.' + ext if ext else '(' + ', '.join(EXTENSIONS) + ')'}"
                           f" (found {seen})")
    return files


def _keys(stem: str) -> list[str]:
    """A file stem and each prefix of it before a ``-`` (``a-b-c`` → ``a-b-c``, ``a``, ``a-b``)."""
    return [stem] + [stem[:i] for i, c in enumerate(stem) if c == "-" and i > 0]


def match_predictions(seq: Sequence, frames: list[int], files: list[Path]) -> dict[int, Path]:
    """One file per frame in ``frames`` by the module's matching rule. Raises :class:`DatasetError`
    for a frame with none (the first one named, the others counted), with several, or a file of two frames."""
    by_key: dict[str, list[Path]] = {}
    numbers: list[tuple[float, Path]] = []
    for p in files:
        for k in _keys(p.stem):
            by_key.setdefault(k, []).append(p)
            if _NUMBER.fullmatch(k):
                numbers.append((float(k), p))
    numbers.sort(key=lambda v: v[0])
    values = np.array([v for v, _ in numbers])
    out: dict[int, Path] = {}
    owner: dict[Path, int] = {}
    missing: list[int] = []
    for i in frames:
        f = seq.frames[i]
        cands = set(by_key.get(Path(f.rgb_path).stem, []))
        lo = int(np.searchsorted(values, f.timestamp - MATCH_DT, side="left"))
        hi = int(np.searchsorted(values, f.timestamp + MATCH_DT, side="right"))
        cands.update(p for _, p in numbers[lo:hi])
        if not cands:
            missing.append(i)
        elif len(cands) > 1:
            names = ", ".join(sorted(p.name for p in cands))
            raise DatasetError(f"frame {i} ({_rgb_name(seq, i)}): {len(cands)} prediction files match it ({names}); "
                               "keep one per frame (or choose a format with --ext)")
        else:
            (p,) = cands
            if p in owner:
                raise DatasetError(f"{p}: matches frames {owner[p]} and {i} ({_rgb_name(seq, owner[p])}, "
                                   f"{_rgb_name(seq, i)}); name each prediction after one frame")
            owner[p] = i
            out[i] = p
    if missing:
        i = missing[0]
        stem, t = Path(seq.frames[i].rgb_path).stem, seq.frames[i].timestamp
        suffix = files[0].suffix if len({p.suffix for p in files}) == 1 else ".<ext>"
        more = f"; {len(missing) - 1} more frame(s) have none" if len(missing) > 1 else ""
        raise DatasetError(f"{files[0].parent}: no prediction for frame {i} ({_rgb_name(seq, i)}, t={t:.6f}): looked "
                           f"for {stem}{suffix}, {stem}-*{suffix} or a file named by its timestamp {t:.6f}{more}")
    return out


def _rgb_name(seq: Sequence, i: int) -> str:
    """Frame ``i``'s RGB file, relative to the sequence folder when inside it."""
    p = Path(seq.frames[i].rgb_path)
    try:
        return str(p.relative_to(seq.root))
    except ValueError:
        return str(p)


# ----------------------------------------------------------------------------- scoring


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
                raise DatasetError(f"{path} (frame {i}, {_rgb_name(seq, i)}): prediction is {x.shape[0]}×{x.shape[1]} "
                                   f"(rows×columns), the image {h}×{w}: stored transposed?")
        elif x.shape != first[0]:
            raise DatasetError(f"{path} (frame {i}, {_rgb_name(seq, i)}): prediction is {x.shape[0]}×{x.shape[1]} "
                               f"but {first[1].name} is {first[0][0]}×{first[0][1]}; every frame must be predicted "
                               "at one size")
        check_values(x, kind, path)
        raw = seq.load_depth(i)
        if raw is None:  # eval_frames keeps frames with a depth file only
            raise DatasetError(f"frame {i} ({_rgb_name(seq, i)}): no GT depth to score against")
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
    from mutualslam_cli.adapt.schemes import SCHEMES

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
    folder = run_dir(Path(out if out is not None else cfg.out), seq.name, name, 0)
    if is_complete(folder) and not force:
        return ExternalResult(folder, read_summary(folder), skipped=True)
    frames = eval_frames(seq, cfg.eval.stride)
    if not frames:
        raise DatasetError(f"{seq.root}: no frame has GT depth; nothing to score")
    files = match_predictions(seq, frames, prediction_files(predictions, ext))  # every file found before any work
    with hold_lock(folder, "mslam eval-depth"):
        (folder / "summary.json").unlink(missing_ok=True)  # a forced rescore is incomplete until its summary
        table = score_predictions(seq, files, kind, cfg, scale, npz_key, progress)
        info = {"model": name, "kind": kind, "scale": scale, "predictions": str(Path(predictions).resolve()),
                "ext": files[frames[0]].suffix.lstrip("."), "npz_key": npz_key,
                "alignment": "per-frame least-squares scale and shift in inverse depth (MiDaS)"
                if kind == "relative-inverse" else "none"}
        write_yaml(folder / "config.yaml", to_dict(cfg))
        atomic_write_text(folder / "per_frame.csv", table.to_csv(index=False))
        summary = _summary(table, seq, name, info, cfg)
        timings = {"total_s": time.perf_counter() - t0}
        write_json(folder / "manifest.json", manifest(command, 0, timings, {
            "sequence": {"name": seq.name, "root": str(seq.root), "frames": len(seq), "meta": seq.meta,
                         "intrinsics": seq.intrinsics.as_list()},
            "external": info}))
        s = summary.to_dict()
        write_json(folder / "summary.json", s)  # last: marks the result complete
    return ExternalResult(folder, s)


def _summary(table: pd.DataFrame, seq: Sequence, name: str, info: dict, cfg: RunConfig) -> Summary:
    """``summary.json`` of an external model: its scores as ``depth.*.adapted``, everything else null with a reason."""
    s = Summary()
    why = "no frame with valid GT depth"
    for key, val in depth_means(table, MODEL).items():
        s.set(f"depth.{key}.{MODEL}", val, why)
        s.absent(f"depth.{key}.pretrained", f"external model {name!r}: not adapted, so no pre-trained/adapted pair; "
                 f"its scores are depth.{key}.adapted")
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
    s.set("depth.frames_evaluated", int(len(table)))
    s.set("depth.eval_stride", cfg.eval.stride)
    for k, v in info.items():
        if v is not None:
            s.set(f"external.{k}", v)
    s.set("sequence.name", seq.name)
    s.set("sequence.frames", len(seq))
    s.set("scheme", name)
    s.set("seed", 0)
    return s

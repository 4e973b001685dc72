"""Another depth network's saved predictions on disk: the file formats and which file is which frame's.

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
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import ConfigError, DatasetError

EXTENSIONS: tuple[str, ...] = ("npy", "npz", "png", "pfm")
MATCH_DT = 1e-4
"""Seconds within which a file named by a number matches a frame's timestamp (frames are ≥ 10 ms apart)."""
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


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
            raise DatasetError(f"frame {i} ({rgb_name(seq, i)}): {len(cands)} prediction files match it ({names}); "
                               "keep one per frame (or choose a format with --ext)")
        else:
            (p,) = cands
            if p in owner:
                raise DatasetError(f"{p}: matches frames {owner[p]} and {i} ({rgb_name(seq, owner[p])}, "
                                   f"{rgb_name(seq, i)}); name each prediction after one frame")
            owner[p] = i
            out[i] = p
    if missing:
        i = missing[0]
        stem, t = Path(seq.frames[i].rgb_path).stem, seq.frames[i].timestamp
        suffix = files[0].suffix if len({p.suffix for p in files}) == 1 else ".<ext>"
        more = f"; {len(missing) - 1} more frame(s) have none" if len(missing) > 1 else ""
        raise DatasetError(f"{files[0].parent}: no prediction for frame {i} ({rgb_name(seq, i)}, t={t:.6f}): looked "
                           f"for {stem}{suffix}, {stem}-*{suffix} or a file named by its timestamp {t:.6f}{more}")
    return out


def rgb_name(seq: Sequence, i: int) -> str:
    """Frame ``i``'s RGB file, relative to the sequence folder when inside it."""
    p = Path(seq.frames[i].rgb_path)
    try:
        return str(p.relative_to(seq.root))
    except ValueError:
        return str(p)


# ----------------------------------------------------------------------------- scoring

"""One sequence of a Microsoft 7-Scenes scene zip → the TUM layout (``mslam datasets download``, ``layout: 7scenes``).

A scene zip (e.g. ``redkitchen.zip``) holds one nested ``seq-NN.zip`` per sequence (or, unzipped,
``seq-NN/`` folders) with ``frame-XXXXXX.color.png``, ``.depth.png`` and ``.pose.txt``. The chosen
sequence becomes ``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt`` (timestamps index / 30 s) and
``groundtruth.txt`` (quaternions of the 4×4 camera-to-world poses); depth stays in millimetres with
the invalid value 65535 set to 0.

Written through the same :class:`~mutualslam_cli.datasets.download.limits.Budget` as any archive: every member
streamed to disk within the limits (the nested zip too, then its own members), file names made from the
frame index (never taken from the archive), a pose file read at most :data:`MAX_POSE_BYTES`, a depth
image decoded only when its PNG header says at most :data:`MAX_DEPTH_PIXELS` pixels.
"""

from __future__ import annotations

import re
import zipfile
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from mutualslam_cli.datasets.download.limits import Budget
from mutualslam_cli.datasets.download.members import check_zip_member, open_zip, reading_archive
from mutualslam_cli.errors import CorruptArchive, DatasetError
from mutualslam_cli.geometry import rot_to_quat

SEVEN_SCENES_FPS = 30.0
"""Frame rate used for the synthetic 7-Scenes timestamps (index / 30 s)."""

SEVEN_SCENES_INVALID_DEPTH = 65535
"""7-Scenes' value of a depth pixel without a measurement (written as 0, the loaders' invalid value)."""

#: ``progress(done, total)``: bytes of the sequence's members consumed so far, and their total.
UnpackProgress = Callable[[int, int], None]

MAX_POSE_BYTES = 4096
"""Largest ``frame-XXXXXX.pose.txt`` read (16 numbers take ~300 bytes)."""
MAX_DEPTH_PIXELS = 50_000_000
"""Largest depth image decoded (7-Scenes' are 640×480)."""

_FRAME_RE = re.compile(r"frame-(\d+)\.(color\.png|color\.jpg|depth\.png|pose\.txt)$")


def _find_sequence(outer: zipfile.ZipFile, sequence: str) -> tuple[zipfile.ZipInfo | None, list[zipfile.ZipInfo]]:
    """The nested ``<sequence>.zip`` member of a scene zip, or the frame members of an unzipped ``<sequence>/``."""
    nested = [i for i in outer.infolist() if PurePosixPath(i.filename).name == f"{sequence}.zip"]
    if nested:
        return nested[0], []
    frames = [i for i in outer.infolist()
              if sequence in PurePosixPath(i.filename).parts[:-1] and _FRAME_RE.search(i.filename)]
    return None, frames


def _pose_line(t: float, text: str) -> str | None:
    """``'t tx ty tz qx qy qz qw'`` from a 7-Scenes 4×4 camera-to-world pose text, ``None`` if not finite."""
    try:
        vals = np.array(text.split(), dtype=np.float64)
    except ValueError:
        return None
    if vals.size != 16 or not np.all(np.isfinite(vals)):
        return None
    T = vals.reshape(4, 4)
    q = rot_to_quat(T[:3, :3])
    return f"{t:.6f} " + " ".join(f"{v:.8f}" for v in (*T[:3, 3], *q))


def _png_pixels(path: Path) -> int | None:
    """Width × height from a PNG's IHDR chunk, or ``None`` when the file does not start like a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big") * int.from_bytes(head[20:24], "big")


def _fix_depth(path: Path, member: str) -> None:
    """Check the depth PNG at ``path`` and set its 65535 (no measurement) pixels to 0, in place."""
    pixels = _png_pixels(path)
    if pixels is None or pixels > MAX_DEPTH_PIXELS:
        raise CorruptArchive(f"{member} is not a depth PNG of at most {MAX_DEPTH_PIXELS} pixels")
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise CorruptArchive(f"{member} is not a 16-bit single-channel depth PNG")
    bad = d == SEVEN_SCENES_INVALID_DEPTH
    if bad.any():
        d[bad] = 0
        if not cv2.imwrite(str(path), d):
            raise OSError(f"{path}: could not write the depth PNG")


def _convert_frames(zf: zipfile.ZipFile, infos: list[zipfile.ZipInfo], dest: Path, source: str,
                    budget: Budget, progress: UnpackProgress | None) -> int:
    frames: dict[int, dict[str, zipfile.ZipInfo]] = {}
    for info in infos:
        m = _FRAME_RE.search(info.filename)
        if m:
            check_zip_member(info, budget)
            frames.setdefault(int(m.group(1)), {})[m.group(2)] = info
    (dest / "rgb").mkdir(parents=True, exist_ok=True)
    (dest / "depth").mkdir(parents=True, exist_ok=True)
    note = f"# {source}; timestamps = frame index / {SEVEN_SCENES_FPS:g} s"
    rgb = ["# color images", note, "# timestamp filename"]
    dep = ["# depth maps (uint16 millimetres, 0 = invalid)", note, "# timestamp filename"]
    gt = ["# ground truth trajectory (camera-to-world, from frame-XXXXXX.pose.txt)", note,
          "# timestamp tx ty tz qx qy qz qw"]
    total, done = sum(i.compress_size for parts in frames.values() for i in parts.values()) or 1, 0
    for idx in sorted(frames):
        parts, t = frames[idx], idx / SEVEN_SCENES_FPS
        for kind, sub, lines in (("color.png", "rgb", rgb), ("color.jpg", "rgb", rgb), ("depth.png", "depth", dep)):
            if kind in parts:
                name = f"frame-{idx:06d}.{kind}"  # our name, not the member's
                with zf.open(parts[kind]) as src, open(dest / sub / name, "wb") as f:
                    budget.copy(src, f, parts[kind].filename)
                if sub == "depth":
                    _fix_depth(dest / sub / name, parts[kind].filename)
                lines.append(f"{t:.6f} {sub}/{name}")
        if "pose.txt" in parts:
            with zf.open(parts["pose.txt"]) as src:
                text = src.read(MAX_POSE_BYTES + 1)
            line = _pose_line(t, text.decode("ascii", "replace")) if len(text) <= MAX_POSE_BYTES else None
            if line:
                gt.append(line)
        done += sum(i.compress_size for i in parts.values())
        if progress:
            progress(done, total)
    for fname, lines in (("rgb.txt", rgb), ("depth.txt", dep), ("groundtruth.txt", gt)):
        (dest / fname).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return len(frames)


def convert_7scenes(archive: Path, sequence: str, dest: Path, progress: UnpackProgress | None = None,
                    budget: Budget | None = None) -> int:
    """Write sequence ``sequence`` (e.g. ``seq-01``) of the 7-Scenes scene zip ``archive`` into ``dest``
    in TUM layout (see the module docstring). Returns the number of frames.

    Raises:
        CorruptArchive: the zip (or the nested one) is truncated or corrupt, or a depth image does not
            decode as 16-bit.
        DatasetError: the archive holds no frame of ``sequence``.
        UnsafeMember, ArchiveTooLarge, OSError: as :func:`~mutualslam_cli.datasets.download.unpack.extract_archive`.
    """
    dest.mkdir(parents=True, exist_ok=True)
    budget = budget or Budget(archive, dest)
    with reading_archive(), open_zip(archive, budget) as outer:
        nested, infos = _find_sequence(outer, sequence)
        source = f"7-Scenes {archive.name} {sequence}"
        if nested is not None:
            check_zip_member(nested, budget)
            inner_path = dest / ".sequence.zip"  # the nested zip is extracted first: zips need seeking
            with outer.open(nested) as src, open(inner_path, "wb") as f:
                budget.copy(src, f, nested.filename)
            try:
                with open_zip(inner_path, budget) as inner:
                    n = _convert_frames(inner, inner.infolist(), dest, source, budget, progress)
            finally:
                inner_path.unlink(missing_ok=True)
        else:
            n = _convert_frames(outer, infos, dest, source, budget, progress)
    if n == 0:
        raise DatasetError(f"{archive}: no {sequence}.zip nor {sequence}/frame-XXXXXX.* members; expected a 7-Scenes "
                           f"scene zip holding {sequence} (check 'sequence:' in datasets.yaml)")
    return n

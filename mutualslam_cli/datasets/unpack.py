"""Unpacking downloaded dataset archives safely, and converting 7-Scenes sequences to the TUM layout.

Used by :mod:`~mutualslam_cli.datasets.download`. Every function writes only inside the folder it
is given (a temporary folder the caller removes on failure):

- :func:`extract_archive`: a ``.tar``/``.tgz``/``.tar.gz`` or ``.zip`` archive, member by member. A
  member with an absolute path or a ``..`` component is refused (:class:`UnsafeMember`); links and
  special files are skipped. A truncated or corrupt archive raises :class:`CorruptArchive`.
- :func:`content_root`: the sequence folder inside an extracted archive (TUM archives hold one
  top folder, ICL-NUIM ``*_frei_png`` archives hold the files at their top level).
- :func:`install_archive`: all of it into a temporary folder beside the sequence folder, then one
  rename into place (so the sequence folder is absent or whole).
- :func:`convert_7scenes`: one ``seq-NN`` of a Microsoft 7-Scenes scene zip (nested ``seq-NN.zip``
  with ``frame-XXXXXX.color.png``, ``.depth.png``, ``.pose.txt``) → TUM layout: ``rgb/``, ``depth/``,
  ``rgb.txt``, ``depth.txt`` (timestamps index / 30 s), ``groundtruth.txt`` (quaternions of the
  4×4 camera-to-world poses); depth stays in millimetres with the invalid value 65535 set to 0.

Progress: ``progress(done, total)`` in bytes of the archive (of the sequence's members for 7-Scenes).
"""

from __future__ import annotations

import errno
import gzip
import logging
import os
import re
import secrets
import shutil
import tempfile
import tarfile
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import IO, Callable, Iterator

import cv2
import numpy as np

from mutualslam_cli.errors import CorruptArchive, DatasetError, UnsafeMember
from mutualslam_cli.geometry import rot_to_quat

log = logging.getLogger(__name__)

#: ``progress(done, total)``: bytes of the archive consumed so far, and its size.
UnpackProgress = Callable[[int, int], None]

SEVEN_SCENES_FPS = 30.0
"""Frame rate used for the synthetic 7-Scenes timestamps (index / 30 s)."""

SEVEN_SCENES_INVALID_DEPTH = 65535
"""7-Scenes' value of a depth pixel without a measurement (written as 0, the loaders' invalid value)."""

_FRAME_RE = re.compile(r"frame-(\d+)\.(color\.png|color\.jpg|depth\.png|pose\.txt)$")
_CHUNK = 1 << 20


def _copy(src: IO[bytes], dst: IO[bytes]) -> None:
    """Copy one member's bytes (a separate function so that tests can make the disk fill up here)."""
    shutil.copyfileobj(src, dst, _CHUNK)


def safe_relpath(name: str) -> PurePosixPath:
    """The relative path of archive member ``name``; :class:`UnsafeMember` when it is absolute or has ``..``."""
    norm = name.replace("\\", "/")
    p = PurePosixPath(norm)
    if norm.startswith("/") or re.match(r"^[A-Za-z]:", norm) or ".." in p.parts:
        raise UnsafeMember(name)
    parts = [s for s in p.parts if s not in ("", ".")]
    return PurePosixPath(*parts) if parts else PurePosixPath(".")


def _write(dest: Path, rel: PurePosixPath, src: IO[bytes]) -> None:
    target = dest.joinpath(*rel.parts)
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "wb") as f:
        _copy(src, f)


def _extract_tar(archive: Path, dest: Path, progress: UnpackProgress | None) -> None:
    size = archive.stat().st_size
    with open(archive, "rb") as raw, tarfile.open(fileobj=raw, mode="r:*") as tf:
        for m in tf:
            rel = safe_relpath(m.name)
            if m.isdir():
                dest.joinpath(*rel.parts).mkdir(parents=True, exist_ok=True)
            elif m.isfile():
                src = tf.extractfile(m)
                assert src is not None
                with src:
                    _write(dest, rel, src)
            else:
                log.warning("%s: skipped %s (not a regular file or folder)", archive, m.name)
            if progress:
                progress(raw.tell(), size)


def _extract_zip(archive: Path, dest: Path, progress: UnpackProgress | None) -> None:
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        total, done = sum(i.compress_size for i in infos) or 1, 0
        for info in infos:
            rel = safe_relpath(info.filename)
            if info.is_dir():
                dest.joinpath(*rel.parts).mkdir(parents=True, exist_ok=True)
            else:
                with zf.open(info) as src:
                    _write(dest, rel, src)
            done += info.compress_size
            if progress:
                progress(done, total)


@contextmanager
def _reading() -> Iterator[None]:
    """Translate the archive readers' many errors for a bad file into :class:`CorruptArchive`."""
    try:
        yield
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error, gzip.BadGzipFile) as e:
        raise CorruptArchive(str(e) or type(e).__name__) from None


def extract_archive(archive: Path, dest: Path, progress: UnpackProgress | None = None) -> None:
    """Extract every member of ``archive`` (tar, possibly compressed, or zip) into the folder ``dest``.

    Raises:
        UnsafeMember: a member with an absolute path or ``..`` (some members may be written already).
        CorruptArchive: the archive is truncated or corrupt.
        OSError: writing failed (e.g. ``errno.ENOSPC``).
    """
    dest.mkdir(parents=True, exist_ok=True)
    with _reading():
        if archive.suffix.lower() == ".zip" or zipfile.is_zipfile(archive):
            _extract_zip(archive, dest, progress)
        else:
            _extract_tar(archive, dest, progress)


def content_root(folder: Path) -> Path:
    """The sequence folder of an extracted archive: its only top entry when that is a folder, else ``folder``."""
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]  # e.g. macOS "._*" files beside it
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return folder


# ----------------------------------------------------------------------------- 7-Scenes


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
    vals = np.array(text.split(), dtype=np.float64)
    if vals.size != 16 or not np.all(np.isfinite(vals)):
        return None
    T = vals.reshape(4, 4)
    q = rot_to_quat(T[:3, :3])
    return f"{t:.6f} " + " ".join(f"{v:.8f}" for v in (*T[:3, 3], *q))


def _depth_png(data: bytes, name: str) -> bytes:
    """The depth PNG with 65535 (no measurement) set to 0; unchanged bytes when it has no such pixel."""
    d = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise CorruptArchive(f"{name} is not a 16-bit single-channel depth PNG")
    bad = d == SEVEN_SCENES_INVALID_DEPTH
    if not bad.any():
        return data
    d[bad] = 0
    ok, buf = cv2.imencode(".png", d)
    if not ok:
        raise OSError(f"{name}: could not encode the depth PNG")
    return buf.tobytes()


def _convert_frames(zf: zipfile.ZipFile, infos: list[zipfile.ZipInfo], dest: Path, source: str,
                    progress: UnpackProgress | None) -> int:
    frames: dict[int, dict[str, zipfile.ZipInfo]] = {}
    for info in infos:
        m = _FRAME_RE.search(info.filename)
        if m:
            frames.setdefault(int(m.group(1)), {})[m.group(2).split(".")[0]] = info
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
        if "color" in parts:
            name = PurePosixPath(parts["color"].filename).name
            with zf.open(parts["color"]) as src, open(dest / "rgb" / name, "wb") as f:
                _copy(src, f)
            rgb.append(f"{t:.6f} rgb/{name}")
        if "depth" in parts:
            name = PurePosixPath(parts["depth"].filename).name
            (dest / "depth" / name).write_bytes(_depth_png(zf.read(parts["depth"]), name))
            dep.append(f"{t:.6f} depth/{name}")
        if "pose" in parts:
            line = _pose_line(t, zf.read(parts["pose"]).decode("ascii", "replace"))
            if line:
                gt.append(line)
        done += sum(i.compress_size for i in parts.values())
        if progress:
            progress(done, total)
    for fname, lines in (("rgb.txt", rgb), ("depth.txt", dep), ("groundtruth.txt", gt)):
        (dest / fname).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return len(frames)


def convert_7scenes(archive: Path, sequence: str, dest: Path, progress: UnpackProgress | None = None) -> int:
    """Write sequence ``sequence`` (e.g. ``seq-01``) of the 7-Scenes scene zip ``archive`` into ``dest``
    in TUM layout (see the module docstring). Returns the number of frames.

    Raises:
        CorruptArchive: the zip (or the nested one) is truncated or corrupt, or a depth image does not
            decode as 16-bit.
        DatasetError: the archive holds no frame of ``sequence``.
        UnsafeMember, OSError: as :func:`extract_archive`.
    """
    dest.mkdir(parents=True, exist_ok=True)
    with _reading(), zipfile.ZipFile(archive) as outer:
        nested, infos = _find_sequence(outer, sequence)
        source = f"7-Scenes {archive.name} {sequence}"
        if nested is not None:
            inner_path = dest / f".{sequence}.zip"  # the nested zip is extracted first: zips need seeking
            with outer.open(nested) as src, open(inner_path, "wb") as f:
                _copy(src, f)
            try:
                with zipfile.ZipFile(inner_path) as inner:
                    n = _convert_frames(inner, inner.infolist(), dest, source, progress)
            finally:
                inner_path.unlink(missing_ok=True)
        else:
            n = _convert_frames(outer, infos, dest, source, progress)
    if n == 0:
        raise DatasetError(f"{archive}: no {sequence}.zip nor {sequence}/frame-XXXXXX.* members; expected a 7-Scenes "
                           f"scene zip holding {sequence} (check 'sequence:' in datasets.yaml)")
    return n


# ----------------------------------------------------------------------------- install


def is_complete(root: Path) -> bool:
    """True when the sequence folder ``root`` exists and is not empty."""
    return root.is_dir() and any(root.iterdir())


def _rename_into(content: Path, root: Path, force: bool) -> None:
    """Rename the unpacked ``content`` folder to ``root`` (replacing an existing one with ``force``)."""
    if root.is_dir() and not any(root.iterdir()):
        root.rmdir()
    if root.exists():
        if not force:
            raise DatasetError(f"{root}: appeared while unpacking; not replaced (--force replaces it)")
        old = Path(tempfile.mkdtemp(prefix=f".{root.name}.old-", dir=root.parent))
        os.replace(root, old / root.name)
        os.rename(content, root)
        shutil.rmtree(old, ignore_errors=True)
        return
    os.rename(content, root)


def install_archive(archive: Path, root: Path, *, layout: str = "archive", sequence: str | None = None,
                    extra: dict[str, Path] | None = None, force: bool = False,
                    progress: UnpackProgress | None = None) -> None:
    """Unpack ``archive`` into a temporary folder beside ``root`` (same file system), copy the ``extra``
    files (name in the sequence folder → source path) into it, then rename it to ``root``.

    ``layout``: ``"archive"`` (the sequence is the archive's only top folder, or its top level) or
    ``"7scenes"`` (:func:`convert_7scenes` of ``sequence``). The temporary folder is removed in every
    case; ``root`` is only ever absent or complete.

    Raises:
        CorruptArchive: the archive is truncated or corrupt (the caller decides what to do with it).
        DatasetError: a member with an absolute path or ``..``, a full disk, another write error.
    """
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.parent / f".{root.name}.unpack-{os.getpid()}-{secrets.token_hex(4)}"
    tmp.mkdir()  # not mkdtemp: the folder may become the sequence folder, so it gets the usual permissions
    try:
        if layout == "7scenes":
            convert_7scenes(archive, str(sequence), tmp, progress)
            content = tmp
        else:
            extract_archive(archive, tmp, progress)
            content = content_root(tmp)
        for name, src in (extra or {}).items():
            shutil.copyfile(src, content / name)
        _rename_into(content, root, force)
    except UnsafeMember as e:
        raise DatasetError(f"{archive}: member {str(e)!r} has an absolute path or '..'; refused to unpack the "
                           f"archive (removed the temporary folder {tmp.name})") from None
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise DatasetError(f"no space left on device while unpacking {archive} into {root.parent}; removed "
                               "the temporary folder, free some space and run the command again") from None
        raise DatasetError(f"{root.parent}: cannot unpack {archive.name} there ({e.strerror or e}); removed the "
                           "temporary folder") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

"""Unpacking downloaded dataset archives safely (used by :mod:`~mutualslam_cli.datasets.download.entry`).

Every function writes only inside the folder it is given (a temporary folder the caller removes on
failure), and every byte it writes is counted against the :mod:`~mutualslam_cli.datasets.download.limits`
(total bytes, free disk, member count, per-member compression ratio):

- :func:`extract_archive`: a ``.tar`` (plain, gzip, bzip2 or xz) or ``.zip`` archive, member by member,
  each streamed to disk. What a member may be is :mod:`~mutualslam_cli.datasets.download.members`' rule
  (:func:`safe_relpath`: relative, no ``..``, at most :data:`MAX_MEMBER_DEPTH` components; no links,
  no special files, zip members stored or deflated), else :class:`UnsafeMember`. A truncated or corrupt
  archive raises :class:`CorruptArchive`.
- :func:`content_root`: the sequence folder inside an extracted archive (TUM archives hold one
  top folder, ICL-NUIM ``*_frei_png`` archives hold the files at their top level).
- :func:`install_archive`: all of it into a temporary folder beside the sequence folder, checked there
  (the caller's ``check``, e.g. the sequence check), marked as mslam's own (:data:`MARKER`), then one
  rename into place (so the sequence folder is absent or whole and checked). ``force`` replaces an
  existing folder only when it carries the marker — one mslam unpacked, never a folder of the user's —
  by moving it aside first and moving it back if the new one cannot take its place;
  :func:`recover_leftovers` finishes or undoes such a swap that a killed process left half done.
- 7-Scenes scene zips: :mod:`~mutualslam_cli.datasets.download.seven_scenes`.

Progress: ``progress(done, total)`` in bytes of the archive (of the sequence's members for 7-Scenes).
"""

from __future__ import annotations

import bz2
import errno
import gzip
import logging
import lzma
import os
import secrets
import shutil
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

from mutualslam_cli.datasets.download.archive_scan import scan_tar
from mutualslam_cli.datasets.download.limits import MAX_HEADER_BYTES, Budget, UnpackLimits
from mutualslam_cli.datasets.download.members import (
    MAX_MEMBER_CHARS,
    MAX_MEMBER_DEPTH,
    check_zip_member,
    member_path,
    open_zip,
    reading_archive,
    refuse_special,
    safe_relpath,
)
from mutualslam_cli.datasets.download.safe_names import path_inside
from mutualslam_cli.datasets.download.seven_scenes import convert_7scenes
from mutualslam_cli.errors import ArchiveTooLarge, CorruptArchive, DatasetError, UnsafeMember

__all__ = ["MARKER", "MAX_MEMBER_CHARS", "MAX_MEMBER_DEPTH", "UnpackProgress", "UnsafeMember", "content_root",
           "extract_archive", "install_archive", "is_complete", "is_unpacked_by_mslam", "not_unpacked_by_mslam",
           "recover_leftovers", "safe_relpath"]

log = logging.getLogger(__name__)

#: ``progress(done, total)``: bytes of the archive consumed so far, and its size.
UnpackProgress = Callable[[int, int], None]
MARKER = ".mslam-unpacked"
"""File that :func:`install_archive` writes into each sequence folder it installs: ``force`` replaces only a
folder that has it."""

class _TarStream:
    """The decompressed tar stream for ``tarfile`` (mode ``r:``): a read larger than
    :data:`MAX_HEADER_BYTES` is refused (``tarfile`` reads pax and long-name headers whole), and a
    decompressor's complaint becomes :class:`CorruptArchive`."""

    def __init__(self, f: IO[bytes]):
        self.f = f

    def read(self, n: int = -1) -> bytes:
        if n is None or n < 0 or n > MAX_HEADER_BYTES:
            raise ArchiveTooLarge(f"a tar header asks for {n} bytes at once (limit {MAX_HEADER_BYTES}; a crafted "
                                  "pax or long-name header?)")
        try:
            return self.f.read(n)
        except OSError as e:
            if e.errno is not None:
                raise
            raise CorruptArchive(str(e)) from None  # bz2: "Invalid data stream"

    def seek(self, pos: int, whence: int = 0) -> int:
        return self.f.seek(pos, whence)

    def tell(self) -> int:
        return self.f.tell()


def _decompressed(raw: IO[bytes]) -> IO[bytes]:
    head = raw.read(6)
    raw.seek(0)
    if head.startswith(b"\x1f\x8b"):
        return gzip.GzipFile(fileobj=raw, mode="rb")  # type: ignore[return-value]
    if head.startswith(b"BZh"):
        return bz2.BZ2File(raw)
    if head.startswith(b"\xfd7zXZ\x00"):
        return lzma.LZMAFile(raw)
    return raw


def _extract_tar(archive: Path, dest: Path, budget: Budget, progress: UnpackProgress | None) -> None:
    size = archive.stat().st_size
    with open(archive, "rb") as raw, _decompressed(raw) as stream:  # the headers first: limits before writing
        scan_tar(stream, budget.declared)
    with open(archive, "rb") as raw, _decompressed(raw) as stream, \
            tarfile.open(fileobj=_TarStream(stream), mode="r:") as tf:  # type: ignore[call-overload]
        for m in tf:
            budget.add_members()
            rel = safe_relpath(m.name)
            if m.issym() or m.islnk():
                refuse_special("sym" if m.issym() else "hard", m.name, m.linkname)
            if m.isdir():
                member_path(dest, rel, folder=True)
            elif m.isfile():
                budget.room(m.name, m.size)
                src = tf.extractfile(m)
                assert src is not None
                with src, open(member_path(dest, rel), "wb") as f:
                    budget.copy(src, f, m.name, consumed=raw.tell)
            else:
                refuse_special("special", m.name)
            if progress:
                progress(raw.tell(), size)


def _extract_zip(archive: Path, dest: Path, budget: Budget, progress: UnpackProgress | None) -> None:
    with open_zip(archive, budget) as zf:
        infos = zf.infolist()
        total, done = sum(i.compress_size for i in infos) or 1, 0
        for info in infos:
            rel = check_zip_member(info, budget)
            if info.is_dir():
                member_path(dest, rel, folder=True)
            else:
                with zf.open(info) as src, open(member_path(dest, rel), "wb") as f:
                    budget.copy(src, f, info.filename)
            done += info.compress_size
            if progress:
                progress(done, total)


def extract_archive(archive: Path, dest: Path, progress: UnpackProgress | None = None,
                    budget: Budget | None = None) -> None:
    """Extract every member of ``archive`` (tar, possibly compressed, or zip) into the folder ``dest``.

    Raises:
        UnsafeMember: a member path that :func:`safe_relpath` refuses, a link or special file, an
            unsupported zip compression (some members may be written already).
        ArchiveTooLarge: a limit of ``budget`` (default :class:`~mutualslam_cli.datasets.download.limits.UnpackLimits`).
        CorruptArchive: the archive is truncated or corrupt.
        OSError: writing failed (e.g. ``errno.ENOSPC``).
    """
    dest.mkdir(parents=True, exist_ok=True)
    budget = budget or Budget(archive, dest)
    with reading_archive():
        if archive.suffix.lower() == ".zip" or zipfile.is_zipfile(archive):
            _extract_zip(archive, dest, budget, progress)
        else:
            _extract_tar(archive, dest, budget, progress)


def content_root(folder: Path) -> Path:
    """The sequence folder of an extracted archive: its only top entry when that is a folder, else ``folder``."""
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]  # e.g. macOS "._*" files beside it
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return folder


# ----------------------------------------------------------------------------- install


def is_complete(root: Path) -> bool:
    """True when the sequence folder ``root`` exists and is not empty."""
    return root.is_dir() and any(root.iterdir())


def is_unpacked_by_mslam(root: Path) -> bool:
    """True when ``root`` is a folder that :func:`install_archive` installed (it holds :data:`MARKER` as a file)."""
    marker = root / MARKER
    return root.is_dir() and not root.is_symlink() and marker.is_file() and not marker.is_symlink()


def not_unpacked_by_mslam(root: Path) -> DatasetError:
    """The one-line refusal to replace ``root`` with ``force``: it is not a folder mslam unpacked."""
    return DatasetError(f"{root}: exists and was not unpacked by mslam (no {MARKER} file in it); --force replaces "
                        "only a sequence folder mslam unpacked, so nothing was touched — move the folder away (or "
                        "give the entry another root) to download it there")


def recover_leftovers(root: Path) -> list[str]:
    """Finish what a killed unpacking of ``root`` left beside it; returns one note per thing done.

    A ``.<name>.old-*`` folder holds the sequence folder a ``force`` swap moved aside: it is moved
    back when ``root`` is missing (the swap was cut before the new folder took its place), else
    removed. ``.<name>.unpack-*`` temporary folders are removed. Call it while holding the download
    lock, so that no live process owns them.
    """
    notes: list[str] = []
    if not root.parent.is_dir():
        return notes
    for old in sorted(root.parent.glob(f".{root.name}.old-*")):
        if (old / root.name).is_dir() and not is_complete(root):
            if root.is_dir():
                root.rmdir()
            os.rename(old / root.name, root)
            notes.append(f"{root}: restored the folder an interrupted --force had moved to {old.name}")
        shutil.rmtree(old, ignore_errors=True)
    for tmp in root.parent.glob(f".{root.name}.unpack-*"):
        shutil.rmtree(tmp, ignore_errors=True)
        notes.append(f"{root.parent}: removed {tmp.name}, left by an interrupted unpacking")
    return notes


def _rename_into(content: Path, root: Path, force: bool) -> None:
    """Rename the unpacked ``content`` folder to ``root``; with ``force`` an existing ``root`` is moved
    aside first and moved back when the rename fails."""
    if root.is_dir() and not any(root.iterdir()):
        root.rmdir()
    if not root.exists():
        os.rename(content, root)
        return
    if not force:
        raise DatasetError(f"{root}: appeared while unpacking; not replaced (--force replaces it)")
    if not is_unpacked_by_mslam(root):
        raise not_unpacked_by_mslam(root)
    old = root.parent / f".{root.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
    old.mkdir()
    os.rename(root, old / root.name)
    try:
        os.rename(content, root)
    except BaseException:
        os.rename(old / root.name, root)  # the old folder back in place
        old.rmdir()
        raise
    shutil.rmtree(old, ignore_errors=True)
    if old.exists():
        log.warning("%s: could not remove the replaced folder %s; the next download removes it", root, old)


def _checked(check: Callable[[Path], None], content: Path, archive: Path, root: Path, force: bool) -> None:
    """``check(content)``; its error as one line that names the archive instead of the hidden folder."""
    try:
        check(content)
    except DatasetError as e:
        why = str(e).replace(str(content), f"<{archive.name}>")
        kept = f"{root} is unchanged" if force and root.exists() else f"{root} was not created"
        raise DatasetError(f"{archive}: the unpacked sequence fails the check ({why}); not installed, {kept}, no "
                           "checksum recorded (the archive stays in place; delete it to download it anew)") from None


def install_archive(archive: Path, root: Path, *, layout: str = "archive", sequence: str | None = None,
                    extra: dict[str, Path] | None = None, force: bool = False,
                    progress: UnpackProgress | None = None, limits: UnpackLimits | None = None,
                    check: Callable[[Path], None] | None = None, marker: str = "") -> None:
    """Unpack ``archive`` into a temporary folder beside ``root`` (same file system), copy the ``extra``
    files (safe file name in the sequence folder → source path) into it, then rename it to ``root``.

    ``layout``: ``"archive"`` (the sequence is the archive's only top folder, or its top level) or
    ``"7scenes"`` (:func:`~mutualslam_cli.datasets.download.seven_scenes.convert_7scenes` of ``sequence``). The
    temporary folder is removed in every case; ``root`` is only ever absent or complete, and with
    ``force`` an existing ``root`` survives any failure.

    ``check(folder)``, when given, is called on the unpacked sequence folder while it is still hidden;
    a :class:`DatasetError` from it leaves ``root`` as it was. ``marker`` is written into :data:`MARKER`
    (e.g. where the folder came from) just before the rename.

    Raises:
        CorruptArchive: the archive is truncated or corrupt (the caller decides what to do with it).
        DatasetError: an unsafe member, a limit (:mod:`~mutualslam_cli.datasets.download.limits`), a full disk,
            another write error — one line each.
    """
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.parent / f".{root.name}.unpack-{os.getpid()}-{secrets.token_hex(4)}"
    tmp.mkdir()  # not mkdtemp: the folder may become the sequence folder, so it gets the usual permissions
    try:
        budget = Budget(archive, root.parent, limits)
        work = tmp / ".archive"
        if layout == "7scenes":
            convert_7scenes(archive, str(sequence), work, progress, budget)
            content = work
        else:
            extract_archive(archive, work, progress, budget)
            content = content_root(work)
        if root.name != work.name:  # checked under its own name: a loader may read it (the TUM family)
            os.rename(content, tmp / root.name)
            content = tmp / root.name
        for name, src in (extra or {}).items():
            with open(src, "rb") as s, open(path_inside(content, name, f"{archive.name}: extra file"), "wb") as d:
                budget.copy(s, d, name)
        if check is not None:
            _checked(check, content, archive, root, force)
        (content / MARKER).unlink(missing_ok=True)  # an archive's own marker does not count: ours is written anew
        with open(content / MARKER, "x", encoding="utf-8") as f:
            f.write(marker or f"unpacked from {archive.name} by mslam datasets download\n")
        _rename_into(content, root, force)
    except UnsafeMember as e:
        raise DatasetError(f"{archive}: {e}; refused to unpack the archive (removed the temporary folder "
                           f"{tmp.name})") from None
    except ArchiveTooLarge as e:
        raise DatasetError(f"refused to unpack {archive}: {e}; removed the temporary folder, the archive stays "
                           "in place") from None
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise DatasetError(f"no space left on device while unpacking {archive} into {root.parent}; removed "
                               "the temporary folder, free some space and run the command again") from None
        raise DatasetError(f"{root.parent}: cannot unpack {archive.name} there ({e.strerror or e}); removed the "
                           "temporary folder" + (f", {root} is unchanged" if force else "")) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

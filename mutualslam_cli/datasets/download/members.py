"""What a member of a downloaded archive may be, and how the readers' errors are reported
(shared by :mod:`~mutualslam_cli.datasets.download.unpack` and :mod:`~mutualslam_cli.datasets.download.seven_scenes`).

A member becomes a path only through :func:`safe_relpath` (relative, no ``..``, no control character,
at most :data:`MAX_MEMBER_DEPTH` components and :data:`MAX_MEMBER_CHARS` characters) and
:func:`member_path` (the final path checked to lie inside the target folder). Links (symbolic or hard)
and special files are refused, as are zip members compressed otherwise than stored or deflate
(``zipfile`` decompresses bzip2 and LZMA chunks without an output bound): a dataset archive holds only
files and folders. Every refusal is an :class:`~mutualslam_cli.errors.UnsafeMember` naming the member.
"""

from __future__ import annotations

import gzip
import lzma
import os
import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath

from mutualslam_cli.datasets.download.archive_scan import zip_declared_members
from mutualslam_cli.datasets.download.limits import Budget
from mutualslam_cli.errors import ArchiveTooLarge, CorruptArchive, UnsafeMember

MAX_MEMBER_DEPTH = 32
"""Most path components of an archive member (TUM members have 3)."""
MAX_MEMBER_CHARS = 1024
"""Longest archive member path (characters)."""
_ZIP_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)


def safe_relpath(name: str) -> PurePosixPath:
    """The relative path of archive member ``name``.

    Raises:
        UnsafeMember: the path is absolute (``/x``, ``C:x``), has a ``..`` component or a control
            character, has more than :data:`MAX_MEMBER_DEPTH` components or :data:`MAX_MEMBER_CHARS`
            characters.
    """
    norm = name.replace("\\", "/")
    p = PurePosixPath(norm)
    if norm.startswith("/") or re.match(r"^[A-Za-z]:", norm) or ".." in p.parts:
        raise UnsafeMember(f"member {name!r} has an absolute path or '..'")
    if any(ord(c) < 32 or c == "\x7f" for c in name):
        raise UnsafeMember(f"member {name!r} has a control character in its path")
    parts = [s for s in p.parts if s not in ("", ".")]
    if len(parts) > MAX_MEMBER_DEPTH or len(name) > MAX_MEMBER_CHARS:
        raise UnsafeMember(f"member {name[:60]!r}… has {len(parts)} path components and {len(name)} characters "
                           f"(limits {MAX_MEMBER_DEPTH} and {MAX_MEMBER_CHARS})")
    return PurePosixPath(*parts) if parts else PurePosixPath(".")


def member_path(dest: Path, rel: PurePosixPath, folder: bool = False) -> Path:
    """``dest / rel``, checked to resolve inside ``dest``, with its folders (and itself when ``folder``) created."""
    target = dest.joinpath(*rel.parts)
    real, base = os.path.realpath(target), os.path.realpath(dest)
    if real != base and not real.startswith(base + os.sep):
        raise UnsafeMember(f"member {rel.as_posix()!r} resolves outside the target folder")
    (target if folder else target.parent).mkdir(parents=True, exist_ok=True)
    return target


def refuse_special(kind: str, name: str, target: str = "") -> None:
    what = {"sym": "a symbolic link", "hard": "a hard link", "special": "a device, FIFO or other special file"}
    to = f" to {target!r}" if target else ""
    raise UnsafeMember(f"member {name!r} is {what[kind]}{to} (a dataset archive holds only files and folders)")


def check_zip_member(info: zipfile.ZipInfo, budget: Budget) -> PurePosixPath:
    """The checked relative path of a zip member (path, type, compression method, declared ratio)."""
    rel = safe_relpath(info.filename)
    kind = stat.S_IFMT(info.external_attr >> 16)  # 0: no Unix type recorded (a plain file or folder)
    if kind == stat.S_IFLNK:
        refuse_special("sym", info.filename)
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        refuse_special("special", info.filename)
    if not info.is_dir() and info.compress_type not in _ZIP_METHODS:
        raise UnsafeMember(f"member {info.filename!r} uses zip compression method {info.compress_type}; "
                           "expected stored or deflate (others cannot be unpacked with bounded memory)")
    budget.ratio(info.filename, info.file_size, info.compress_size)
    return rel


def open_zip(archive: Path, budget: Budget) -> zipfile.ZipFile:
    """``archive`` opened, its member count and declared total checked against ``budget`` (nothing written);
    the count its end-of-central-directory record declares is checked before the directory is read."""
    declared = zip_declared_members(archive)
    if declared is not None:
        budget.declared(declared, 0)
    zf = zipfile.ZipFile(archive)
    infos = zf.infolist()
    try:
        budget.add_members(len(infos))
        budget.room("", sum(i.file_size for i in infos))
    except ArchiveTooLarge:
        zf.close()
        raise
    return zf


@contextmanager
def reading_archive() -> Iterator[None]:
    """Translate the archive readers' many errors for a bad file into :class:`CorruptArchive`."""
    try:
        yield
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error, gzip.BadGzipFile, lzma.LZMAError) as e:
        raise CorruptArchive(str(e) or type(e).__name__) from None

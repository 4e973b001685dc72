"""What an archive declares about itself, read before anything of it is written
(used by :mod:`~mutualslam_cli.datasets.download.unpack` and :mod:`~mutualslam_cli.datasets.download.members`).

An archive of a quarter of a million empty members is half a megabyte; unpacking it member by member
creates files until the member limit is reached, which took ~45 s of one core before the archive was
refused. The limits on the member count and the declared bytes are therefore checked first, from the
headers alone:

- :func:`scan_tar`: walks the (decompressed) tar stream header by header, skipping the data of each
  member unread where the stream can seek, and stops with
  :class:`~mutualslam_cli.errors.ArchiveTooLarge` as soon as the count passes the limit. It reads pax
  ``size`` records and GNU base-256 sizes as ``tarfile`` does, and does not count extension headers
  (pax, GNU long names) as members. Where a header cannot be parsed it stops quietly: ``tarfile``, which
  unpacks afterwards and counts every member again, reports the damage.
- :func:`zip_declared_members`: the member count of a zip's end-of-central-directory record (zip64
  included), read before ``zipfile`` builds an object per member of the central directory.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import IO

from mutualslam_cli.datasets.download.limits import MAX_HEADER_BYTES
from mutualslam_cli.errors import ArchiveTooLarge

BLOCK = 512
_ZERO = bytes(BLOCK)
_EXTENSIONS = (b"x", b"g", b"L", b"K", b"X")  # pax, pax global, GNU long name / link, Solaris pax
_NO_DATA = b"123456"  # links, devices, folders, FIFOs: their size field does not announce data


def _number(field: bytes) -> int | None:
    """A tar header's numeric field (octal text, or GNU base-256); ``None`` when it is neither."""
    if field[:1] == b"\x80":
        return int.from_bytes(field[1:], "big")
    text = field.split(b"\0", 1)[0].strip()
    if not text:
        return 0
    try:
        return int(text, 8)
    except ValueError:
        return None


def _pax_records(data: bytes) -> dict[bytes, bytes]:
    """The ``key=value`` records of a pax extended header's ``data`` (up to the first malformed one)."""
    out, pos = {}, 0
    while pos < len(data):
        space = data.find(b" ", pos)
        try:
            length = int(data[pos:space])
        except ValueError:
            break
        if space < 0 or length <= 0:
            break
        key, _, value = data[space + 1:pos + length - 1].partition(b"=")
        out[key] = value
        pos += length
    return out


def _text(field: bytes) -> str:
    return field.split(b"\0", 1)[0].decode("utf-8", "replace")


def _member_name(block: bytes, pax: dict[bytes, bytes], long_name: str | None) -> str:
    """The name of the member whose header is ``block`` (pax ``path``, else a GNU long name, else ustar's)."""
    if b"path" in pax:
        return pax[b"path"].decode("utf-8", "replace")
    prefix = _text(block[345:500]) + "/" if block[257:263] == b"ustar\0" and block[345] else ""
    return long_name or prefix + _text(block[:100])


def _skip(stream: IO[bytes], n: int) -> None:
    try:
        stream.seek(n, os.SEEK_CUR)
    except (OSError, ValueError):
        while n > 0 and (buf := stream.read(min(n, 1 << 20))):
            n -= len(buf)


def scan_tar(stream: IO[bytes], check: Callable[[int, int, str], None]) -> tuple[int, int]:
    """Walk the tar headers of ``stream`` (decompressed, positioned at its start), calling
    ``check(members, declared_bytes, member_name)`` after each member, which raises to stop; returns the
    totals.

    Raises:
        ArchiveTooLarge: from ``check``, or an extension header larger than :data:`MAX_HEADER_BYTES`.
    """
    members = declared = 0
    pax: dict[bytes, bytes] = {}
    long_name: str | None = None
    while len(block := stream.read(BLOCK)) == BLOCK and block != _ZERO:
        size = _number(block[124:136])
        if size is None:
            break  # not a header: tarfile reports it when it gets there
        kind, padded = block[156:157], -(-size // BLOCK) * BLOCK
        if kind in _EXTENSIONS:
            if size > MAX_HEADER_BYTES:
                raise ArchiveTooLarge(f"a tar header asks for {size} bytes at once (limit {MAX_HEADER_BYTES}; a "
                                      "crafted pax or long-name header?)")
            data = stream.read(padded)
            if kind == b"x":
                pax = _pax_records(data[:size])
            elif kind == b"L":
                long_name = _text(data[:size])
            continue
        if pax.get(b"size", b"").isdigit():
            size, padded = int(pax[b"size"]), -(-int(pax[b"size"]) // BLOCK) * BLOCK
        name = _member_name(block, pax, long_name) if size else ""  # only a member with bytes is named
        pax, long_name = {}, None
        members += 1
        if kind not in _NO_DATA:
            declared += size
            _skip(stream, padded)
        check(members, declared, name)
    return members, declared


def zip_declared_members(path: Path) -> int | None:
    """The member count that the end-of-central-directory record of the zip ``path`` declares (``None``: no
    such record found; ``zipfile`` reports the damage)."""
    with open(path, "rb") as f:
        end = f.seek(0, os.SEEK_END)
        tail_len = min(end, 22 + 0xFFFF + 20)  # the record, its longest comment, the zip64 locator
        f.seek(end - tail_len)
        tail = f.read(tail_len)
        i = tail.rfind(b"PK\x05\x06")
        if i < 0 or len(tail) - i < 22:
            return None
        total = int.from_bytes(tail[i + 10:i + 12], "little")
        if total == 0xFFFF and i >= 20 and tail[i - 20:i - 16] == b"PK\x06\x07":
            f.seek(int.from_bytes(tail[i - 12:i - 4], "little"))
            rec = f.read(56)
            if rec[:4] == b"PK\x06\x06" and len(rec) == 56:
                total = int.from_bytes(rec[32:40], "little")
        return total

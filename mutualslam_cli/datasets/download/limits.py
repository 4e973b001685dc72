"""Limits on what unpacking one downloaded archive may write (:mod:`~mutualslam_cli.datasets.download.unpack`).

A crafted or broken archive must not fill the disk, the memory or the inode table. Every byte an
unpacking writes goes through :meth:`Budget.copy` (members are streamed in chunks of
:data:`CHUNK_BYTES`, never read whole), which enforces, with their defaults:

- **total bytes** written ≤ :data:`UNPACK_MULTIPLE` × the archive's size (the publishers' archives hold
  PNG images, which do not compress further: they unpack to about their own size), or the
  ``max_bytes`` given instead (``mslam datasets download --max-unpack-gb GB``);
- **free disk**: the total also stays :data:`MIN_FREE_BYTES` below what was free on the target's
  file system when unpacking began;
- **member count** ≤ :data:`MAX_MEMBERS` (the longest TUM sequences hold ~40 000 files); the count and the
  declared total are checked from the headers before anything is written (:meth:`Budget.declared`,
  :mod:`~mutualslam_cli.datasets.download.archive_scan`), and again member by member while unpacking;
- **compression ratio of a member**: a member larger than :data:`RATIO_FLOOR_BYTES` may not unpack to
  more than :data:`MAX_RATIO` × its compressed bytes (deflate reaches ~1000× on zeros, a zip bomb's
  filling; images reach ~1×, text ~5×). For a zip the declared sizes are checked before anything is
  written (zipfile stops a member at its declared size); for a compressed tar, whose stream has one
  ratio, the compressed bytes a member consumed are measured while it streams;
- **metadata**: a single read of tar metadata (a pax or GNU long-name header, which ``tarfile`` reads
  whole into memory) ≤ :data:`MAX_HEADER_BYTES`.

Passing a limit raises :class:`~mutualslam_cli.errors.ArchiveTooLarge` naming the member, the limit and
how to change it; the caller removes what was written. Sizes in bytes; messages say GB (10⁹ bytes).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from mutualslam_cli.errors import ArchiveTooLarge

UNPACK_MULTIPLE = 10.0
"""Default limit on the unpacked total, as a multiple of the archive's size."""
MIN_FREE_BYTES = 100_000_000
"""Bytes left free on the target's file system (unpacking stops before it would use them)."""
MAX_MEMBERS = 200_000
"""Most members (files and folders) an archive may hold."""
MAX_RATIO = 100.0
"""Largest unpacked / compressed size of one member larger than :data:`RATIO_FLOOR_BYTES`."""
RATIO_FLOOR_BYTES = 1_000_000
"""Members up to this size are not ratio-checked (a small text file may compress well)."""
MAX_HEADER_BYTES = 16 * 2**20
"""Largest single read of archive metadata (bytes)."""
CHUNK_BYTES = 1 << 20
"""Bytes copied per step."""


@dataclass(frozen=True)
class UnpackLimits:
    """The limits of one unpacking (module docstring); ``max_bytes`` ``None``: ``multiple`` × the archive."""

    max_bytes: int | None = None
    multiple: float = UNPACK_MULTIPLE
    max_members: int = field(default_factory=lambda: MAX_MEMBERS)  # read when built: a test may lower it
    max_ratio: float = MAX_RATIO
    ratio_floor: int = RATIO_FLOOR_BYTES
    min_free: int = MIN_FREE_BYTES


def gb(n: float) -> str:
    """``n`` bytes in GB with three significant digits."""
    return f"{n / 1e9:.3g}"


def disk_free(folder: Path) -> int:
    """Bytes free for this user on the file system of ``folder``."""
    return shutil.disk_usage(folder).free


class Budget:
    """What one unpacking of ``archive`` into (a temporary folder in) ``folder`` may still write."""

    def __init__(self, archive: Path, folder: Path, limits: UnpackLimits | None = None):
        self.limits = lim = limits or UnpackLimits()
        size = Path(archive).stat().st_size
        if lim.max_bytes is not None:
            self.limit, self.why = lim.max_bytes, "the --max-unpack-gb limit"
        else:
            self.limit = int(lim.multiple * size)
            self.why = f"{lim.multiple:g}× the archive's {gb(size)} GB; --max-unpack-gb GB sets another limit"
        self.folder = Path(folder)
        self.free = disk_free(self.folder) - lim.min_free
        self.written = 0
        self.members = 0

    def declared(self, members: int, nbytes: int, name: str = "") -> None:
        """Check what the archive's headers declare — ``members`` members of ``nbytes`` bytes in all, up to
        member ``name`` (``""``: the whole archive) — against the limits, before anything is written (nothing
        is counted)."""
        self._too_many(members)
        self.room(name, nbytes)

    def add_members(self, n: int = 1) -> None:
        """Count ``n`` more members (files, folders, links)."""
        self.members += n
        self._too_many(self.members)

    def _too_many(self, members: int) -> None:
        if members > self.limits.max_members:
            raise ArchiveTooLarge(f"it holds more than {self.limits.max_members} members (the limit; a dataset "
                                  "archive holds a few thousand)")

    def room(self, name: str, n: int) -> None:
        """Check that ``n`` more bytes (of member ``name``; ``""``: the archive's declared total) fit in both
        byte limits, without counting them."""
        what = f"member {name!r} takes the unpacked size" if name else f"its members add up to {gb(n)} GB,"
        if self.written + n > self.limit:
            raise ArchiveTooLarge(f"{what} past {gb(self.limit)} GB ({self.why})")
        if self.written + n > self.free:
            raise ArchiveTooLarge(f"{what} past the {gb(max(self.free, 0))} GB free on the disk of {self.folder} "
                                  f"(keeping {gb(self.limits.min_free)} GB spare); free some space")

    def ratio(self, name: str, size: int, compressed: int) -> None:
        """Check a member's unpacked ``size`` against its ``compressed`` bytes (:data:`MAX_RATIO`)."""
        lim = self.limits
        if size > lim.ratio_floor and size > lim.max_ratio * max(compressed, 1):
            raise ArchiveTooLarge(f"member {name!r} expands {size / max(compressed, 1):.0f}× ({gb(size)} GB from "
                                  f"{compressed} compressed bytes; the limit is {lim.max_ratio:g}× — a zip bomb?)")

    def copy(self, src: IO[bytes], dst: IO[bytes], name: str, consumed: Callable[[], int] | None = None) -> int:
        """Stream member ``name`` from ``src`` to ``dst`` within the limits; returns its bytes.

        ``consumed()``, when given, is the position in the compressed archive, so that the member's
        ratio is checked while it streams (a compressed tar)."""
        start = consumed() if consumed is not None else 0
        n = 0
        while buf := src.read(CHUNK_BYTES):
            self.room(name, len(buf))
            dst.write(buf)
            n += len(buf)
            self.written += len(buf)
            if consumed is not None:
                self.ratio(name, n, consumed() - start)
        return n

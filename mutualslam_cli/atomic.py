"""Atomic file writes: a reader sees the old file or the new one, never a half-written one.

Every file mslam writes goes through here (results, caches, trajectories, weights): the data
goes to a temporary file in the destination's folder, which is then renamed over it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

_UMASK = os.umask(0o022)  # read the process umask once (at import, before any worker thread) ...
os.umask(_UMASK)  # ... and put it back


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on error it is removed.

    For writers that want a file name (``torch.save``, ``np.save``); the parent folder is created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions, like open()
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (flushed to disk before the rename)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_with(path: str | os.PathLike[str], write: Callable[[str], bool], what: str) -> None:
    """Write ``path`` atomically with a writer that picks the format from the file name's extension
    (open3d's): ``write(name)`` writes a temporary file of the same extension and returns success.

    Raises:
        OSError: ``write`` returned False (naming ``path`` and ``what`` was being written).
    """
    with atomic_path(path) as tmp:
        side = tmp.with_name(tmp.name + Path(path).suffix)
        try:
            if not write(str(side)):
                raise OSError(f"{path}: could not write the {what}")
            with open(side, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(side, tmp)
        finally:
            side.unlink(missing_ok=True)

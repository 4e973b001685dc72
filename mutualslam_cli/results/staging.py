"""A run's folder changes only when the run completes: the run writes a staging folder beside it, which then
replaces the run folder in one rename.

:func:`staged` yields ``<parent>/.<name>.staging-XXXX``; when the ``with`` block returns, that folder takes
the run folder's place — on Linux by ``renameat2(RENAME_EXCHANGE)``, one atomic step in which a reader sees
the old run or the new one, never neither — and the old run is removed. When the block raises (a failed
stage, a full disk, Ctrl-C), the staging folder is removed and the run folder is as it was, byte for byte:
a failed ``--force`` keeps the old, complete run. A process killed mid-run leaves only its staging folder,
which the next run of the same folder removes (hidden: ``report`` and ``ablate`` never see it).

The caller holds the run folder's lock (:func:`~mutualslam_cli.results.lock.hold_lock` with ``beside``: the
lock file is ``<parent>/.<name>.lock``, which no rename touches), so only one process stages a folder at a
time and every staging folder found beside it belongs to a process that died.
"""

from __future__ import annotations

import ctypes
import errno
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

_UMASK = os.umask(0o022)
os.umask(_UMASK)
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def staging_prefix(folder: Path) -> str:
    """The name every staging folder of ``folder`` starts with: ``.<name>.staging-``."""
    return f".{folder.name}.staging-"


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap ``a`` and ``b`` in one step (Linux ``renameat2``); False where the system or file system cannot."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(b))


def _sync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def replace_folder(new: Path, folder: Path) -> None:
    """Put the folder ``new`` in the place of ``folder`` (which may be missing) and remove what was there."""
    if not os.path.lexists(folder):
        os.rename(new, folder)
    elif _exchange(new, folder):
        _remove(new)  # now the old run
    else:  # no atomic exchange here: two renames, with a moment in which the folder is missing
        old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=folder.parent))
        os.rename(folder, old / folder.name)
        try:
            os.rename(new, folder)
        except BaseException:
            os.rename(old / folder.name, folder)
            raise
        _remove(old)
    _sync_dir(folder.parent)


@contextmanager
def staged(folder: str | os.PathLike[str], from_current: bool = False) -> Iterator[Path]:
    """Yield a fresh staging folder beside ``folder``; it replaces ``folder`` when the block returns and is
    removed when the block raises (module docstring). The caller holds ``folder``'s lock.

    Args:
        from_current: start from the files of the current ``folder`` (``mslam fuse`` adds to a finished run).
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    prefix = staging_prefix(folder)
    for stale in folder.parent.iterdir():
        if stale.name.startswith((prefix, f".{folder.name}.old-")):  # left by a process that died
            log.info("removing %s, left by a run that did not finish", stale)
            _remove(stale)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=folder.parent))
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700; a run folder gets the usual permissions
        if from_current and folder.is_dir():  # copies, not hard links: a writer that edits a file in place
            shutil.copytree(folder, tmp, symlinks=True, dirs_exist_ok=True)  # must not reach the original
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    try:
        replace_folder(tmp, folder)
    except BaseException:
        _remove(tmp)
        raise

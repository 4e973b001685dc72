"""One process at a time per result folder: an advisory ``flock`` on its lock file.

``mslam run`` (and ``eval-depth``, ``fuse``) holds the lock of its run folder
(``<out>/<seq>/<scheme>/seed<k>/``) while it works on it, and ``mslam ablate`` the lock of its results
root, so two processes started on the same folder never interleave their files: the second stops at
once with :class:`~mutualslam_cli.errors.ResultsLocked`, naming the holder.

A results root's lock file is ``<folder>/.lock``. A run folder's is beside it, ``<parent>/.<name>.lock``
(``beside=True``): a run writes a staging folder that replaces the run folder whole when the run completes
(:mod:`~mutualslam_cli.results.staging`), so a lock file inside it would be replaced with it, and a run
that fails would still have changed the old run's folder.

Usage::

    with hold_lock(folder, "mslam run", beside=True):
        ...  # only this process works on folder

Choices:

- ``fcntl.flock(LOCK_EX | LOCK_NB)``: the kernel drops the lock when the holder's file is closed,
  which includes the holder dying (``kill -9``, a crash, a cluster job hitting its time limit).
  A ``.lock`` *file* therefore never blocks anybody by itself: it stays in the folder after a run
  (deleting it on release would let two processes lock two different files of the same name)
  and holds the pid, host, start time and command of the last holder, for the message of the
  next process that finds the folder locked.
- The lock file is written in place, not through :mod:`~mutualslam_cli.atomic`: renaming a new
  file over it would replace the very file the holder has locked. It is a note for humans; no
  result depends on it, and :func:`~mutualslam_cli.results.run_folder.is_complete` ignores it. The same
  holds for the folder it lives in: it is never renamed while the lock exists (hence ``beside``).
- Not re-entrant: a second :func:`hold_lock` on the same folder fails even in the holding process.
  A child forked while the lock is held shares it until the child exits (spawned children do
  not).
- On a filesystem without ``flock`` support the work goes on unlocked, with a warning. Linux NFS
  clients map ``flock`` to NFS byte-range locks, which do work between machines.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path

from mutualslam_cli.errors import ResultsLocked
from mutualslam_cli.types import JSONObject

log = logging.getLogger(__name__)

#: File name of the lock inside a locked folder.
LOCK_NAME = ".lock"

_UNSUPPORTED = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}


def lock_path(folder: str | os.PathLike[str], beside: bool = False) -> Path:
    """``<folder>/.lock``; with ``beside``, ``<parent>/.<name>.lock`` (a run folder, replaced whole by a run)."""
    folder = Path(folder)
    return folder.parent / f".{folder.name}{LOCK_NAME}" if beside else folder / LOCK_NAME


def read_holder(folder: str | os.PathLike[str], beside: bool = False) -> JSONObject:
    """What the current (or last) holder wrote into the lock file of ``folder`` (:func:`lock_path`): ``pid``,
    ``host``, ``since`` (ISO 8601 local time), ``what`` and ``argv``; ``{}`` when the file is absent, empty or
    unreadable."""
    try:
        info = json.loads(lock_path(folder, beside).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _locked_message(folder: Path, what: str, holder: JSONObject) -> str:
    if holder.get("pid") is not None:
        who = (f"{holder.get('what') or 'another process'} (pid {holder['pid']} on {holder.get('host', '?')}, "
               f"since {holder.get('since', '?')})")
    else:
        who = "another process that is just starting"
    return (f"{folder} is locked by {who}; {what} would interleave its files with it. Wait for it to "
            f"finish, or stop it (a stopped process releases the lock at once) and run again")


@contextmanager
def hold_lock(folder: str | os.PathLike[str], what: str, beside: bool = False) -> Iterator[None]:
    """Hold the exclusive lock of ``folder`` for the duration of the ``with`` block.

    Creates ``folder`` (with ``beside``: only its parent) and the lock file (:func:`lock_path`) when
    needed, takes the lock without waiting, records the holder (pid, host, start time, ``what``,
    ``sys.argv``) in the lock file, and releases the lock when the block exits, normally or by an exception.

    Args:
        folder: the folder to lock (a run folder, or a grid's results root).
        what: what the caller is doing, e.g. ``"mslam run"``; shown to whoever finds the folder locked.
        beside: the lock file is beside ``folder``, not in it (a run folder: it is replaced whole).

    Raises:
        ResultsLocked: another open file holds the lock (another process, or this one: not
            re-entrant). The message names the folder, the holder's pid, host, start time and
            command, and what to do.
    """
    folder = Path(folder)
    path = lock_path(folder, beside)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    try:
        if _try_lock(fd, folder, what, beside):
            info = {"pid": os.getpid(), "host": socket.gethostname(), "what": what,
                    "since": datetime.now().astimezone().isoformat(timespec="seconds"), "argv": sys.argv}
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode("utf-8"), 0)
        yield
    finally:
        os.close(fd)  # closing the last descriptor releases the flock


def _try_lock(fd: int, folder: Path, what: str, beside: bool) -> bool:
    """Lock ``fd`` without waiting: True when locked, False when the filesystem has no locks."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise ResultsLocked(_locked_message(folder, what, read_holder(folder, beside))) from None
    except OSError as e:
        if e.errno not in _UNSUPPORTED:
            raise
        log.warning("%s: the filesystem does not support file locks (%s); working without a lock", folder, e.strerror)
        return False
    return True

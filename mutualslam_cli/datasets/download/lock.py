"""One process at a time per downloaded file: an advisory ``flock`` on ``<download folder>/NAME.lock``.

``mslam datasets download`` holds the lock of every file of an entry (its archive, its GT file) from
before the first byte is fetched until the archive is unpacked and its checksum recorded. A second
command that needs the same file does not wait: it stops at once with
:class:`~mutualslam_cli.errors.DownloadLocked`, one line naming the file and the holder (pid, host,
since when), and touches nothing. Not waiting is deliberate: a download takes minutes to hours, and
the second command would only find the work done (run it again afterwards: it skips or reuses).

As for result folders (:mod:`~mutualslam_cli.results.lock`): the kernel drops the lock when the holder
exits, however it exits, so a ``.lock`` file never blocks by itself and stays beside the download; it
holds the last holder's pid, host and start time for the message. On a file system without locks the
download goes on unlocked, with a warning. :func:`locked_update` is the short, *blocking* variant for
read-modify-write of a small shared file (``checksums.json``), held for milliseconds.

A ``.lock`` file is opened without following a symbolic link, and the holder's record is read through
its schema (:data:`LOCK_SCHEMA`): one of another shape is named as damaged in the message, never shown as
a holder (:mod:`~mutualslam_cli.datasets.download.files`).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from datetime import datetime
from pathlib import Path

from mutualslam_cli.datasets.download.files import (
    COUNT,
    TEXT,
    Schema,
    check_record,
    open_no_follow,
    read_text_no_follow,
)
from mutualslam_cli.errors import DamagedRecord, DownloadLocked

log = logging.getLogger(__name__)

LOCK_SUFFIX = ".lock"
_UNSUPPORTED = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}
LOCK_SCHEMA: Schema = {"pid": COUNT, "host": TEXT, "since": TEXT}
"""The fields of a ``.lock`` file's holder record."""


def _holder(path: Path) -> str:
    """Who holds the lock ``path``, from its record (read through :data:`LOCK_SCHEMA`)."""
    try:
        text = read_text_no_follow(path)
        if text is None or not text.strip():  # the holder has not written its record yet
            return "a process that is just starting"
        info = check_record(json.loads(text), LOCK_SCHEMA, str(path))
    except ValueError as e:
        return f"holder unknown: {path}: damaged record (not valid JSON: {e})"
    except DamagedRecord as e:
        return f"holder unknown: {e} (damaged record)"
    except OSError as e:
        return f"holder unknown: {path}: cannot read it ({e.strerror or e})"
    return f"pid {info['pid']} on {info['host']}, since {info['since']}"


def _open_locked(path: Path, blocking: bool) -> int:
    """An open descriptor of ``path`` holding its flock (not locked, with a warning, where the file system
    has no locks); ``BlockingIOError`` when not ``blocking`` and another open file holds it."""
    fd = open_no_follow(path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except BlockingIOError:
        os.close(fd)
        raise
    except OSError as e:
        if e.errno not in _UNSUPPORTED:
            os.close(fd)
            raise
        log.warning("%s: the file system does not support file locks (%s); going on without one", path, e.strerror)
    return fd


@contextmanager
def download_lock(folder: Path, names: list[str]) -> Iterator[None]:
    """Hold ``folder/NAME.lock`` for each of ``names`` (safe file names) during the ``with`` block.

    Raises:
        DownloadLocked: another open file holds one of the locks; those taken already are released.
    """
    with ExitStack() as stack:
        for name in names:
            path = Path(folder) / (name + LOCK_SUFFIX)
            try:
                fd = _open_locked(path, blocking=False)
            except BlockingIOError:
                raise DownloadLocked(
                    f"{Path(folder) / name}: another mslam process ({_holder(path)}) is downloading or unpacking "
                    "this file; nothing was touched — wait for it to finish (or stop it) and run the command "
                    "again") from None
            stack.callback(os.close, fd)  # closing the descriptor releases the lock
            info = {"pid": os.getpid(), "host": socket.gethostname(),
                    "since": datetime.now().astimezone().isoformat(timespec="seconds")}
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode("utf-8"), 0)
        yield


@contextmanager
def locked_update(path: Path) -> Iterator[None]:
    """Wait for and hold ``path + ".lock"`` while the block reads and rewrites the small file ``path``."""
    fd = _open_locked(Path(str(path) + LOCK_SUFFIX), blocking=True)
    try:
        yield
    finally:
        os.close(fd)

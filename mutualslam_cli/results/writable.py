"""Whether a results or report folder can be written, and one line saying why not.

:func:`check_output_folder` runs before any work (``mslam run``, ``eval-depth``, ``ablate``, ``report``),
creating nothing, so a ``--out`` that is a file, a read-only folder or one without permission is refused at
once. :func:`write_errors` turns what a write can still meet later (a full disk mid-run, a sub-folder made
read-only) into the same :class:`~mutualslam_cli.errors.OutputError` — naming the path and what to do — when
the failing path lies under the folder, or the error is one only a write raises (no space, a read-only file
system), or the disk is found full after the failure (writers that lose ``errno``: numpy's short write,
torch's zip writer). Any other error passes through unchanged.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from mutualslam_cli.errors import OutputError

#: Free bytes below which a failed write is taken for a full disk.
LOW_SPACE = 16 << 20
_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
_READ_ONLY = {errno.EROFS}
_DENIED = {errno.EACCES, errno.EPERM}
_NOT_A_FOLDER = {errno.ENOTDIR, errno.EEXIST, errno.EISDIR}
#: errno values that only a write raises: an error with one of them is a write error wherever its path is.
_WRITE_ONLY = _FULL | _READ_ONLY


def _reason(code: int | None, exc: BaseException | None = None) -> str:
    """What went wrong and what to do, for an errno (``None``: a writer that lost it on a full disk)."""
    if code is None or code in _FULL:
        what = os.strerror(code) if code is not None else f"the disk is full: {exc}"
        return f"{what}; free space there (or choose another --out) and run again"
    if code in _READ_ONLY:
        return f"{os.strerror(code)}; choose another --out"
    if code in _DENIED:
        return f"{os.strerror(code)}; make it writable or choose another --out"
    if code in _NOT_A_FOLDER:
        return f"{os.strerror(code)}: a file is where a folder should be; move it away or choose another --out"
    return f"{os.strerror(code)}; choose another --out"


def _is_under(path: str | os.PathLike[str] | None, root: Path) -> bool:
    if path is None:
        return False
    try:
        Path(os.path.abspath(path)).relative_to(os.path.abspath(root))
    except ValueError:
        return False
    return True


def _disk_full(path: Path) -> bool:
    """Whether the file system of ``path`` (or of its nearest existing parent) has under :data:`LOW_SPACE` free."""
    for p in (path, *path.parents):
        if p.exists():
            try:
                return shutil.disk_usage(p).free < LOW_SPACE
            except OSError:
                return False
    return False


def output_error(exc: BaseException, root: str | os.PathLike[str], state: str = "") -> OutputError | None:
    """The :class:`OutputError` for ``exc`` raised while writing under ``root``, or ``None`` when ``exc`` is not
    a write error there (module docstring). ``state``: what became of the work (appended to the message)."""
    root = Path(root)
    code = getattr(exc, "errno", None) if isinstance(exc, OSError) else None
    if isinstance(exc, OSError) and code is not None and (code in _WRITE_ONLY or _is_under(exc.filename, root)):
        where, reason = (exc.filename if exc.filename is not None else root), _reason(code)
    elif isinstance(exc, (OSError, RuntimeError)) and _disk_full(root):
        where, reason = root, _reason(None, exc)
    else:
        return None
    return OutputError(f"{where}: cannot write: {reason}" + (f"; {state}" if state else ""))


@contextmanager
def write_errors(root: str | os.PathLike[str], state: str = "") -> Iterator[None]:
    """Within the block, a write error under ``root`` (:func:`output_error`) becomes :class:`OutputError`."""
    try:
        yield
    except (OSError, RuntimeError) as e:
        err = output_error(e, root, state)
        if err is None:
            raise
        raise err from None


def check_output_folder(folder: str | os.PathLike[str], what: str = "results") -> Path:
    """Make sure ``folder`` can take the ``what`` before any work, creating nothing: an existing folder gets a
    file made and removed in it; a missing one needs its nearest existing parent to be a folder this process
    may write into (it is created by the first write).

    Returns:
        ``folder`` as a :class:`~pathlib.Path`.

    Raises:
        OutputError: ``folder`` (or a parent) is a file, is read-only or denied.
    """
    folder = Path(folder)
    base = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if base is not None and not base.is_dir():
        raise OutputError(f"{base}: is a file, not a folder for the {what}; " + (
            "choose another --out (a folder, created when missing)" if base == folder else
            f"{folder} cannot be made under it: choose another --out"))
    try:
        if base == folder:
            fd, probe = tempfile.mkstemp(prefix=".mslam-probe-", dir=folder)
            os.close(fd)
            os.unlink(probe)
        elif base is not None and not os.access(base, os.W_OK | os.X_OK):
            code = errno.EROFS if _read_only(base) else errno.EACCES
            raise OSError(code, os.strerror(code))
    except OSError as e:
        where = folder if base == folder else base
        raise OutputError(f"{where}: cannot write the {what} there: {_reason(e.errno)}") from None
    return folder


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False

"""Names from outside that become paths: one rule, checked before the name touches the file system.

A file name that comes from a URL (``datasets.yaml``'s ``download:`` block, ``--base-url``) or from a
registry field (``gt:``, ``sequence:``) is *validated*, never decoded into a path:

- the URL's last path segment is percent-decoded, and the decoded text must be a single path
  component: no ``/``, ``\\`` or control character, not ``.`` or ``..``, not starting with ``.``;
- it uses a conservative character set: ASCII letters, digits, ``_``, ``-``, ``+`` and ``.``, starting
  with a letter, digit or ``_`` (every file the publishers serve has such a name), at most
  :data:`MAX_NAME_CHARS` characters;
- it is not one of mslam's own files in the download folder (:data:`RESERVED_NAMES`, or ending in
  :data:`RESERVED_SUFFIXES`);
- the final path (:func:`path_inside`) is checked to lie directly inside its folder after resolving
  symbolic links.

A name that breaks the rule raises :class:`~mutualslam_cli.errors.UnsafeName` naming where it came from;
nothing has been written by then. Archive *members* are relative paths, not single names: they
follow :func:`~mutualslam_cli.datasets.download.unpack.safe_relpath`, which applies the same "no ``..``, no
absolute path, stays inside" rule component by component.
"""

from __future__ import annotations

import os
import re
import urllib.parse
from pathlib import Path

from mutualslam_cli.errors import UnsafeName

#: The characters and shape of a safe file name.
SAFE_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_+.-]*")
MAX_NAME_CHARS = 200
"""Longest accepted name (characters; file systems allow 255 bytes, and ``.part``/``.lock`` are appended)."""
RESERVED_NAMES = frozenset({"checksums.json"})
"""Files of mslam's own in the download folder, which a downloaded file must not replace."""
RESERVED_SUFFIXES = (".part", ".partinfo", ".lock")
"""Suffixes of mslam's own files beside a download (``NAME.part``, ``NAME.partinfo``, ``NAME.lock``)."""

_EXPECTED = ("expected one file name of letters, digits, '_', '-', '+' and '.', not starting with '.', "
             "without '/' or '..'")


def check_name(name: str, where: str) -> str:
    """``name`` when it is a safe single file name (see the module docstring).

    Args:
        name: the decoded name.
        where: where it came from, for the message (e.g. ``"datasets.yaml entry 'x': gt"``).

    Raises:
        UnsafeName: one line naming ``where``, the name and the rule.
    """
    problem = None
    if not name:
        problem = "is empty"
    elif any(c in name for c in "/\\") or name in (".", ".."):
        problem = "is a path, not one file name"
    elif name.startswith("."):
        problem = "starts with '.'"
    elif len(name) > MAX_NAME_CHARS:
        problem = f"is longer than {MAX_NAME_CHARS} characters"
    elif not SAFE_NAME_RE.fullmatch(name):
        problem = "has characters outside the safe set"
    elif name in RESERVED_NAMES or name.endswith(RESERVED_SUFFIXES):
        problem = "is the name of one of mslam's own files"
    if problem:
        raise UnsafeName(f"{where}: file name {name!r} {problem}; {_EXPECTED} — refused, nothing written")
    return name


def url_file_name(url: str) -> str:
    """The safe file name at the end of ``url``'s path (percent-decoded, then checked).

    Raises:
        UnsafeName: the URL is not http(s), or its last segment is not a safe file name.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise UnsafeName(f"{url}: expected an http:// or https:// URL ending in a file name")
    raw = parts.path.rsplit("/", 1)[-1]
    try:
        name = urllib.parse.unquote(raw, errors="strict")
    except UnicodeDecodeError:
        raise UnsafeName(f"{url}: the URL's file name {raw!r} is not UTF-8 once decoded; {_EXPECTED}") from None
    return check_name(name, f"{url}: the URL's file name")


def path_inside(folder: Path, name: str, where: str) -> Path:
    """``folder / name`` after :func:`check_name`, checked to resolve to a file directly inside ``folder``.

    Raises:
        UnsafeName: the name breaks the rule, or the path resolves elsewhere (a symbolic link).
    """
    check_name(name, where)
    path = Path(folder) / name
    if os.path.realpath(path) != os.path.join(os.path.realpath(folder), name):
        raise UnsafeName(f"{where}: {path} resolves to {os.path.realpath(path)}, outside {folder} (a symbolic "
                         "link?); refused, nothing written")
    return path

"""How mslam opens its own files in ``<data root>/_downloads/``: never through a symbolic link, and its JSON
records only through one schema check.

Whoever can write into the download folder (another user on a shared data disk, a crafted archive
unpacked there by another tool) could leave a symbolic link where mslam expects its own file, so that
appending to ``NAME.part`` overwrites the file it points to, or a record of any shape where mslam expects
its own. So:

- :func:`open_no_follow` opens with ``O_NOFOLLOW`` (the kernel refuses a link as the last component);
  :func:`refuse_link` checks a path that is about to be renamed, replaced or measured. Either raises
  :class:`~mutualslam_cli.errors.DamagedRecord` naming the path, and nothing is written.
- :func:`read_record` reads a JSON object (``NAME.partinfo``, ``NAME.lock``, an entry of
  ``checksums.json``) and checks each field against a :data:`Schema`; a record of another shape raises
  :class:`~mutualslam_cli.errors.DamagedRecord` naming the file, the field, what was expected and what
  is there. The caller decides what a damaged record means (start over, or say how to fix it); it is
  never trusted.
"""

from __future__ import annotations

import errno
import json
import os
import re
from collections.abc import Callable
from pathlib import Path

from mutualslam_cli.errors import DamagedRecord
from mutualslam_cli.types import JSON, JSONObject

#: A field's rule: what the message says is expected, and the test of a value (a missing field is ``None``).
Rule = tuple[str, Callable[[JSON], bool]]
#: Field name → rule.
Schema = dict[str, Rule]


def _count(v: JSON) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


TEXT: Rule = ("text", lambda v: isinstance(v, str))
OPTIONAL_TEXT: Rule = ("text or null", lambda v: v is None or isinstance(v, str))
COUNT: Rule = ("a whole number ≥ 0", _count)
OPTIONAL_COUNT: Rule = ("a whole number ≥ 0 or null", lambda v: v is None or _count(v))
SHA256: Rule = ("64 lower-case hex digits", lambda v: isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v)
                is not None)

_LINK = "is a symbolic link; mslam opens its own files here only directly (remove the link; nothing was written)"


def _short(value: JSON) -> str:
    text = json.dumps(value, ensure_ascii=True)
    return text if len(text) <= 60 else text[:57] + "..."


def refuse_link(path: Path) -> None:
    """Raise :class:`DamagedRecord` when ``path`` is a symbolic link (absent or a plain file: nothing to do)."""
    if os.path.islink(path):
        raise DamagedRecord(f"{path}: {_LINK}")


def open_no_follow(path: Path, flags: int, mode: int = 0o666) -> int:
    """``os.open(path, flags | O_NOFOLLOW | O_CLOEXEC)``; a link as ``path`` raises :class:`DamagedRecord`."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except OSError as e:
        if e.errno == errno.ELOOP or os.path.islink(path):
            raise DamagedRecord(f"{path}: {_LINK}") from None
        raise


def read_text_no_follow(path: Path, limit: int = 1 << 20) -> str | None:
    """The text of the small file ``path`` (at most ``limit`` bytes), or ``None`` when it does not exist.

    Raises:
        DamagedRecord: a link, larger than ``limit``, or not UTF-8.
    """
    try:
        fd = open_no_follow(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise DamagedRecord(f"{path}: larger than {limit} bytes; expected a small JSON record")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise DamagedRecord(f"{path}: not UTF-8 text; expected a small JSON record") from None


def check_record(data: JSON, schema: Schema, where: str) -> JSONObject:
    """``data`` when it is a JSON object whose fields follow ``schema`` (other fields are kept, unchecked).

    Raises:
        DamagedRecord: ``where``, the first wrong field, what was expected and what is there.
    """
    if not isinstance(data, dict):
        raise DamagedRecord(f"{where}: expected a JSON object with {', '.join(schema)}, got {_short(data)}")
    for name, (expected, ok) in schema.items():
        if not ok(data.get(name)):
            got = _short(data[name]) if name in data else "nothing"
            raise DamagedRecord(f"{where}: field '{name}' must be {expected}, got {got}")
    return data


def read_record(path: Path, schema: Schema) -> JSONObject | None:
    """The JSON object in ``path`` checked against ``schema``, or ``None`` when ``path`` does not exist.

    Raises:
        DamagedRecord: a link, not JSON, or a field of another shape (see :func:`check_record`).
    """
    text = read_text_no_follow(path)
    if text is None:
        return None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:  # what json.loads of a str raises (a ValueError)
        raise DamagedRecord(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None
    return check_record(data, schema, str(path))


def text_field(record: JSONObject, name: str) -> str | None:
    """Field ``name`` of a record checked by :func:`check_record` whose schema says ``TEXT`` or ``OPTIONAL_TEXT``
    (``None``: null, or absent)."""
    v = record.get(name)
    return v if isinstance(v, str) else None


def count_field(record: JSONObject, name: str) -> int | None:
    """Field ``name`` of a record checked by :func:`check_record` whose schema says ``COUNT`` or
    ``OPTIONAL_COUNT`` (``None``: null, or absent)."""
    v = record.get(name)
    return v if isinstance(v, int) and not isinstance(v, bool) else None

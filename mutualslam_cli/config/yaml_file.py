"""YAML a user wrote (a run config, ``datasets.yaml``, a camera file, a ``--set`` value), read strictly.

``yaml.safe_load`` never runs code, but it trusts the shape: a key given twice silently keeps the last
block, and a few aliases (``*name``) can stand for billions of values ("billion laughs"), which every walk
over the data then expands. :func:`parse_yaml` refuses both, and :func:`read_yaml_mapping` adds what a
file can be wrong in: not a regular file (a folder, a pipe), too large, not UTF-8 text, not a mapping at
the top. Each refusal is one line naming the file (and the line, where there is one) and raised as the
caller's error class (:class:`~mutualslam_cli.errors.ConfigError` by default).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Hashable
from pathlib import Path
from typing import Any, TypeGuard

import yaml

from mutualslam_cli.errors import ConfigError, MslamError
from mutualslam_cli.types import JSON

#: Aliases (``*name``) one document may hold. No settings file needs one; a handful keeps hand-written
#: anchors working, and 16 of them can expand into at most a few hundred values.
ALIAS_BUDGET = 16
#: The largest YAML file read (bytes): settings files are a few kB.
MAX_BYTES = 4 << 20


#: The ``note`` of the YAML errors :class:`StrictLoader` raises for what it refuses (not a syntax error).
REFUSED = "refused by mslam's strict YAML reader"


def refusal(reason: str, mark: yaml.Mark) -> yaml.MarkedYAMLError:
    """The YAML error of a refusal: ``reason`` at ``mark`` (the line), told apart by :func:`is_refusal`."""
    return yaml.MarkedYAMLError(problem=reason, problem_mark=mark, note=REFUSED)


def is_refusal(e: BaseException) -> TypeGuard[yaml.MarkedYAMLError]:
    """Whether ``e`` is a refusal of :class:`StrictLoader` (a key given twice, too many aliases)."""
    return isinstance(e, yaml.MarkedYAMLError) and e.note == REFUSED


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping and more than :data:`ALIAS_BUDGET`
    aliases."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > ALIAS_BUDGET:
                raise refusal(f"more than {ALIAS_BUDGET} aliases (*name): refused, as a few aliases can stand for "
                              "billions of values", self.peek_event().start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict[Hashable, object]:
        if isinstance(node, yaml.MappingNode):
            first: dict[object, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # `<<: *base` then own keys: overriding the merged ones is what a merge is for
                key = self.construct_object(key_node, deep=True)
                try:
                    seen = key in first
                except TypeError:  # an unhashable key: the constructor names it below
                    continue
                if seen:
                    raise refusal(f"key {key!r} is given twice in one mapping (first on line {first[key] + 1}); "
                                  "the second would silently replace the first", key_node.start_mark)
                first[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def _problem(e: yaml.YAMLError) -> tuple[str, str]:
    """``(":line", reason)`` of a YAML error (``""`` where it has no position)."""
    mark = getattr(e, "problem_mark", None)
    where = f":{mark.line + 1}" if mark is not None else ""
    if is_refusal(e):
        return where, str(e.problem)
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    return where, f"not valid YAML ({problem})"


def parse_yaml(text: str, where: str, error: type[MslamError] = ConfigError) -> JSON:
    """The value of one YAML document, read by :class:`StrictLoader`.

    Typed as :data:`~mutualslam_cli.types.JSON`, what a settings file holds; YAML can also spell a date, a
    binary or a set (``!!set``), which the readers of the value refuse as a wrong type.

    Args:
        where: what the text is (a file name, ``--set 'key=value'``), the start of any message.
        error: the class raised.

    Raises:
        error: not valid YAML, a duplicate key, too many aliases (``"<where>:<line>: <reason>"``).
    """
    try:
        return yaml.load(text, Loader=StrictLoader)  # StrictLoader is a SafeLoader
    except yaml.YAMLError as e:
        line, reason = _problem(e)
        raise error(f"{where}{line}: {reason}") from None
    except RecursionError:
        raise error(f"{where}: nested too deeply to be a settings file") from None


def read_text_file(path: str | os.PathLike[str], error: type[MslamError] = ConfigError, what: str = "YAML file") -> str:
    """The UTF-8 text of the regular file ``path`` (at most :data:`MAX_BYTES`), or ``error`` naming it: missing,
    a folder or another non-file, unreadable, too large, not UTF-8."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: not found (expected a {what})") from None
    except OSError as e:
        raise error(f"{path}: cannot be read ({e.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a folder, not a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: not a regular file (a device, pipe or socket), not a {what}")
    if st.st_size > MAX_BYTES:
        raise error(f"{path}: {st.st_size} bytes; a {what} is at most {MAX_BYTES} bytes")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise error(f"{path}: cannot be read ({e.strerror})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); save it as UTF-8") \
            from None


def read_yaml_mapping(path: str | os.PathLike[str], error: type[MslamError] = ConfigError,
                      what: str = "YAML file") -> dict[str, Any]:
    """The YAML mapping in the file ``path`` (``{}`` for an empty file), read by :func:`read_text_file` and
    :func:`parse_yaml`: a :data:`~mutualslam_cli.types.JSONObject` whose fields the caller checks (typed
    ``Any``-valued as callers read it as their own shape).

    Raises:
        error: one line naming the file: every refusal of those two, or a top level that is not a mapping.
    """
    data = parse_yaml(read_text_file(path, error, what), str(path), error)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping (key: value lines) at the top of the {what}, "
                    f"got {type(data).__name__}")
    return data

"""Plain (YAML) values into typed, frozen dataclasses, and ``--set key=value`` overrides.

The machinery behind :mod:`mutualslam_cli.config`: every field is checked against its annotation
(``Literal`` choices, lists, mappings, optionals, bool / int / float / str), and an error names the
dotted key, what was expected and what was found; a string holds no NUL. The ranges of values (finite, a
count's bounds) are declared beside the fields and checked by :mod:`~mutualslam_cli.config.checks`.
``--set`` values are YAML, read by :mod:`~mutualslam_cli.config.yaml_file` as a config file is.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import TYPE_CHECKING, Literal, TypeVar

from mutualslam_cli.config.yaml_file import parse_yaml
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import JSON, JSONObject

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

#: A record class :func:`build` makes.
T = TypeVar("T", bound="DataclassInstance")


def coerce(value: JSON, tp: object, where: str) -> object:
    """Check/convert one YAML value to the annotated type ``tp`` (a type or a typing form such as
    ``list[str]``, ``Literal[...]``, ``X | None``); the value returned is of that type."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        if isinstance(value, bool) and {"on", "off"} <= set(typing.get_args(tp)):
            value = "on" if value else "off"  # YAML 1.1 reads a bare on/off as a boolean
        if value not in typing.get_args(tp):
            raise ConfigError(f"{where}: {value!r} is not one of {list(typing.get_args(tp))}")
        return value
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (elem,) = typing.get_args(tp)
        return [coerce(v, elem, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        kt, vt = typing.get_args(tp)
        return {coerce(k, kt, where): coerce(v, vt, f"{where}.{k}") for k, v in value.items()}
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return coerce(value, a, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: invalid value {value!r}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if tp is float:
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if value != value:
            raise ConfigError(f"{where} = nan: expected a finite number (NaN is not allowed)")
        try:
            return float(value)
        except OverflowError:  # an integer beyond a float's range: infinite, which its range refuses
            return float("inf") if value > 0 else float("-inf")
    if tp is str:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        if "\0" in str(value):
            raise ConfigError(f"{where} = {value!r}: expected a string without NUL characters")
        return str(value)
    return value


def build(cls: type[T], data: JSON, where: str) -> T:
    """An instance of the dataclass ``cls`` from a mapping of plain values, nested dataclasses
    included; an unknown key or a value of the wrong type raises :class:`ConfigError` naming it."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names, key=str)
    if unknown:
        raise ConfigError(f"{where or 'top level'}: unknown key(s) {unknown}; valid keys: {sorted(names)}")
    kwargs: dict[str, object] = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        tp = hints[f.name]
        key = f"{where}.{f.name}" if where else f.name
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):  # a nested record's hint is its class
            kwargs[f.name] = build(tp, {} if data[f.name] is None else data[f.name], key)
        else:
            kwargs[f.name] = coerce(data[f.name], tp, key)
    return cls(**kwargs)


def parse_override(text: str) -> tuple[list[str], JSON]:
    """``"adapt.lr=1e-4"`` → ``(["adapt", "lr"], 1e-4)``; the value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected key=value, e.g. adapt.lr=1e-4")
    key, raw = text.split("=", 1)
    value = parse_yaml(raw, f"--set {text!r}") if raw.strip() else ""
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {text!r}: empty key")
    return parts, value


def apply_overrides(data: JSONObject, overrides: list[str], create: bool) -> JSONObject:
    """Apply ``--set``-style ``key=value`` overrides to the nested mapping ``data`` in place.

    Args:
        create: make missing sections (a config file being read); otherwise every section on the
            way must exist (overrides on a complete config).
    """
    for ov in overrides:
        parts, value = parse_override(ov)
        node = data
        for p in parts[:-1]:
            if create and p not in node:
                node[p] = {}
            section = node.get(p)
            if not isinstance(section, dict):
                raise ConfigError(f"--set {ov!r}: {p} is not a config section")
            node = section
        node[parts[-1]] = value
    return data

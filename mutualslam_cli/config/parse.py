"""Plain (YAML) values into typed, frozen dataclasses, ``--set key=value`` overrides, and the checks
of the values the tool cannot work with (:func:`check_run`, :func:`check_vo`).

The machinery behind :mod:`mutualslam_cli.config`: every field is checked against its annotation
(``Literal`` choices, lists, mappings, optionals, bool / int / float / str), and an error names the
dotted key, what was expected and what was found.
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from typing import Any, Literal

import yaml

from mutualslam_cli.errors import ConfigError

#: The values of ``device`` (:mod:`~mutualslam_cli.device`).
DEVICE_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


def check_device_spec(spec: Any) -> None:
    """Raise :class:`ConfigError` unless ``spec`` is ``auto``, ``cpu``, ``cuda`` or ``cuda:N``."""
    if not isinstance(spec, str) or not DEVICE_PATTERN.match(spec):
        raise ConfigError(f"device: {spec!r} is not one of auto, cpu, cuda, cuda:N")


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Check/convert one YAML value to the annotated type ``tp``."""
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
            raise ConfigError(f"{where}: NaN is not allowed")
        return float(value)
    if tp is str:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
    return value


def build(cls: type, data: Any, where: str) -> Any:
    """An instance of the dataclass ``cls`` from a mapping of plain values, nested dataclasses
    included; an unknown key or a value of the wrong type raises :class:`ConfigError` naming it."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; valid keys: {sorted(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        tp = hints[f.name]
        key = f"{where}.{f.name}" if where else f.name
        if dataclasses.is_dataclass(tp):
            kwargs[f.name] = build(tp, data[f.name] or {}, key)
        else:
            kwargs[f.name] = coerce(data[f.name], tp, key)
    return cls(**kwargs)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"adapt.lr=1e-4"`` → ``(["adapt", "lr"], 1e-4)``; the value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected key=value, e.g. adapt.lr=1e-4")
    key, raw = text.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as e:
        raise ConfigError(f"--set {text!r}: value is not valid YAML ({e})") from None
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {text!r}: empty key")
    return parts, value


def apply_overrides(data: dict[str, Any], overrides: list[str], create: bool) -> dict[str, Any]:
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
            if not isinstance(node.get(p), dict):
                raise ConfigError(f"--set {ov!r}: {p} is not a config section")
            node = node[p]
        node[parts[-1]] = value
    return data


def check_vo(cfg: Any) -> None:
    """Raise :class:`ConfigError` for options of a ``VOConfig`` the front end cannot work with."""
    rules = [
        ("grid_size", cfg.grid_size >= 4, "an integer ≥ 4 (pixels)"),
        ("max_fts", cfg.max_fts >= max(cfg.min_tracked, 8), f"≥ min_tracked ({cfg.min_tracked}) and ≥ 8"),
        ("min_tracked", cfg.min_tracked >= 6, "≥ 6 (PnP needs at least 6 matches)"),
        ("core_kfs", cfg.core_kfs >= 2, "≥ 2 keyframes"),
        ("klt_window", cfg.klt_window >= 5, "≥ 5 pixels"),
        ("klt_levels", cfg.klt_levels >= 0, "≥ 0"),
        ("fb_threshold_px", cfg.fb_threshold_px > 0, "> 0 pixels"),
        ("ransac_threshold_px", cfg.ransac_threshold_px > 0, "> 0 pixels"),
        ("kf_min_parallax_px", cfg.kf_min_parallax_px > 0, "> 0 pixels"),
        ("kf_min_tracked_ratio", 0 < cfg.kf_min_tracked_ratio <= 1, "in (0, 1]"),
        ("inject_outliers", 0 <= cfg.inject_outliers < 1, "in [0, 1)"),
    ]
    for name, ok, expected in rules:
        if not ok:
            raise ConfigError(f"vo.{name} = {getattr(cfg, name)!r}: expected {expected}")


def check_run(cfg: Any) -> None:
    """Raise :class:`ConfigError` naming the first value of a ``RunConfig`` the tool cannot work with."""
    check_vo(cfg.vo)
    check_device_spec(cfg.device)
    checks = [
        (cfg.adapt.lr > 0, "adapt.lr must be > 0"),
        (cfg.adapt.validate_every >= 1, "adapt.validate_every (m) must be ≥ 1"),
        (cfg.adapt.patience >= 1, "adapt.patience (n) must be ≥ 1"),
        (cfg.adapt.steps_per_keyframe >= 1, "adapt.steps_per_keyframe must be ≥ 1"),
        ((cfg.adapt.step_cost_ms == "measured" or cfg.adapt.step_cost_ms > 0) and cfg.adapt.max_steps >= 1,
         "adapt.step_cost_ms must be > 0 or 'measured', adapt.max_steps ≥ 1"),
        (cfg.vo.inject_outliers == 0 or cfg.adapt.labels == "hindsight",
         "vo.inject_outliers corrupts the finished front end's map: it needs adapt.labels=hindsight"),
        (cfg.adapt.train_width % 32 == 0 and cfg.adapt.train_height % 32 == 0
         and 0 <= cfg.adapt.train_width <= cfg.net.width and 0 <= cfg.adapt.train_height <= cfg.net.height,
         "adapt.train_width/train_height must be multiples of 32 in [0, net.width/net.height] (0 = the net's)"),
        (0 <= cfg.adapt.freeze_stages <= 5, "adapt.freeze_stages must be in 0..5 (encoder stages)"),
        (cfg.adapt.val_max >= 0 and cfg.ba.window >= 0, "adapt.val_max and ba.window must be ≥ 0 (0 = all)"),
        (0 <= cfg.adapt.alpha <= 1, "adapt.alpha must be in [0, 1]"),
        (cfg.net.width % 32 == 0 and cfg.net.height % 32 == 0, "net.width and net.height must be multiples of 32"),
        (0 < cfg.net.min_depth < cfg.net.max_depth, "net.min_depth must be in (0, net.max_depth)"),
        (cfg.data.stride >= 1, "data.stride must be ≥ 1"),
        (cfg.data.max_frames >= 0, "data.max_frames must be ≥ 0"),
        (cfg.eval.pcd_threshold > 0, "eval.pcd_threshold must be > 0"),
        (cfg.eval.batch >= 0 and cfg.eval.export_frames >= 0,
         "eval.batch (0 = auto) and eval.export_frames must be ≥ 0"),
        (cfg.ba.max_targets >= 1 and cfg.ba.rounds >= 1 and cfg.ba.levels >= 1,
         "ba.max_targets, ba.rounds and ba.levels must be ≥ 1"),
        (0 <= cfg.ba.nearby_slots < cfg.ba.max_targets, "ba.nearby_slots must be in [0, ba.max_targets)"),
        (0 < cfg.ba.image_scale <= 1, "ba.image_scale must be in (0, 1]"),
        (0 < cfg.ba.huber_grey <= cfg.ba.outlier_grey, "ba.huber_grey must be in (0, ba.outlier_grey]"),
        (cfg.dense.every >= 0, "dense.every must be ≥ 0 (0 = keyframes)"),
        ("sequence" in cfg.dense.scalings and len(set(cfg.dense.scalings)) == len(cfg.dense.scalings),
         "dense.scalings must hold 'sequence' (the headline scores) and no name twice"),
        (cfg.dense.voxel_size > 0 and cfg.dense.trunc_voxels >= 1, "dense.voxel_size > 0 and dense.trunc_voxels ≥ 1"),
        (0 < cfg.dense.depth_min < cfg.dense.depth_max, "dense.depth_min must be in (0, dense.depth_max)"),
        (cfg.dense.block_resolution >= 2 and cfg.dense.block_count >= 1,
         "dense.block_resolution ≥ 2 and dense.block_count ≥ 1"),
        (cfg.dense.weight_threshold >= 0, "dense.weight_threshold must be ≥ 0"),
        (cfg.dense.render_width >= 32, "dense.render_width must be ≥ 32"),
    ]
    for ok, msg in checks:
        if not ok:
            raise ConfigError(msg)

"""The values the tool cannot work with: :func:`check_run` over a whole run configuration,
:func:`check_vo` over the front end's section (the front end checks it on its own too) and
:func:`check_device_spec` over a device name. Each raises :class:`~mutualslam_cli.errors.ConfigError`
naming the first offending key."""

from __future__ import annotations

import re
from typing import Any

from mutualslam_cli.errors import ConfigError

#: The values of ``device`` (:mod:`~mutualslam_cli.device`).
DEVICE_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


def check_device_spec(spec: Any) -> None:
    """Raise :class:`ConfigError` unless ``spec`` is ``auto``, ``cpu``, ``cuda`` or ``cuda:N``."""
    if not isinstance(spec, str) or not DEVICE_PATTERN.match(spec):
        raise ConfigError(f"device: {spec!r} is not one of auto, cpu, cuda, cuda:N")


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

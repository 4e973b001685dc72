"""The ``summary.json`` of a run (DESIGN §8): its required keys, the builder that records a value
or ``null`` with its reason, and the flat ``a.b.c`` view other tools read.

A value that cannot be computed is ``null`` and its reason is under ``notes`` (same dotted key),
never 0. Every stage writes its own keys (:mod:`mutualslam_cli.stages`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

#: Keys other tools read from ``summary.json`` (dotted paths), DESIGN §8.
SUMMARY_KEYS: tuple[str, ...] = (
    "depth.pcd.lsq.pretrained", "depth.pcd.lsq.adapted",
    "depth.pcd.median.pretrained", "depth.pcd.median.adapted",
    "depth.esi.pretrained", "depth.esi.adapted",
    "depth.pcd_nonkf.lsq.pretrained", "depth.pcd_nonkf.lsq.adapted",
    "depth.pcd_nonkf.median.pretrained", "depth.pcd_nonkf.median.adapted",
    "depth.esi_nonkf.pretrained", "depth.esi_nonkf.adapted",
    "depth.pcd.seq_lsq.pretrained", "depth.pcd.seq_lsq.adapted",
    "depth.pcd_online.lsq", "depth.pcd_online.median", "depth.pcd_online.seq_lsq",
    "adaptation.reg.shrink.mean",
    "trajectory.ate_rmse_m.vo", "trajectory.ate_rmse_m.ba", "trajectory.ate_rmse_m.all_frames",
    "trajectory.local_scale.vo.max_over_min", "trajectory.local_scale.ba.max_over_min",
    "trajectory.local_ate_m.vo", "trajectory.local_ate_m.ba",
    "vo.keyframes", "vo.tracked_fraction",
    "map.points.vo", "map.points.culled", "map.points.ba",
    "map.esi.vo", "map.esi.culled", "map.esi.ba",
    "timing.vo_fps", "timing.depth_ms", "timing.finetune_ms", "timing.ba_s", "timing.total_s",
)


def plain(x: Any) -> Any:
    """numpy scalars/arrays and Paths → JSON-safe Python values; NaN/inf → None."""
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, Path):
        return str(x)
    return x


class Summary:
    """Builds the nested ``summary.json`` with explicit nulls and reasons.

    >>> s = Summary()
    >>> s.set("vo.keyframes", 12)
    >>> s.absent("trajectory.ate_rmse_m.ba", "global BA not run")
    >>> s.to_dict()["trajectory"]["ate_rmse_m"]["ba"] is None
    True
    """

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}
        self.notes: dict[str, str] = {}

    @classmethod
    def from_dict(cls, nested: dict[str, Any], drop_prefix: str | None = None) -> Summary:
        """The builder of a written ``summary.json`` (``nested``), without the keys (and notes) that
        start with ``drop_prefix`` — a stage run again on a finished run rewrites its own keys."""
        flat = flatten(nested)
        notes = flat.pop("notes", None) or {}
        s = cls()
        keep = (lambda k: not k.startswith(drop_prefix)) if drop_prefix else (lambda k: True)
        s.values = {k: v for k, v in flat.items() if keep(k)}
        s.notes = {k: v for k, v in notes.items() if keep(k)}
        return s

    def set(self, key: str, value: Any, reason_if_missing: str = "not computed") -> None:
        """Set a dotted key; ``None``/NaN values are recorded as absent with the reason."""
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            self.absent(key, reason_if_missing)
        else:
            self.values[key] = value
            self.notes.pop(key, None)

    def absent(self, key: str, reason: str) -> None:
        """Record ``key`` as ``null`` with ``reason`` under ``notes``."""
        self.values[key] = None
        self.notes[key] = reason

    def to_dict(self, required: Iterable[str] = SUMMARY_KEYS) -> dict[str, Any]:
        """Nested dict; required keys never set are ``null`` with reason "not computed"."""
        vals = dict(self.values)
        notes = dict(self.notes)
        for k in required:
            if k not in vals:
                vals[k] = None
                notes.setdefault(k, "not computed by this run")
        nested: dict[str, Any] = {}
        for k, v in vals.items():
            node = nested
            parts = k.split(".")
            for p in parts[:-1]:
                node = node.setdefault(p, {})
            node[parts[-1]] = v
        nested["notes"] = dict(sorted(notes.items()))
        return plain(nested)


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dict → ``{"a.b.c": value}`` (``notes`` kept as one entry)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict) and k != "notes":
            out.update(flatten(v, key))
        else:
            out[key] = v
    return out

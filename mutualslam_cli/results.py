"""Result folders (DESIGN §8): atomic files, manifest, and the ``summary.json`` schema.

A run writes ``<out>/<sequence>/<scheme>/seed<k>/``. Every file is written to a temporary
name in the same folder and renamed, so a killed run never leaves a half-written file.
A run is complete when ``summary.json`` exists; it is written last.

``summary.json`` holds the keys of :data:`SUMMARY_KEYS`. A value that cannot be computed is
``null`` and its reason is under ``notes`` (same dotted key), never 0.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import yaml

from mutualslam_cli import __version__

#: Keys other tools read from ``summary.json`` (dotted paths), DESIGN §8.
SUMMARY_KEYS: tuple[str, ...] = (
    "depth.pcd.lsq.pretrained", "depth.pcd.lsq.adapted",
    "depth.pcd.median.pretrained", "depth.pcd.median.adapted",
    "depth.esi.pretrained", "depth.esi.adapted",
    "depth.pcd_nonkf.lsq.pretrained", "depth.pcd_nonkf.lsq.adapted",
    "depth.pcd_nonkf.median.pretrained", "depth.pcd_nonkf.median.adapted",
    "depth.esi_nonkf.pretrained", "depth.esi_nonkf.adapted",
    "trajectory.ate_rmse_m.vo", "trajectory.ate_rmse_m.ba", "trajectory.ate_rmse_m.all_frames",
    "vo.keyframes", "vo.tracked_fraction",
    "map.points.vo", "map.points.culled", "map.points.ba",
    "map.esi.vo", "map.esi.culled", "map.esi.ba",
    "timing.vo_fps", "timing.depth_ms", "timing.finetune_ms", "timing.ba_s", "timing.total_s",
)


def run_dir(out: str | Path, sequence: str, scheme: str, seed: int) -> Path:
    """``<out>/<sequence>/<scheme>/seed<k>``; ``+`` in scheme names is kept (valid in paths)."""
    return Path(out) / sequence / scheme / f"seed{seed}"


def is_complete(folder: Path) -> bool:
    """A run is complete when its ``summary.json`` exists."""
    return (Path(folder) / "summary.json").is_file()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _plain(x: Any) -> Any:
    """numpy scalars/arrays and Paths → JSON-safe Python values; NaN/inf → None."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(path: Path, obj: Any) -> None:
    """Atomic, indented JSON; NaN becomes ``null``."""
    atomic_write_text(path, json.dumps(_plain(obj), indent=2, sort_keys=False) + "\n")


def write_yaml(path: Path, obj: Any) -> None:
    """Atomic YAML of plain values (``yaml.safe_dump``, never Python objects)."""
    atomic_write_text(path, yaml.safe_dump(_plain(obj), sort_keys=False))


def git_revision() -> str | None:
    """The repository's HEAD commit (with ``-dirty``), or ``None`` outside a checkout."""
    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=5)
        return rev.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def versions() -> dict[str, str]:
    """Versions of Python, mslam and the numerical libraries, for manifests."""
    out = {"python": sys.version.split()[0], "mslam": __version__, "platform": platform.platform()}
    for mod in ("numpy", "torch", "cv2", "open3d", "pandas"):
        try:
            out[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - a missing optional library is simply not listed
            continue
    return out


def manifest(command: list[str] | None, seed: int, timings: dict[str, float], extra: dict | None = None) -> dict:
    """The ``manifest.json`` content: command, versions, git revision, seed, timings, host."""
    return {
        "command": command if command is not None else sys.argv,
        "seed": seed,
        "versions": versions(),
        "git_revision": git_revision(),
        "cpu_count": os.cpu_count(),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "timings_s": timings,
        **(extra or {}),
    }


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
        return _plain(nested)


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


def read_summary(folder: Path) -> dict[str, Any]:
    """Load ``summary.json`` of a result folder."""
    from mutualslam_cli.errors import DatasetError

    path = Path(folder) / "summary.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: no summary.json (run incomplete or not a result folder)") from None
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None

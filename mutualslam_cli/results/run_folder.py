"""A run's folder (DESIGN §8): where it lives, its JSON/YAML files, manifest and trajectories.

A run writes ``<out>/<sequence>/<scheme>/seed<k>/``. Every file is written to a temporary
name in the same folder and renamed, so a killed run never leaves a half-written file.
A run is complete when ``summary.json`` (:mod:`~mutualslam_cli.results.summary`) exists; it is
written last.
"""

from __future__ import annotations

import io
import json
import platform
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from mutualslam_cli import __version__
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.machine import cpu_info
from mutualslam_cli.results.fingerprint import code_fingerprint
from mutualslam_cli.results.summary import plain
from mutualslam_cli.types import Document, Trajectory


def run_dir(out: str | Path, sequence: str, scheme: str, seed: int) -> Path:
    """``<out>/<sequence>/<scheme>/seed<k>``; ``+`` in scheme names is kept (valid in paths)."""
    return Path(out) / sequence / scheme / f"seed{seed}"


def is_complete(folder: Path) -> bool:
    """A run is complete when its ``summary.json`` exists."""
    return (Path(folder) / "summary.json").is_file()


def write_json(path: Path, obj: object) -> None:
    """Atomic, indented JSON; NaN becomes ``null``."""
    atomic_write_text(path, json.dumps(plain(obj), indent=2, sort_keys=False) + "\n")


def write_yaml(path: Path, obj: object) -> None:
    """Atomic YAML of plain values (``yaml.safe_dump``, never Python objects)."""
    atomic_write_text(path, yaml.safe_dump(plain(obj), sort_keys=False))


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
        except Exception:  # a missing optional library is simply not listed
            continue
    return out


def manifest(command: list[str] | None, seed: int, timings: Mapping[str, float],
             extra: Mapping[str, object] | None = None) -> Document:
    """The ``manifest.json`` content: command, versions, git revision, seed, timings, the CPU."""
    return {
        "command": command if command is not None else sys.argv,
        "seed": seed,
        "versions": versions(),
        "git_revision": git_revision(),
        "code_fingerprint": code_fingerprint(),  # the results book's test of a stale record (:mod:`.fingerprint`)
        **cpu_info(),  # model, SIMD flags, kind (DESIGN §10), cores: results and timings depend on them
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "timings_s": timings,
        **(extra or {}),
    }


def fuse_record(command: list[str] | None, time_s: float, device: Mapping[str, object]) -> Document:
    """The ``fuse`` entry of a run's ``manifest.json`` (``mslam fuse`` on the finished run): its command, seconds,
    versions, device (:func:`~mutualslam_cli.device.describe_device`), git revision and time."""
    return {"command": command, "time_s": time_s, "versions": versions(), "device": device,
            "git_revision": git_revision(), "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def read_manifest(folder: Path) -> dict[str, Any]:
    """Load ``manifest.json`` of a result folder (:func:`manifest`'s content)."""
    path = Path(folder) / "manifest.json"
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        raise DatasetError(f"{path}: missing or not valid JSON (not a finished run folder?)") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object (the manifest of mslam run)")
    return data


def write_trajectories(folder: Path, traj_kf: Trajectory, traj_all: Trajectory, suffix: str = "") -> None:
    """``traj_kf<suffix>.txt`` and ``traj_all<suffix>.txt`` in TUM format (atomic)."""
    for name, traj in ((f"traj_kf{suffix}.txt", traj_kf), (f"traj_all{suffix}.txt", traj_all)):
        buf = io.StringIO()
        write_tum_trajectory(buf, traj)
        atomic_write_text(folder / name, buf.getvalue())

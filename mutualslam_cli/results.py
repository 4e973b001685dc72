"""Result folders (DESIGN §8): atomic files, manifest, and the ``summary.json`` schema.

A run writes ``<out>/<sequence>/<scheme>/seed<k>/``. Every file is written to a temporary
name in the same folder and renamed, so a killed run never leaves a half-written file.
A run is complete when ``summary.json`` exists; it is written last.

``summary.json`` holds the keys of :data:`SUMMARY_KEYS`. A value that cannot be computed is
``null`` and its reason is under ``notes`` (same dotted key), never 0.
"""

from __future__ import annotations

import io
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pandas as pd
import yaml

from mutualslam_cli import __version__
from mutualslam_cli.atomic import atomic_write_bytes, atomic_write_text  # noqa: F401 - re-exported for callers
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.map_ply import read_ply, write_ply  # noqa: F401 - the map files of a run
from mutualslam_cli.types import Trajectory

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


# ----------------------------------------------------------------------------- files of a run


def write_trajectories(folder: Path, traj_kf: Trajectory, traj_all: Trajectory, suffix: str = "") -> None:
    """``traj_kf<suffix>.txt`` and ``traj_all<suffix>.txt`` in TUM format (atomic)."""
    for name, traj in ((f"traj_kf{suffix}.txt", traj_kf), (f"traj_all{suffix}.txt", traj_all)):
        buf = io.StringIO()
        write_tum_trajectory(buf, traj)
        atomic_write_text(folder / name, buf.getvalue())


# ----------------------------------------------------------------------------- summary assembly


def summarise_frontend(summary: Summary, *, keyframes: int, tracked_fraction: float, map_points: int,
                       vo_mode: str, frames: int, vo_time_s: float, traj: dict[str, Any],
                       map_esi: float) -> None:
    """``vo.*``, ``timing.vo_fps``, ``map.points.vo``, ``trajectory.ate_rmse_m.{vo,all_frames}``, ``map.esi.vo``.

    Args:
        traj: :func:`mutualslam_cli.evaluation.evaluate_trajectory`'s result (``kf``, ``all``, ``notes``).
        vo_time_s: the front end's own run time (seconds).
    """
    summary.set("vo.keyframes", keyframes)
    summary.set("vo.tracked_fraction", tracked_fraction)
    if vo_mode != "svo":
        summary.absent("timing.vo_fps", f"oracle front end (--vo {vo_mode}): no tracking to time")
    else:
        summary.set("timing.vo_fps", frames / vo_time_s if vo_time_s > 0 else None)
    summary.set("map.points.vo", map_points)
    _set_ate(summary, traj, {"kf": "trajectory.ate_rmse_m.vo", "all": "trajectory.ate_rmse_m.all_frames"})
    if vo_mode != "svo":
        summary.notes["trajectory.ate_rmse_m.vo"] = "oracle front end: keyframe poses are GT poses"
    summary.set("map.esi.vo", map_esi, "no map point has GT depth at its host pixel")


def _set_ate(summary: Summary, traj: dict[str, Any], names: dict[str, str]) -> None:
    """RMSE of :func:`~mutualslam_cli.evaluation.evaluate_trajectory`'s ``kf``/``all`` under ``names``."""
    for key, name in names.items():
        r = traj[key]
        if r is None:
            summary.absent(name, traj["notes"].get(key, traj["notes"].get("trajectory", "not computed")))
        else:
            summary.set(name, float(r.rmse))
            if getattr(r, "note", None):  # re-initialised VO: each segment aligned on its own
                summary.notes[name] = r.note


#: ``summary.json`` keys of culling and global BA (DESIGN §8).
BA_KEYS = ("trajectory.ate_rmse_m.ba", "map.points.culled", "map.points.ba", "map.esi.culled", "map.esi.ba",
           "timing.ba_s")


def summarise_ba_absent(summary: Summary, reason: str, requested: int) -> None:
    """Every BA key ``null`` with ``reason``; ``ba.requested``: Algorithm 1's requests."""
    for key in BA_KEYS:
        summary.absent(key, reason)
    summary.set("ba.triggers", 0)
    summary.set("ba.requested", requested)


def summarise_ba(summary: Summary, *, traj: dict[str, Any], points_culled: int | None, esi_culled: float,
                 points_ba: int, esi_ba: float, ba_s: float, runs: list[dict[str, Any]], requested: int,
                 no_culling: str | None = None) -> None:
    """Culling and global BA (paper Tables 4–5): ``trajectory.ate_rmse_m.{ba,all_frames_ba}``,
    ``map.{points,esi}.{culled,ba}``, ``timing.ba_s`` and ``ba.*``.

    Args:
        traj: :func:`~mutualslam_cli.evaluation.evaluate_trajectory` of the map after the final BA.
        points_culled, esi_culled: the front end's map without every point culled (its own depths).
        points_ba, esi_ba: the map after the final BA.
        ba_s: seconds of every culling + BA (Algorithm 1's triggers and the final one).
        runs: ``stats`` of each :func:`~mutualslam_cli.ba.global_ba.run_global_ba`, the final last.
        requested: times Algorithm 1 requested global BA.
        no_culling: why there was no culling (``map.*.culled`` are then null with it).
    """
    _set_ate(summary, traj, {"kf": "trajectory.ate_rmse_m.ba", "all": "trajectory.ate_rmse_m.all_frames_ba"})
    if no_culling:
        summary.absent("map.points.culled", no_culling)
        summary.absent("map.esi.culled", no_culling)
    else:
        summary.set("map.points.culled", points_culled)
        summary.set("map.esi.culled", esi_culled, "no kept map point has GT depth at its host pixel")
    summary.set("map.points.ba", points_ba)
    summary.set("map.esi.ba", esi_ba, "no map point has GT depth at its host pixel after BA")
    summary.set("timing.ba_s", ba_s)
    summary.set("ba.triggers", len(runs) - 1)
    summary.set("ba.requested", requested)
    final = runs[-1]
    for key in ("n_judged_elsewhere", "n_refined", "n_unrefined", "n_diverged", "n_targets", "iterations", "cost0",
                "cost"):
        summary.set(f"ba.final.{key}", final[key])


def summarise_outliers(summary: Summary, ids: np.ndarray, injected: np.ndarray, culled: np.ndarray | None) -> None:
    """``map.outliers.{injected,culled}`` and ``map.inliers.kept`` of a run with ``vo.inject_outliers``.

    Args:
        ids: ``(P,)`` ids of every map point; injected: ids of the corrupted ones.
        culled: ``(P,)`` bool, culled points (``None``: this run did not cull).
    """
    bad = np.isin(ids, injected)
    summary.set("map.outliers.injected", int(bad.sum()))
    if culled is None:
        why = "no culling in this run (ba.enabled=false, ba.culling=false or scheme 'none')"
        summary.absent("map.outliers.culled", why)
        summary.absent("map.inliers.kept", why)
        return
    summary.set("map.outliers.culled", float(culled[bad].mean()) if bad.any() else None, "no outlier injected")
    summary.set("map.inliers.kept", float((~culled[~bad]).mean()) if (~bad).any() else None,
                "every point is an outlier")


def summarise_stages(summary: Summary, timings: dict[str, float], ba_trigger_s: float, vo_cached: bool) -> None:
    """``timing.total_s`` and the run's wall time split by stage, ``timing.stage_s.*`` (seconds).

    ``frontend`` (VO or oracle; a cached front end costs only its loading), ``adaptation`` (online
    fine-tuning without the BA it triggered), ``ba`` (every culling + global BA: Algorithm 1's
    requests and the final one), ``evaluation`` (depth of every frame with GT by both models),
    ``other`` (the rest: loading the sequence and the network, trajectory and map metrics, writing
    files). The five add up to ``total_s``.
    """
    ba = ba_trigger_s + timings.get("ba_final_s", 0.0)
    parts = {"frontend": timings.get("vo_s", 0.0), "adaptation": timings.get("adapt_s", 0.0) - ba_trigger_s,
             "ba": ba, "evaluation": timings.get("eval_s", 0.0)}
    parts["other"] = timings["total_s"] - sum(parts.values())
    summary.set("timing.total_s", timings["total_s"])
    for k, v in parts.items():
        summary.set(f"timing.stage_s.{k}", float(v))
    if vo_cached:
        summary.notes["timing.stage_s.frontend"] = "front end loaded from the cache"


def summarise_adaptation(summary: Summary, scheme: str, step_ms: list[float], keyframe_ms: list[float],
                         kf_rows: list[dict[str, Any]] | None = None) -> None:
    """``timing.finetune_ms`` (median per optimiser step) and ``timing.finetune_kf_ms`` (per keyframe);
    with the keyframe rows, ``adaptation.keyframes_trained`` and, for scheme ``luo``,
    ``adaptation.luo_keyframes_with_partner`` (training keyframes that found a simulated stereo partner)."""
    why = "scheme 'none': no fine-tuning" if scheme == "none" else "no keyframe was trained on"
    summary.set("timing.finetune_ms", float(np.median(step_ms)) if step_ms else None, why)
    summary.set("timing.finetune_kf_ms", float(np.median(keyframe_ms)) if keyframe_ms else None, why)
    if kf_rows is None:
        return
    summary.set("adaptation.keyframes_trained", sum(bool(r.get("trained")) for r in kf_rows))
    if scheme == "luo":
        training = [r for r in kf_rows if not r.get("is_validation")]
        summary.set("adaptation.luo_keyframes_with_partner", sum(bool(str(r.get("sources") or "").strip())
                                                                 for r in training))
        summary.set("adaptation.training_keyframes", len(training))


def depth_means(table: pd.DataFrame, model: str, suffix: str = "") -> dict[str, float | None]:
    """Means over the rows of ``table`` of one model's per-frame depth metrics.

    Args:
        table: per-frame rows of :func:`mutualslam_cli.evaluation.evaluate_depth` (or a selection).
        model: column prefix (``pretrained`` or ``adapted``).
        suffix: appended to the metric name (``_nonkf`` → ``pcd_nonkf.lsq``).

    Returns:
        ``{"pcd<suffix>.lsq": %, "pcd<suffix>.median": %, "esi<suffix>": log units}``; ``None``
        where no row has the value (no frame with valid GT depth).
    """
    def mean(col: str) -> float | None:
        return float(np.nanmean(table[col])) if col in table and table[col].notna().any() else None

    return {f"pcd{suffix}.lsq": mean(f"{model}_pcd_lsq"), f"pcd{suffix}.median": mean(f"{model}_pcd_median"),
            f"esi{suffix}": mean(f"{model}_esi")}


def summarise_depth(summary: Summary, table: pd.DataFrame, ms: dict[str, float], scheme: str) -> None:
    """``timing.depth_ms`` and ``depth.{pcd,esi}[_nonkf].*.{pretrained,adapted}`` from the per-frame table.

    All frames (the paper's figure) and the frames the adaptation never saw (not keyframes). For
    scheme ``none`` the adapted values are the pre-trained model's.
    """
    summary.set("timing.depth_ms", ms.get("adapted", ms.get("pretrained")))
    evaluated = {k for k in ("pretrained", "adapted") if f"{k}_pcd_lsq" in table}
    for model in ("pretrained", "adapted"):
        src = model if model in evaluated else "pretrained"
        for group, rows, why in (("", table, "no frame with valid GT depth"),
                                 ("_nonkf", table[~table["is_keyframe"]] if len(table) else table,
                                  "no non-keyframe with valid GT depth")):
            for key, val in depth_means(rows, src, group).items():
                summary.set(f"depth.{key}.{model}", val, why)
    if scheme == "none":
        summary.notes["depth.pcd.lsq.adapted"] = "scheme 'none': the adapted model is the pre-trained model"
    summary.set("depth.frames_evaluated", int(len(table)))

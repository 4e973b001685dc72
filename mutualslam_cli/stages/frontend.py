"""The front-end stage of a run: our VO or an oracle, cached per sequence + front-end config + seed.

Every scheme of a grid reuses one front-end result, so :func:`run_frontend` keeps it in
``<results>/_cache/vo/<sequence>-<mode>-<key>.npz`` (key: :func:`vo_cache_key`).

The entry is data only: an ``np.savez`` archive of the arrays of
:func:`~mutualslam_cli.vo.result.vo_to_arrays`, read back with ``allow_pickle=False``, so a results
folder shared on a cluster cannot run code in whoever reads it. Entries written by earlier
versions (``.pkl``, pickled) are ignored, never unpickled. An entry that cannot be read (truncated,
garbage, another layout version) is logged as a warning naming the file, recomputed and overwritten.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Progress
from mutualslam_cli.stages.evaluation import set_ate
from mutualslam_cli.vo.result import VOResult, vo_from_arrays, vo_to_arrays
from mutualslam_cli.vo.depth_oracle import run_oracle
from mutualslam_cli.vo.frontend import FRONTEND_VERSION, run_vo
from mutualslam_cli.vo.pose_oracle import run_pose_oracle

log = logging.getLogger(__name__)

#: Version of the oracle front ends in their cache key (2: ``gt`` = pose oracle, ``gt-depth`` = depth oracle).
ORACLE_VERSION = 2


def vo_cache_key(seq: Sequence, cfg: RunConfig) -> str:
    """Cache key of a front-end result: sequence identity + front-end and data config + seed."""
    ident = {
        "root": str(Path(seq.root).resolve()), "n": len(seq),
        "first": seq.frames[0].timestamp if len(seq) else None,
        "last": seq.frames[-1].timestamp if len(seq) else None,
        "vo": {k: v for k, v in to_dict(cfg.vo).items() if k != "inject_outliers"},
        "data": {"max_frames": cfg.data.max_frames, "stride": cfg.data.stride},
        "seed": cfg.seed, "intr": seq.intrinsics.as_list(), "version": FRONTEND_VERSION,
    }
    if cfg.vo.mode != "svo":  # "gt" was the depth oracle before version 2 of the oracles
        ident["oracle_version"] = ORACLE_VERSION
    return hashlib.sha1(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()[:16]


def cache_path(cache_dir: Path, seq: Sequence, cfg: RunConfig) -> Path:
    """Where :func:`run_frontend` keeps the front-end result of ``seq`` under ``cfg``."""
    return Path(cache_dir) / f"{seq.name}-{cfg.vo.mode}-{vo_cache_key(seq, cfg)}.npz"


def load_cached(path: Path) -> VOResult | None:
    """The front-end result stored in ``path``; ``None`` when there is none or it is invalid.

    Read with ``allow_pickle=False``. An invalid entry (not an ``.npz``, truncated, another layout
    version, inconsistent arrays) is logged as a warning naming the file, and ``None`` returned.
    """
    if not path.is_file():
        return None
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError("not an .npz archive")
        with z:
            vo = vo_from_arrays(z)
    except Exception as e:  # noqa: BLE001 - whatever is wrong with the file, the entry is recomputed
        log.warning("VO cache %s is unreadable (%s: %s); recomputing it", path, type(e).__name__, e)
        return None
    log.info("front end loaded from cache %s", path)
    return vo


def save_cached(path: Path, vo: VOResult) -> None:
    """Write ``vo`` to ``path`` atomically as an ``.npz`` of :func:`~mutualslam_cli.vo.result.vo_to_arrays`."""
    arrays = vo_to_arrays(vo)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to a name
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())


def run_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                 progress: Progress | None = None) -> tuple[VOResult, bool]:
    """Run (or load from cache) the front end selected by ``cfg.vo.mode``.

    Returns:
        ``(vo_result, from_cache)``.
    """
    path = None
    if cache_dir is not None:
        path = cache_path(cache_dir, seq, cfg)
        cached = load_cached(path)
        if cached is not None:
            return cached, True
    cb = (lambda info: progress("vo", info)) if progress else None
    if cfg.vo.mode == "gt":  # pose oracle: our VO's tracks (cached like any svo run) re-triangulated with GT poses
        svo, _ = run_frontend(seq, replace(cfg, vo=replace(cfg.vo, mode="svo")), cache_dir, progress)
        vo = run_pose_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb, vo=svo)
    elif cfg.vo.mode == "gt-depth":
        vo = run_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb)
    else:
        vo = run_vo(seq, cfg.vo, seed=cfg.seed, progress=cb)
    if path is not None:
        save_cached(path, vo)
    return vo, False


# ----------------------------------------------------------------------------- summary keys


def summarise_frontend(summary: Summary, *, keyframes: int, tracked_fraction: float, map_points: int,
                       vo_mode: str, frames: int, vo_time_s: float, traj: dict[str, Any],
                       map_esi: float) -> None:
    """``vo.*``, ``timing.vo_fps``, ``map.points.vo``, ``trajectory.ate_rmse_m.{vo,all_frames}``, ``map.esi.vo``.

    Args:
        traj: :func:`mutualslam_cli.stages.evaluation.evaluate_trajectory`'s result (``kf``, ``all``, ``notes``).
        vo_time_s: the front end's own run time (seconds).
    """
    summary.set("vo.keyframes", keyframes)
    summary.set("vo.tracked_fraction", tracked_fraction)
    if vo_mode != "svo":
        summary.absent("timing.vo_fps", f"oracle front end (--vo {vo_mode}): no tracking to time")
    else:
        summary.set("timing.vo_fps", frames / vo_time_s if vo_time_s > 0 else None)
    summary.set("map.points.vo", map_points)
    set_ate(summary, traj, {"kf": "trajectory.ate_rmse_m.vo", "all": "trajectory.ate_rmse_m.all_frames"})
    if vo_mode != "svo":
        summary.notes["trajectory.ate_rmse_m.vo"] = "oracle front end: keyframe poses are GT poses"
    summary.set("map.esi.vo", map_esi, "no map point has GT depth at its host pixel")

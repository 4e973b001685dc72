"""The front-end stage of a run (:func:`run_stage`): our VO or an oracle, cached per sequence +
front-end config + seed.

Every scheme of a grid reuses one front-end result, so :func:`run_frontend` keeps it in
``<results>/_cache/vo/<sequence>-<mode>-<key>.npz`` (key: :func:`vo_cache_key`).

The entry is data only: an ``np.savez`` archive of the arrays of
:func:`~mutualslam_cli.vo.result.vo_to_arrays`, read back with ``allow_pickle=False``, so a results
folder shared on a cluster cannot run code in whoever reads it; any other file there (a pickle) is
never read. An entry that cannot be read (truncated,
garbage, another layout version) is logged as a warning naming the file, recomputed and overwritten.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.ba.culling import inject_outliers
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.slam_metrics import esi_of_log_errors, evaluate_trajectory, map_log_depth_errors, set_ate
from mutualslam_cli.types import Progress
from mutualslam_cli.vo.depth_oracle import run_oracle
from mutualslam_cli.vo.frontend import FRONTEND_VERSION, run_vo
from mutualslam_cli.vo.pose_oracle import run_pose_oracle
from mutualslam_cli.vo.result import VOResult, vo_from_arrays, vo_to_arrays

log = logging.getLogger(__name__)

#: Version of the oracle front ends in their cache key (2: ``gt`` = pose oracle, ``gt-depth`` = depth oracle).
ORACLE_VERSION = 2


def vo_cache_key(seq: Sequence, cfg: RunConfig) -> str:
    """Cache key of a front-end result: sequence identity + front-end and data config + seed."""
    ident = {
        "root": str(Path(seq.root).resolve()), "n": len(seq),
        "first": seq.frames[0].timestamp if len(seq) else None,
        "last": seq.frames[-1].timestamp if len(seq) else None,
        "vo": {k: v for k, v in to_dict(cfg.vo).items() if k not in ("inject_outliers", "bridge_segments")},
        "data": {"max_frames": cfg.data.max_frames, "stride": cfg.data.stride},
        "seed": cfg.seed, "intr": seq.intrinsics.as_list(), "version": FRONTEND_VERSION,
    }
    if cfg.vo.mode != "svo":  # an oracle's result also depends on the oracles' version
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


def load_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                  progress: Progress | None = None) -> tuple[VOResult, bool, np.ndarray]:
    """The front end's result as a run uses it: :func:`run_frontend`, then the ``vo.inject_outliers``
    test knob (applied to the cached result, not part of its key).

    Returns:
        ``(vo, from_cache, injected)``: ``injected`` holds the ids of the corrupted map points.
    """
    vo, cached = run_frontend(seq, cfg, cache_dir, progress)
    vo, injected = inject_outliers(vo, cfg.vo.inject_outliers, cfg.seed)
    return vo, cached, injected


@dataclass
class FrontEnd:
    """What the front-end stage hands on.

    Attributes:
        vo: keyframes, map and trajectories (with the injected outliers, if any).
        cached: loaded from the VO cache.
        injected: ids of map points corrupted by ``vo.inject_outliers``.
        map_errors: ``(P,)`` log-depth error of each map point in its host keyframe against GT
            (:func:`~mutualslam_cli.stages.evaluation.map_log_depth_errors`; NaN without GT).
        points_with_gt: map points with GT depth at their host pixel.
    """

    vo: VOResult
    cached: bool
    injected: np.ndarray
    map_errors: np.ndarray
    points_with_gt: int


def run_stage(run: RunContext) -> FrontEnd:
    """The front end of a run (cached per sequence, front-end config and seed): ``traj_kf.txt``,
    ``traj_all.txt``, ``map_vo.ply`` and the keys ``vo.*``, ``timing.vo_fps``, ``map.points.vo``,
    ``map.esi.vo`` and ``trajectory.ate_rmse_m.{vo,all_frames}``."""
    seq, cfg, summary = run.seq, run.cfg, run.summary
    with run.timed("frontend"):
        vo, cached, injected = load_frontend(seq, cfg, run.cache / "vo", run.progress)
    write_trajectories(run.folder, vo.traj_kf, vo.traj_all)
    err = map_log_depth_errors(seq, vo)  # per point log z − log z*: the map's colours and its e_si
    write_ply(run.folder / "map_vo.ply", vo.points_world(), err)
    esi, n_gt = esi_of_log_errors(err)
    mode = cfg.vo.mode
    summary.set("vo.keyframes", len(vo.keyframes))
    summary.set("vo.tracked_fraction", vo.tracked_fraction)
    if mode != "svo":
        summary.absent("timing.vo_fps", f"oracle front end (--vo {mode}): no tracking to time")
    else:
        vo_time_s = float(vo.meta.get("time_s", run.timings["frontend"]))
        summary.set("timing.vo_fps", len(seq) / vo_time_s if vo_time_s > 0 else None)
    summary.set("map.points.vo", len(vo.points))
    set_ate(summary, evaluate_trajectory(seq, vo, cfg.eval.ate_max_dt),
            {"kf": "vo", "all": "all_frames"})
    if mode != "svo":
        summary.notes["trajectory.ate_rmse_m.vo"] = "oracle front end: keyframe poses are GT poses"
    summary.set("map.esi.vo", esi, "no map point has GT depth at its host pixel")
    summary.set("vo.segments", len({k.segment for k in vo.keyframes}))
    if mode == "svo":
        summary.set("vo.relocalisations", len(vo.meta.get("relocalisations", [])))
        summary.set("vo.relocalisations_rejected", int(vo.meta.get("reloc_rejected", 0)))
    else:
        for key in ("vo.relocalisations", "vo.relocalisations_rejected"):
            summary.absent(key, f"oracle front end (--vo {mode}): GT poses, nothing to relocalise")
    summary.set("vo.from_cache", cached)
    summary.set("vo.mode", mode)
    return FrontEnd(vo, cached, injected, err, n_gt)

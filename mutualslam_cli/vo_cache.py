"""The front-end stage of a run: our VO or an oracle, cached per sequence + front-end config + seed.

Every scheme of a grid reuses one front-end result, so :func:`run_frontend` keeps it in
``<results>/_cache/vo/`` under :func:`vo_cache_key`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import pickle
from dataclasses import replace
from pathlib import Path

from mutualslam_cli import results as res
from mutualslam_cli.adapt.stage import Progress
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.vo.frontend import FRONTEND_VERSION, run_vo
from mutualslam_cli.vo.oracle import run_oracle
from mutualslam_cli.vo.output import VOResult
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


def run_frontend(seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                 progress: Progress | None = None) -> tuple[VOResult, bool]:
    """Run (or load from cache) the front end selected by ``cfg.vo.mode``.

    Returns:
        ``(vo_result, from_cache)``.
    """
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{seq.name}-{cfg.vo.mode}-{vo_cache_key(seq, cfg)}.pkl"
        if path.is_file():
            try:
                with open(path, "rb") as f:
                    vo = pickle.load(f)
                log.info("front end loaded from cache %s", path)
                return vo, True
            except Exception as e:  # noqa: BLE001 - a corrupt cache entry is recomputed
                log.warning("ignoring unreadable VO cache %s (%s)", path, e)
    cb = (lambda info: progress("vo", info)) if progress else None
    if cfg.vo.mode == "gt":  # pose oracle: our VO's tracks (cached like any svo run) re-triangulated with GT poses
        svo, _ = run_frontend(seq, replace(cfg, vo=replace(cfg.vo, mode="svo")), cache_dir, progress)
        vo = run_pose_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb, vo=svo)
    elif cfg.vo.mode == "gt-depth":
        vo = run_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb)
    else:
        vo = run_vo(seq, cfg.vo, seed=cfg.seed, progress=cb)
    if path is not None:
        res.atomic_write_bytes(path, pickle.dumps(vo, protocol=pickle.HIGHEST_PROTOCOL))
    return vo, False



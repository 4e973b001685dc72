"""The adaptation stage of scheme ``comoda``: every frame through :class:`~mutualslam_cli.adapt.comoda.ComodaAdapter`.

Unlike the keyframe schemes (:mod:`mutualslam_cli.stages.adaptation`), CoMoDa needs no SLAM: it is driven by
every frame of the sequence (undistorted, at network resolution), trains its own pose network, and
its chained poses form a trajectory of its own. The VO front end still runs (the pipeline's map, BA
and the VO's ATE are unchanged), so Table 4 can show the PoseNet trajectory beside the VO's.

Outputs, in the run folder: ``frames.csv`` (one row per frame: trained, static, batch, loss parts,
step ms) and ``traj_posenet.txt`` (TUM format); in ``summary.json``: ``timing.finetune_ms`` (median
per Adam step), ``timing.finetune_kf_ms`` (median per *frame* update),
``trajectory.ate_rmse_m.posenet`` (Sim(3)-aligned ATE of the chained poses against GT, null with a
reason when not computable) and ``adaptation.pose_network`` (the resolved folder of the pose files the
pose network started from, or ``"random (encoder from the depth encoder, decoder random)"``;
:func:`~mutualslam_cli.adapt.comoda_pose.make_pose_net`).
"""

from __future__ import annotations

import io
import logging
import time

import numpy as np
import pandas as pd

from mutualslam_cli.adapt.comoda import ComodaAdapter, FrameStep
from mutualslam_cli.adapt.comoda_pose import make_pose_net
from mutualslam_cli.adapt.comoda_source import source_triplets
from mutualslam_cli.adapt.depthnet import DepthNet, prepare
from mutualslam_cli.adapt.inputs import to_net_image
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import MslamError
from mutualslam_cli.metrics import trajectory as tm
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.types import Scalar, Trajectory
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)

#: summary.json key of the PoseNet trajectory's ATE (metres after Sim(3) alignment).
POSENET_ATE_KEY = "trajectory.ate_rmse_m.posenet"
#: summary.json key naming the pose network the run started from (a folder, or random).
POSE_NETWORK_KEY = "adaptation.pose_network"


def frame_row(info: FrameStep) -> dict[str, Scalar]:
    """A flat CSV row of one frame's step (loss parts as ``loss_<part>``)."""
    row: dict[str, Scalar] = {"frame": info.frame, "target": info.target, "trained": info.trained,
                           "static": info.static, "batch": " ".join(map(str, info.batch)), "step_ms": info.step_ms}
    row.update({f"loss_{k}": v for k, v in info.loss.items()})
    return row


def posenet_ate(seq: Sequence, traj: Trajectory, max_dt: float) -> tuple[float | None, str]:
    """Sim(3)-aligned ATE RMSE of ``traj`` against the sequence's GT, or ``(None, reason)``."""
    if seq.gt is None or len(seq.gt) == 0:
        return None, "sequence has no GT poses"
    if len(traj) < 3:
        return None, f"only {len(traj)} PoseNet poses"
    try:
        return float(tm.ate(seq.gt, traj, align="sim3", max_dt=max_dt).rmse), ""
    except MslamError as e:
        return None, str(e)


def run_stage(run: RunContext, net: DepthNet, fast: bool) -> DepthNet:
    """Adapt ``net`` on every frame of the sequence with the CoMoDa-style adapter; write its outputs.

    Args:
        run: the run (``cfg.adapt.comoda_*`` settings, ``cfg.net`` resolution and ``weights`` (its pose
            files, if any, start the pose network), ``cfg.seed``; the source-domain replay bank is
            kept in ``<cache>/comoda`` for the next runs).
        net: the depth network to adapt (a copy of the pre-trained one; changed in place).
        fast: bf16 autocast for the forward passes.

    Returns:
        The adapted depth network.
    """
    seq, cfg, folder, summary = run.seq, run.cfg, run.folder, run.summary
    cache_dir = run.cache / "comoda"
    w, h = cfg.net.width, cfg.net.height
    net = prepare(net, fast, device=run.device)
    bank = (source_triplets(cfg.adapt.comoda_replay_capacity, w, h, cache_dir=cache_dir)
            if cfg.adapt.comoda_replay_from == "source" and cfg.adapt.comoda_replay_per_step > 0 else None)
    pose_net, pose_source = make_pose_net(net, cfg.adapt, weights_dir=cfg.net.weights)
    log.info("comoda: pose network: %s", pose_source)
    summary.set(POSE_NETWORK_KEY, pose_source)
    adapter = ComodaAdapter(net, pose_net, cfg.adapt,
                            seq.intrinsics.scaled(w, h).K(), seed=cfg.seed, fast=fast, replay_bank=bank,
                            device=run.device)
    und = Undistorter(seq.intrinsics)
    rows: list[dict[str, Scalar]] = []
    per_frame: list[float] = []  # ms of each trained frame's update
    t0 = time.perf_counter()
    for i in range(len(seq)):
        info = adapter.add_frame(to_net_image(und.image(seq.load_rgb(i)), w, h))
        rows.append(frame_row(info))
        if info.trained:
            per_frame.append(info.step_ms)
        run.report("adapt", {"done": i + 1, "total": len(seq), **rows[-1], "elapsed_s": time.perf_counter() - t0})
    atomic_write_text(folder / "frames.csv", pd.DataFrame(rows).to_csv(index=False))
    traj = Trajectory(np.array([f.timestamp for f in seq.frames]), adapter.trajectory())
    buf = io.StringIO()
    write_tum_trajectory(buf, traj)
    atomic_write_text(folder / "traj_posenet.txt", buf.getvalue())
    why = "no frame was trained on (fewer than 3 frames, or all static)"
    summary.set("timing.finetune_ms", float(np.median(adapter.step_ms)) / cfg.adapt.comoda_steps_per_frame
                if adapter.step_ms else None, why)
    summary.set("timing.finetune_kf_ms", float(np.median(per_frame)) if per_frame else None, why)
    summary.set("adaptation.steps", len(per_frame) * cfg.adapt.comoda_steps_per_frame)
    for key in ("timing.finetune_batch_ms", "timing.finetune_consolidate_ms"):
        summary.absent(key, "scheme 'comoda' updates per frame, without keyframe batches or a regulariser")
    value, reason = posenet_ate(seq, traj, cfg.eval.ate_max_dt)
    summary.set(POSENET_ATE_KEY, value, reason)
    return net  # adapter.net is this network, trained in place

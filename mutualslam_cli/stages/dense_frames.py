"""Which frames the dense stage fuses and with which metric poses (:mod:`mutualslam_cli.stages.dense`).

The run's trajectory files (after BA when present) give the poses; each tracking segment is brought
into the GT frame by the Sim(3) aligning that trajectory to GT; the front end's own Sim(3) scales
convert the network's map-unit depth to metres.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.associate import read_tum_trajectory
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.dense import tsdf
from mutualslam_cli.errors import DatasetError, GeometryError
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.types import Trajectory


@dataclass
class FusedFrame:
    """One frame to fuse: sequence index, keyframe id (or None), segment and pose ``(4, 4)`` in the GT frame (m)."""

    frame: int
    kf_id: int | None
    segment: int
    T_metric: np.ndarray


def _trajectory(folder: Path, name: str) -> tuple[Trajectory | None, str]:
    """``traj_<name>_ba.txt`` when the run has it, else ``traj_<name>.txt``; and which one it was."""
    for suffix, what in (("_ba", "after global BA"), ("", "front end, no BA")):
        path = folder / f"traj_{name}{suffix}.txt"
        if path.is_file():
            return read_tum_trajectory(path), what
    return None, "missing"


def _segments_of(seq: Sequence, vo: VOResult, traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Sequence index (−1: none) and tracking segment (−1: untracked) of each pose of an all-frames trajectory."""
    by_time = {f.timestamp: i for i, f in enumerate(seq.frames)}
    idx = np.array([by_time.get(float(t), -1) for t in traj.timestamps], np.int64)
    ok = (idx >= 0) & (idx < len(vo.frame_segment))
    seg = np.full(len(idx), -1, np.int64)
    seg[ok] = vo.frame_segment[idx[ok]]
    return idx, seg


def _gt(seq: Sequence) -> Trajectory:
    """The sequence's GT poses; GeometryError without (the dense stage checks first)."""
    if seq.gt is None:
        raise GeometryError("sequence has no GT poses: no Sim(3) to bring the run into metres")
    return seq.gt


def select_frames(seq: Sequence, vo: VOResult, folder: Path, every: int,
                  max_dt: float) -> tuple[list[FusedFrame], dict[int, float], str]:
    """The frames to fuse with their metric poses, the Sim(3) scale of each aligned segment, and a note
    naming the trajectory used. The Sim(3) aligns the trajectory that is fused: the keyframes'
    (``every`` 0), or every tracked frame's (``every`` > 0; a short window with < 3 keyframes can be fused so).

    Raises:
        DatasetError: the trajectory files do not match the front end.
        GeometryError: no segment has 3 poses associated with GT (no Sim(3)).
    """
    name = "kf" if every == 0 else "all"
    traj, what = _trajectory(folder, name)
    if every == 0:
        if traj is None or len(traj) != len(vo.keyframes):
            raise DatasetError(f"{folder}: traj_kf*.txt has {0 if traj is None else len(traj)} poses for "
                               f"{len(vo.keyframes)} keyframes (is this the run's front end?)")
        idx = np.array([k.frame_index for k in vo.keyframes], np.int64)
        seg = np.array([k.segment for k in vo.keyframes], np.int64)
        keep = np.ones(len(idx), bool)
    else:
        if traj is None:
            raise DatasetError(f"{folder}: no traj_all.txt (the poses of every tracked frame)")
        idx, seg = _segments_of(seq, vo, traj)
        keep = (seg >= 0) & (idx % every == 0)
    sims = tsdf.sim3_per_segment(_gt(seq), traj, seg, max_dt)
    if not sims:
        raise GeometryError(f"no tracking segment has 3 {'keyframes' if every == 0 else 'frames'} associated with "
                            "GT poses: no Sim(3) to metres")
    kf_of = {k.frame_index: k.id for k in vo.keyframes}
    frames = [FusedFrame(int(i), kf_of.get(int(i)), int(g), tsdf.apply_sim3(T, *sims[int(g)]))
              for i, g, T, k in zip(idx, seg, traj.poses, keep) if k and int(g) in sims]
    note = ("keyframes" if every == 0 else f"every k-th frame (k = {every})") + f", {what}"
    return frames, {k: v[2] for k, v in sims.items()}, note


def front_end_scales(seq: Sequence, vo: VOResult, cfg: RunConfig) -> dict[int, float]:
    """Sim(3) scale of each segment of the front end's trajectory (the map the depth ratios are in): the
    keyframes' or every tracked frame's, as :func:`select_frames` aligns the fused one."""
    if cfg.dense.every == 0:
        traj, seg = vo.traj_kf, np.array([k.segment for k in vo.keyframes], np.int64)
    else:
        traj = vo.traj_all
        seg = _segments_of(seq, vo, traj)[1]
    return {s: v[2] for s, v in tsdf.sim3_per_segment(_gt(seq), traj, seg, cfg.eval.ate_max_dt).items()}

"""A frame's pose when tracking is weak: fast rotation, motion blur and a rolling shutter.

When the camera sweeps or rolls fast, three things happen at once: KLT loses most tracks (blur), the
map points left are few because the depth filter had no time to converge new ones, and the tracks
that survive disagree with one global-shutter pose by several pixels (a rolling shutter reads the
rows of a 640×480 frame over tens of milliseconds, during which a 200°/s rotation turns the view by
several degrees). The front end's pose test at ``vo.ransac_threshold_px`` then calls it a loss
although the pose is well determined. On a frame whose map-point inliers fall below
``WEAK_FACTOR × vo.min_tracked`` (after re-projecting lost points), :func:`rescue_pose`

1. lets the depth-filter seeds whose inverse depth is known to ``1 / SEED_POSE_RATIO`` of their range
   join the pose, at their mean depth (a rotation-led pose hardly depends on depth), and
2. when the support is still short of ``vo.min_tracked``, widens the inlier threshold
   ``WIDE_FACTOR``-fold, as a search that the residual says the prior failed calls for.

A pose so found must be carried by at least ``vo.min_tracked`` tracks within ``KEEP_FACTOR`` of its
threshold (a widened one also by ``MIN_SHARE`` of the tracks it was given); else the frame is lost, and why
(:func:`loss_reason`): too few tracks survived KLT, or the tracks left agree on no pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mutualslam_cli.map.assemble import LOSS_REASONS
from mutualslam_cli.vo.state import Tracks
from mutualslam_cli.vo.tracking import estimate_pose, reprojection_errors

KEEP_FACTOR = 2.0
"""Map-point tracks farther than ``KEEP_FACTOR × threshold`` from their projection are dropped."""

WEAK_FACTOR = 2
"""Below ``WEAK_FACTOR × min_tracked`` PnP inliers a frame is weak: lost map points are re-projected and
matched, and the pose is rescued."""

SEED_POSE_RATIO = 10.0
"""On a weak frame, seeds with σ below ``ρ_range / SEED_POSE_RATIO`` join the pose estimate."""

WIDE_FACTOR = 3.0
"""The rescue's widened inlier threshold, in multiples of ``vo.ransac_threshold_px``."""

RESCUES = ("seeds", "wide")
"""How a weak frame's pose was rescued (``vo.rescued.*``)."""

MIN_SHARE = 0.5
"""A widened pose must put at least this share of the tracks it was given within its bound."""

@dataclass
class Pose:
    """A frame's pose and what carries it.

    Attributes:
        T: ``(4, 4)`` world-to-camera pose (``None``: none found).
        inl: ``(M,)`` inliers among the map-point tracks given.
        near: ``(M,)`` map-point tracks within ``KEEP_FACTOR × thr`` (kept).
        support: tracks within that bound, seeds included.
        how: ``"points"``, ``"seeds"`` (seeds joined) or ``"wide"`` (widened threshold).
    """

    T: np.ndarray | None
    inl: np.ndarray
    near: np.ndarray
    support: int
    how: str = "points"


def judge(T: np.ndarray | None, inl: np.ndarray, Xw: np.ndarray, xn: np.ndarray, thr: float) -> Pose:
    """The :class:`Pose` of ``T`` on ``(M, 3)`` map points seen at ``(M, 2)`` normalised ``xn``."""
    near = np.zeros(len(Xw), bool)
    if T is not None:
        near = reprojection_errors(T, Xw, xn) < KEEP_FACTOR * thr
    return Pose(T, inl, near, int(near.sum()))


def seed_points(tr: Tracks, poses_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(S, 3)`` at the mean depth of the seed tracks whose depth is known to
    ``1 / SEED_POSE_RATIO`` of their range, and their ``(S,)`` rows in ``tr``.

    Args:
        tr: the tracks; poses_wc: ``(K, 4, 4)`` camera-to-world poses of the keyframes (their hosts).
    """
    s = tr.seed
    ok = (tr.pid < 0) & (np.sqrt(s["sigma2"]) < s["z_range"] / SEED_POSE_RATIO)
    ok &= (s["a"] / (s["a"] + s["b"]) > 0.5) & (s["mu"] > 1e-6)
    rows = np.flatnonzero(ok)
    if not len(rows):
        return np.zeros((0, 3)), rows
    T_wh = poses_wc[tr.host[rows]]
    Xh = tr.f_h[rows] / s["mu"][rows, None]
    return np.einsum("nij,nj->ni", T_wh[:, :3, :3], Xh) + T_wh[:, :3, 3], rows


def rescue_pose(best: Pose, Xw: np.ndarray, xn: np.ndarray, Xs: np.ndarray, xs: np.ndarray,
                priors: list[np.ndarray], thr: float, min_tracked: int, seed: int) -> Pose:
    """A weak frame's pose: ``best`` (found on the map points alone) or a better supported one with seeds,
    then with a widened threshold (module docstring).

    Args:
        best: the pose on the ``(M, 3)`` map points ``Xw`` seen at ``(M, 2)`` normalised ``xn``.
        Xs, xs: ``(S, 3)`` seed points (:func:`seed_points`) and their ``(S, 2)`` normalised observations.
        priors: ``T_cw`` starts; thr: the inlier threshold (normalised units); min_tracked: ``vo.min_tracked``.
        seed: the RANSAC seed.
    """
    m = len(Xw)
    Xa, xa = np.r_[Xw, Xs], np.r_[xn, xs]
    for factor, how in zip((1.0, WIDE_FACTOR), RESCUES):
        if best.T is not None and best.support >= min_tracked:
            break
        t = factor * thr
        T, inl = estimate_pose(Xa, xa, priors, t, seed=seed)
        if T is None:
            continue
        near_all = reprojection_errors(T, Xa, xa) < KEEP_FACTOR * t
        if factor > 1.0 and near_all.sum() < MIN_SHARE * len(Xa):
            continue
        if int(near_all.sum()) > best.support:
            best = Pose(T, inl[:m], near_all[:m], int(near_all.sum()), how)
    return best


def loss_reason(n_tracks: int, min_tracked: int) -> str:
    """``"too_few_tracks"`` when KLT kept fewer than ``min_tracked`` usable tracks, else ``"failed_alignment"``."""
    return LOSS_REASONS[0] if n_tracks < min_tracked else LOSS_REASONS[1]

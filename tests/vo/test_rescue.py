"""A weak frame's pose (vo/rescue.py) and the untracked frames by reason (map/assemble.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.map.assemble import LOSS_REASONS, frames_lost
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.rescue import SEED_POSE_RATIO, judge, loss_reason, rescue_pose, seed_points
from mutualslam_cli.vo.state import Tracks
from mutualslam_cli.vo.tracking import _exp_se3, estimate_pose

F = 500.0  # focal length (px): thresholds below are pixels / F
THR = 2.0 / F


def _scene(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points 1–3 m in front of a camera at the origin, and the true pose of a camera turned by 3°."""
    X = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(1, 3, n)]
    T = _exp_se3(np.array([0.02, -0.01, 0.0, 0.0, np.radians(3.0), 0.01]))
    return X, T


def _observe(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    pc = X @ T[:3, :3].T + T[:3, 3]
    return pc[:, :2] / pc[:, 2:3]


def _rolling_shutter(xn: np.ndarray, px_per_row: float) -> np.ndarray:
    """Observations shifted sideways in proportion to their row (a rolling shutter under a fast pan)."""
    out = xn.copy()
    out[:, 0] += px_per_row * (xn[:, 1] * F) / F
    return out


def _rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    c = (np.trace(A[:3, :3] @ B[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def test_wide_threshold_rescues_a_rolling_shutter_frame():
    """A frame whose tracks disagree with one pose by up to ~15 px (a row-proportional shift) has too few
    tracks within the normal bound; the widened search finds the pose close to the truth."""
    rng = np.random.default_rng(0)
    X, T_true = _scene(60, rng)
    xn = _rolling_shutter(_observe(T_true, X), px_per_row=0.06) + rng.normal(0, 0.3 / F, (60, 2))
    T, inl = estimate_pose(X, xn, [np.eye(4)], THR, seed=0)
    best = judge(T, inl, X, xn, THR)
    assert best.support < 30  # the normal bound calls it a loss
    got = rescue_pose(best, X, xn, np.zeros((0, 3)), np.zeros((0, 2)), [np.eye(4)], THR, 30, seed=0)
    assert got.how == "wide"
    assert got.support >= 30
    assert got.T is not None
    assert _rot_err_deg(got.T, T_true) < 3.0  # the shear's bias (±15 px at the top and bottom rows)


def test_seeds_carry_a_frame_with_few_map_points():
    """20 map points are too few; 40 seeds at their (slightly wrong) depths join and carry the pose."""
    rng = np.random.default_rng(1)
    X, T_true = _scene(60, rng)
    xn = _observe(T_true, X) + rng.normal(0, 0.3 / F, (60, 2))
    Xs = X[20:] * rng.uniform(0.98, 1.02, (40, 1))  # seed depth known to ~2 %
    T, inl = estimate_pose(X[:20], xn[:20], [np.eye(4)], THR, seed=0)
    best = judge(T, inl, X[:20], xn[:20], THR)
    assert best.support < 30
    got = rescue_pose(best, X[:20], xn[:20], Xs, xn[20:], [np.eye(4)], THR, 30, seed=0)
    assert got.how == "seeds"
    assert got.support >= 30
    assert len(got.near) == 20  # the map points' flags only: seeds are not dropped here
    assert got.T is not None
    assert _rot_err_deg(got.T, T_true) < 0.5


def test_random_tracks_are_not_rescued():
    """Tracks that agree on no pose stay a loss, however wide the search."""
    rng = np.random.default_rng(2)
    X, _ = _scene(60, rng)
    xn = rng.uniform(-0.6, 0.6, (60, 2))
    T, inl = estimate_pose(X, xn, [np.eye(4)], THR, seed=0)
    best = judge(T, inl, X, xn, THR)
    got = rescue_pose(best, X, xn, np.zeros((0, 3)), np.zeros((0, 2)), [np.eye(4)], THR, 30, seed=0)
    assert got.T is None or got.support < 30


def test_seed_points_take_only_settled_seeds():
    tr = Tracks.empty()
    n = 3
    tr.pid = np.array([-1, -1, 5])
    tr.host = np.zeros(n, np.int64)
    tr.f_h = np.tile([0.0, 0.0, 1.0], (n, 1))
    tr.seed = dfl.new_seeds(n, dfl.SeedInit(2.0, 0.5))
    tr.seed["sigma2"][0] = (tr.seed["z_range"][0] / (2 * SEED_POSE_RATIO)) ** 2  # settled
    tr.seed["a"][:] = 15.0  # mostly inlier measurements
    tr.seed["sigma2"][2] = 0.0  # a map point's row: never a seed point
    X, rows = seed_points(tr, np.eye(4)[None])
    assert rows.tolist() == [0]
    assert X[0] == pytest.approx([0.0, 0.0, 2.0])


def test_loss_reason():
    assert loss_reason(10, 30) == "too_few_tracks"
    assert loss_reason(45, 30) == "failed_alignment"


def test_frames_lost_by_reason():
    # frames 0-1 before the first segment, a loss at 5 (alignment) with 4 untracked frames, one at 12
    # (tracks) with 7: 3 tried for relocalisation (the loss's own and 2 more), 4 waiting for initialisation
    seg = np.zeros(20, np.int64)
    seg[[0, 1]] = -1
    seg[5:9] = -1
    seg[12:19] = -1
    got = frames_lost(seg, [(5, "failed_alignment", ""), (12, "too_few_tracks", "")], init_wait=2)
    assert set(got) == set(LOSS_REASONS)
    assert got == {"failed_alignment": 3, "too_few_tracks": 3, "failed_init": 2 + 1 + 4}
    assert sum(got.values()) == int((seg < 0).sum())

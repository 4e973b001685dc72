"""Scale drift (metrics.scale_drift): local Sim(3) scale over windows of keyframes against the global one."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.errors import GeometryError
from mutualslam_cli.geometry import quat_to_rot
from mutualslam_cli.metrics.scale_drift import scale_drift
from mutualslam_cli.types import Trajectory


def _gt(n: int) -> Trajectory:
    """A camera circling a 1 m circle 1.5 times with a vertical wave: curved in every window of 15."""
    a = np.linspace(0.0, 3.0 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.stack([np.cos(a), np.sin(a), 0.2 * np.sin(3 * a)], axis=1)
    return Trajectory(100.0 + 0.1 * np.arange(n), poses)


def _moved(positions: np.ndarray, gt: Trajectory, seed: int = 0) -> Trajectory:
    """``positions`` put into an arbitrary map frame (rotation, offset, unit 0.37): what a monocular map holds."""
    R = quat_to_rot(np.random.default_rng(seed).normal(size=4))
    poses = gt.poses.copy()
    poses[:, :3, 3] = 0.37 * positions @ R.T + np.array([2.0, -1.0, 0.5])
    return Trajectory(gt.timestamps, poses)


def test_a_scale_drifting_linearly_from_0_8_to_1_2_gives_max_over_min_1_5():
    n, w = 400, 15
    gt = _gt(n)
    c = np.linspace(0.8, 1.2, n - 1)  # the map's unit per GT metre along the run, step k → k+1
    est = np.vstack([np.zeros(3), np.cumsum(c[:, None] * np.diff(gt.positions, axis=0), axis=0)])
    r = scale_drift(gt, _moved(est, gt), window=w)
    assert len(r.rel_scale) == n - w + 1
    assert r.n_crossing == r.n_degenerate == 0
    # a window's w − 1 steps have c within [c_k, c_k + (w − 2)·Δ] (Δ = 0.4 / (n − 2)), and its Sim(3) scale is
    # 1 / (a weighted mean of them): the extreme windows sit within (w − 2)·Δ of the ends 0.8 and 1.2
    d = (w - 2) * 0.4 / (n - 2)
    assert (1.2 - d) / (0.8 + d) - 1e-3 <= r.max_over_min <= 1.5 + 1e-3
    assert r.max_over_min == pytest.approx(1.5, abs=0.04)
    # s_loc ∝ 1 / c: the first windows (c ≈ 0.8) have the largest local scale, falling monotonically
    assert np.argmax(r.rel_scale) == 0
    assert np.argmin(r.rel_scale) == len(r.rel_scale) - 1
    assert np.all(np.diff(r.rel_scale) < 0)
    assert r.min < 1.0 < r.max
    assert r.start[0] == 0
    assert r.end[0] == w - 1
    assert r.start_time[1] == pytest.approx(gt.timestamps[1])


def test_a_map_that_holds_its_scale_has_max_over_min_1_and_no_local_error():
    gt = _gt(120)
    r = scale_drift(gt, _moved(gt.positions, gt), window=15)
    assert r.max_over_min == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(r.rel_scale, 1.0, atol=1e-9)
    assert r.global_scale == pytest.approx(1 / 0.37, rel=1e-9)
    assert r.local_ate < 1e-9
    assert r.global_rmse < 1e-9


def test_local_error_is_lower_than_the_global_one_where_the_scale_drifts():
    n = 200
    gt = _gt(n)
    c = np.linspace(0.8, 1.2, n - 1)
    est = np.vstack([np.zeros(3), np.cumsum(c[:, None] * np.diff(gt.positions, axis=0), axis=0)])
    r = scale_drift(gt, _moved(est, gt), window=15)
    assert r.local_ate < 0.1 * r.global_rmse
    assert r.global_rmse > 0.05


def test_windows_never_mix_two_segments():
    n, w = 90, 15
    gt = _gt(n)
    seg = (np.arange(n) >= 50).astype(int)
    est = gt.positions.copy()
    est[seg == 1] = 0.5 * est[seg == 1] + np.array([3.0, -1.0, 0.0])  # a restart: own origin, own unit
    r = scale_drift(gt, _moved(est, gt), segments=seg, window=w)
    assert r.n_crossing == w - 1
    assert len(r.rel_scale) == n - w + 1 - (w - 1)
    assert set(r.segment.tolist()) == {0, 1}
    assert np.all(seg[r.start] == seg[r.end])
    # each window aligned within its own segment: exact, and relative to its own segment's unit (the two
    # differ by 2 exactly: a restart is not drift, and the whole fit's scale means nothing across restarts)
    assert np.max(r.local_rmse) < 1e-9
    np.testing.assert_allclose(r.rel_scale, 1.0, atol=1e-9)
    assert r.ref_scale[-1] / r.ref_scale[0] == pytest.approx(2.0, rel=1e-9)
    # without the segments, windows across the restart mix the units and fit badly
    mixed = scale_drift(gt, _moved(est, gt), window=w)
    assert np.max(mixed.local_rmse) > 0.05


def test_fewer_keyframes_than_a_window_is_an_error_not_a_number():
    gt = _gt(10)
    with pytest.raises(GeometryError, match="10 keyframes with GT < 15"):
        scale_drift(gt, _moved(gt.positions, gt), window=15)
    with pytest.raises(ValueError, match=r"window 2 \(≥ 3\)"):
        scale_drift(gt, gt, window=2)

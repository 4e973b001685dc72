"""Map-point culling with CNN depth (Eq. 10) and host selection by L_val (paper Fig. 3)."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.backend.culling import choose_hosts, correct, cull_map_points
from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.types import Intrinsics, Trajectory

INTR = Intrinsics(100.0, 100.0, 50.0, 40.0, 100, 80)


def test_eq10_cases():
    d_cnn = np.array([1.0, 1.0, 1.0, 2.0, 2.0])
    d_mp = np.array([1.4, 1.6, 0.6, 5.0, 0.1])
    # within γ·d_CNN; outside; inside (|0.4| < 0.5); outside but d_CNN > d_max; same, far below
    np.testing.assert_array_equal(correct(d_mp, d_cnn, 0.5, 1.5), [True, False, True, True, True])
    np.testing.assert_array_equal(correct(d_mp, d_cnn, 0.5, 3.0), [True, False, True, False, False])
    assert not correct(np.array([1.0]), np.array([np.nan]), 0.5, 1.5)[0]
    with pytest.raises(ShapeError):
        correct(np.ones(2), np.ones(3), 0.5, 1.5)


def test_host_is_the_best_validated_observer():
    obs = [np.array([0, 1, 2]), np.array([0, 2]), np.array([3]), np.array([1, 2])]
    val = {0: 0.3, 1: 0.1, 2: 0.2, 4: 0.0}  # kf 3 never validated
    hosts = choose_hosts(obs, np.array([0, 0, 3, 1]), val)
    np.testing.assert_array_equal(hosts, [1, 2, 3, 1])
    tie = choose_hosts([np.array([2, 1])], np.array([2]), {1: 0.5, 2: 0.5})
    assert tie[0] == 1  # ties go to the lower id
    nan = choose_hosts([np.array([0, 1])], np.array([0]), {0: np.nan, 1: 0.4})
    assert nan[0] == 1


def _vo() -> tuple[VOResult, np.ndarray]:
    """Two keyframes 0.2 apart along x; three points seen by both, hosted in kf 0."""
    T1 = np.eye(4)
    T1[0, 3] = 0.2
    kfs = [Keyframe(0, 0, 0.0, np.eye(4)), Keyframe(1, 1, 0.1, T1)]
    Xw = np.array([[0.1, 0.0, 1.0], [0.1, 0.05, 1.2], [0.15, -0.05, 0.8]])
    pix = Xw[:, :2] / Xw[:, 2:3] * 100.0 + [50.0, 40.0]
    pts = MapPoints(np.arange(3), np.zeros(3, np.int64), pix, 1.0 / Xw[:, 2], np.zeros(3),
                    [np.array([0, 1])] * 3, [np.zeros((2, 2))] * 3)
    vo = VOResult(kfs, pts, INTR, Trajectory(np.array([0.0, 0.1]), np.stack([np.eye(4), T1])), np.zeros(2, np.int64))
    return vo, Xw


def test_cull_uses_depth_in_the_chosen_host():
    vo, Xw = _vo()
    seen = {}

    def depth_at(k, px):
        seen[k] = px.copy()
        truth = Xw[:, 2]  # a pure x-translation keeps z the same in both keyframes
        out = truth[: len(px)].copy()
        out[1] *= 2.0  # the CNN contradicts point 1 …
        out[2] = np.nan  # … and has nothing for point 2
        return out

    res = cull_map_points(vo, {0: 0.5, 1: 0.2}, depth_at, gamma=0.5, d_max=5.0)
    np.testing.assert_array_equal(res.host, [1, 1, 1])
    assert list(seen) == [1]
    # the pixels handed over are the projections into kf 1, not the kf-0 host pixels
    expect = (Xw[:, :2] - [0.2, 0.0]) / Xw[:, 2:3] * 100.0 + [50.0, 40.0]
    np.testing.assert_allclose(seen[1], expect, atol=1e-9)
    np.testing.assert_allclose(res.d_mp, Xw[:, 2], atol=1e-9)
    np.testing.assert_array_equal(res.keep, [True, False, True])
    np.testing.assert_array_equal(res.judged, [True, True, False])
    assert (res.n_before, res.n_after) == (3, 2)
    # beyond d_max the CNN is not trusted: nothing is culled
    res_far = cull_map_points(vo, {0: 0.5, 1: 0.2}, depth_at, gamma=0.5, d_max=1.0)
    assert res_far.keep[1]


def test_cull_rejects_bad_parameters_and_lookups():
    vo, _ = _vo()
    with pytest.raises(ConfigError):
        cull_map_points(vo, {}, lambda k, p: np.ones(len(p)), gamma=0.0)
    with pytest.raises(ShapeError):
        cull_map_points(vo, {}, lambda k, p: np.ones(len(p) + 1))

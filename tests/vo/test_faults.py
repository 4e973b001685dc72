"""Faults injected into the front end's map on purpose (mutualslam_cli.vo.faults): ``vo.inject_outliers``."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.errors import ConfigError
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.map.state import MapState
from mutualslam_cli.types import FrameRef, Intrinsics, Trajectory
from mutualslam_cli.vo.faults import corrupt_depths, inject_outliers


def test_inject_outliers_is_seeded_and_only_scales_depths():
    rng = np.random.default_rng(0)
    P = 200
    obs = [np.array([0, 1]) for _ in range(P)]
    pts = MapPoints(np.arange(P) + 1000, np.zeros(P, np.int64), rng.random((P, 2)) * 50, rng.uniform(0.2, 1, P),
                    np.zeros(P), obs, [np.zeros((2, 2)) for _ in range(P)])
    vo = VOResult([Keyframe(0, 0, 0.0, np.eye(4)), Keyframe(1, 1, 0.1, np.eye(4))], pts,
                  Intrinsics(50, 50, 25, 25, 50, 50), Trajectory(np.array([0.0, 0.1]), np.stack([np.eye(4)] * 2)),
                  np.zeros(2, np.int64))
    out, ids = inject_outliers(vo, 0.1, seed=3)
    assert len(ids) == 20
    assert len(np.unique(ids)) == 20
    assert np.isin(ids, pts.ids).all()
    bad = np.isin(pts.ids, ids)
    factor = pts.inv_depth / out.points.inv_depth  # depth multiplier
    np.testing.assert_allclose(np.sort(np.unique(np.round(factor[bad], 12))), [0.4, 2.0])
    np.testing.assert_array_equal(out.points.inv_depth[~bad], pts.inv_depth[~bad])
    np.testing.assert_array_equal(out.points.pixel, pts.pixel)
    np.testing.assert_array_equal(inject_outliers(vo, 0.1, seed=3)[1], ids)  # seeded
    assert not np.array_equal(inject_outliers(vo, 0.1, seed=4)[1], ids)
    assert inject_outliers(vo, 0.0, seed=3)[0] is vo
    with pytest.raises(ConfigError):
        inject_outliers(vo, 1.0, seed=3)


def test_corrupt_depths_writes_the_same_outliers_into_the_map():
    """The state's map after :func:`corrupt_depths` is :func:`inject_outliers` of its snapshot: the same ids, the
    same inverse depths, the world positions refreshed; nothing else changes."""
    rng = np.random.default_rng(1)
    st = MapState(Intrinsics(50, 50, 25, 25, 50, 50), 2)
    st.start_segment(0, 0, "homography")
    T1 = np.eye(4)
    T1[0, 3] = 0.1
    for k, T in enumerate((np.eye(4), T1)):
        st.add_keyframe(k, 0.1 * k, T, 0)
    P = 60
    px = rng.random((P, 2)) * 50
    st.add_points(np.zeros(P, np.int64), px, (px - 25) / 50, rng.uniform(0.2, 1, P), np.full(P, 0.01),
                      [{0: p, 1: p} for p in px])
    frames = [FrameRef(i, 0.1 * i, None, None, None) for i in range(2)]
    vo = st.snapshot(frames)
    want, want_ids = inject_outliers(vo, 0.2, seed=5)
    ids = corrupt_depths(st, vo, 0.2, seed=5)
    np.testing.assert_array_equal(ids, want_ids)
    after = st.snapshot(frames)
    np.testing.assert_array_equal(after.points.inv_depth, want.points.inv_depth)
    np.testing.assert_array_equal(after.points.pixel, vo.points.pixel)
    moved = np.isin(after.points.ids, ids)
    assert not np.allclose(after.points_world()[moved], vo.points_world()[moved])
    np.testing.assert_array_equal(after.points_world()[~moved], vo.points_world()[~moved])
    assert len(corrupt_depths(st, after, 0.0, seed=5)) == 0

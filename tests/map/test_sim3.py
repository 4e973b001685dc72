"""Similarities (:mod:`mutualslam_cli.map.sim3`): composition, inverse, poses and points moved alike, and poses that
follow a reference keyframe."""

from __future__ import annotations

import numpy as np

from mutualslam_cli.geometry import exp_so3, se3_inv
from mutualslam_cli.map.sim3 import Sim3, follow, rescaled


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(rng.normal(size=(1, 3)))[0]
    T[:3, 3] = rng.normal(size=3)
    return T


def _sim(rng: np.random.Generator) -> Sim3:
    return Sim3(exp_so3(rng.normal(size=(1, 3)))[0], rng.normal(size=3), float(rng.uniform(0.5, 2.0)))


def test_compose_and_inverse_act_as_the_maps_they_name():
    rng = np.random.default_rng(0)
    A, B, X = _sim(rng), _sim(rng), rng.normal(size=(5, 3))
    np.testing.assert_allclose(A.compose(B).apply_points(X), A.apply_points(B.apply_points(X)), atol=1e-12)
    np.testing.assert_allclose(A.inverse().apply_points(A.apply_points(X)), X, atol=1e-12)
    np.testing.assert_allclose((A.matrix() @ np.c_[X, np.ones(5)].T)[:3].T, A.apply_points(X), atol=1e-12)
    np.testing.assert_array_equal(Sim3.identity().apply_points(X), X)


def test_a_moved_pose_sees_the_moved_points_where_it_saw_them():
    """``T_wc ↦ [R·R_wc | s·R·t_wc + t]`` with points ``X ↦ s·R·X + t``: a point's bearing in the camera is kept and its
    depth grows by s (so inverse depths ÷ s)."""
    rng = np.random.default_rng(1)
    S, T, X = _sim(rng), _pose(rng), rng.normal(size=(4, 3))
    before = X @ se3_inv(T)[:3, :3].T + se3_inv(T)[:3, 3]
    T2 = S.apply_pose(T)
    after = S.apply_points(X) @ se3_inv(T2)[:3, :3].T + se3_inv(T2)[:3, 3]
    np.testing.assert_allclose(after, S.s * before, atol=1e-12)
    np.testing.assert_array_equal(S.apply_poses(np.stack([T, T]))[1], T2)


def test_onto_moves_one_pose_onto_another():
    rng = np.random.default_rng(2)
    A, B = _pose(rng), _pose(rng)
    np.testing.assert_allclose(Sim3.onto(A, B, 1.7).apply_pose(A), B, atol=1e-12)


def test_poses_follow_their_reference_rigidly_or_in_its_new_unit():
    rng = np.random.default_rng(3)
    ref_old, ref_new, T = _pose(rng), _pose(rng), _pose(rng)
    rel = se3_inv(ref_old) @ T
    np.testing.assert_allclose(se3_inv(ref_new) @ follow(T, se3_inv(ref_old), ref_new), rel, atol=1e-12)
    np.testing.assert_allclose(se3_inv(ref_new) @ follow(T, se3_inv(ref_old), ref_new, 2.0), rescaled(rel, 2.0),
                               atol=1e-12)
    np.testing.assert_array_equal(rescaled(rel, 2.0)[:3, :3], rel[:3, :3])
    assert follow(np.stack([T, T]), se3_inv(ref_old), ref_new).shape == (2, 4, 4)

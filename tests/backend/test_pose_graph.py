"""The Sim(3) pose graph that closes a loop (mutualslam_cli.backend.pose_graph)."""

from __future__ import annotations

import itertools

import numpy as np

from mutualslam_cli.backend.loop_detector import LoopClosure
from mutualslam_cli.backend.pose_graph import close_loop
from mutualslam_cli.geometry import exp_so3
from mutualslam_cli.map.refinement import apply_refinement
from mutualslam_cli.map.state import MapState
from mutualslam_cli.types import Intrinsics

INTR = Intrinsics(250.0, 250.0, 160.0, 120.0, 320, 240)


def _circle(n: int) -> list[np.ndarray]:
    """GT ``T_wc`` of ``n`` keyframes on a 2 m circle, looking along it."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        T = np.eye(4)
        T[:3, :3] = exp_so3(np.array([[0.0, a, 0.0]]))[0]
        T[:3, 3] = [2 * np.sin(a), 0.0, 2 * np.cos(a) - 2]
        out.append(T)
    return out


def _drifted(gt: list[np.ndarray], step_scale: float) -> tuple[list[np.ndarray], list[float]]:
    """The odometry of ``gt`` with a rotation bias per step and a unit that shrinks by ``step_scale`` per step."""
    bias = exp_so3(np.array([[0.0, 0.004, 0.002]]))[0]
    poses, units, unit = [gt[0].copy()], [1.0], 1.0
    for a, b in itertools.pairwise(gt):
        rel = np.linalg.inv(a) @ b
        rel[:3, :3] = bias @ rel[:3, :3]
        unit *= step_scale
        rel[:3, 3] *= unit
        poses.append(poses[-1] @ rel)
        units.append(unit)
    return poses, units


def test_a_loop_spreads_its_correction_over_the_keyframes_it_closes():
    gt = _circle(40)
    poses, units = _drifted(gt, 0.99)
    st = MapState(INTR, 400)
    for k, T in enumerate(poses):
        st.add_keyframe(5 * k, 0.1 * k, T, 0)
        rel = np.eye(4)
        rel[:3, 3] = [0.1, 0.0, 0.0]
        st.track_frame(5 * k + 1, 0, k, rel)  # a frame just after each keyframe
    # one point per keyframe, 2 units in front of it in its own (drifted) unit
    for k in range(len(poses)):
        st.add_points(np.array([k]), np.array([[160.0, 120.0]]), np.zeros((1, 2)), np.array([0.5]),
                          np.array([0.01]), [{k: np.array([160.0, 120.0])}])
    # the last keyframe sees the first one's place: its true pose, and the drifted unit's ratio to the old one
    loop = LoopClosure(query=39, match=0, T_cw=np.linalg.inv(gt[39]), scale=1 / units[39], inliers=100, spread=0.1,
                       n_new=50, n_old=50)
    r = close_loop(st, loop)
    err0 = np.array([np.linalg.norm(p[:3, 3] - g[:3, 3]) for p, g in zip(poses, gt)])
    err1 = np.array([np.linalg.norm(p[:3, 3] - g[:3, 3]) for p, g in zip(r.T_wc, gt)])
    assert err0.max() > 0.5
    assert err1.max() < 0.15 * err0.max()
    assert err1.mean() < 0.15 * err0.mean()
    np.testing.assert_allclose(r.T_wc[0], poses[0], atol=1e-9)  # the old end stays
    assert abs(r.scale[-1] * units[39] - 1) < 0.05  # the drifted unit restored
    # the refinement moves the map: poses, the points' depths by their host's unit, the frames with their keyframe
    apply_refinement(st, r)
    np.testing.assert_allclose(st.map.rho[39], 0.5 / r.scale[-1])
    np.testing.assert_allclose(st.pose(20), r.T_wc[20])
    np.testing.assert_allclose(st.frame_rel[5 * 39 + 1][1][:3, 3], [0.1 * r.scale[-1], 0.0, 0.0])


def _state(poses: list[np.ndarray], segment_of=lambda k: 0) -> MapState:
    st = MapState(INTR, 400)
    for k, T in enumerate(poses):
        st.add_keyframe(5 * k, 0.1 * k, T, segment_of(k))
        st.add_points(np.array([k]), np.array([[160.0, 120.0]]), np.zeros((1, 2)), np.array([0.5]),
                          np.array([0.01]), [{k: np.array([160.0, 120.0])}])
    return st


def test_a_loop_scale_is_trusted_only_as_far_as_its_standard_error():
    gt = _circle(40)  # exact odometry: the map is right, and a loop claims the unit shrank by 20 %
    wrong = dict(query=39, match=0, T_cw=np.linalg.inv(gt[39]), scale=0.8, inliers=100, spread=0.1, n_new=50,
                 n_old=50)
    sure = close_loop(_state(gt), LoopClosure(**wrong, scale_error=0.01))
    unsure = close_loop(_state(gt), LoopClosure(**wrong, scale_error=0.5))
    assert abs(np.log(sure.scale[-1] / 0.8)) < 0.05  # a sure loop's scale is followed
    assert abs(np.log(unsure.scale[-1])) < 0.05  # an unsure one leaves the odometry's unit as it was


def test_a_wrong_bridge_scale_is_corrected_at_the_bridge():
    gt = _circle(40)
    poses = [T.copy() for T in gt]
    for k in range(20, 40):  # keyframes 20+ are a second segment, joined by a bridge that got the scale 1.5x wrong
        poses[k][:3, 3] = gt[20][:3, 3] + 1.5 * (gt[k][:3, 3] - gt[20][:3, 3])
    st = _state(poses, segment_of=lambda k: int(k >= 20))
    st.joined[1] = 0  # the bridge: one map unit
    loop = LoopClosure(query=39, match=0, T_cw=np.linalg.inv(gt[39]), scale=1 / 1.5, inliers=100, spread=0.1,
                       n_new=50, n_old=50, scale_error=0.02)
    r = close_loop(st, loop)
    assert np.all(np.abs(np.log(r.scale[:20])) < 0.05)  # the first segment's unit unchanged
    assert np.all(np.abs(np.log(r.scale[20:] * 1.5)) < 0.05)  # the second one's restored, at the bridge
    err = np.array([np.linalg.norm(p[:3, 3] - g[:3, 3]) for p, g in zip(r.T_wc, gt)])
    assert err.max() < 0.1


def test_a_loop_the_map_already_agrees_with_is_not_closed_again():
    from mutualslam_cli.backend.loop_detector import LoopDetector

    gt = _circle(40)
    st = _state(gt)
    det = LoopDetector(INTR, 0.01)
    same = LoopClosure(query=39, match=0, T_cw=np.linalg.inv(gt[39]), scale=1.0, inliers=100, spread=0.1,
                       n_new=50, n_old=50)
    assert det.already_closed(st, same)
    assert det.rejected == {"already closed": 1}
    turned = gt[39].copy()
    turned[:3, :3] = turned[:3, :3] @ exp_so3(np.array([[0.0, 0.05, 0.0]]))[0]  # 2.9 degrees off
    assert not det.already_closed(st, LoopClosure(**{**same.__dict__, "T_cw": np.linalg.inv(turned)}))
    assert not det.already_closed(st, LoopClosure(**{**same.__dict__, "scale": 1.1}))

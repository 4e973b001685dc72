"""Scale-consistent re-initialisation: a new segment joined to the map before it (mutualslam_cli.backend.bridges)."""

from __future__ import annotations

import numpy as np
import pytest
from synth import make_tum_dir, plant_tracking_failures

from mutualslam_cli.backend.bridges import Bridge, bridge_segment, bridged, plan_bridge
from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import exp_so3, scale_motion
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.metrics.trajectory import ate, ate_segments
from mutualslam_cli.types import Intrinsics, Trajectory
from mutualslam_cli.vo.camera import Undistorter
from mutualslam_cli.vo.frontend import run_vo


@pytest.fixture(scope="module")
def two_segments(tmp_path_factory):
    """A room with five black frames, tracked with relocalisation off: two segments, two units."""
    root = make_tum_dir(tmp_path_factory.mktemp("bridge"), scene="room", n=100, width=320, height=240, seed=2)
    plant_tracking_failures(root, blackout=(30, 34))
    seq = load_sequence(root)
    vo = run_vo(seq, VOConfig(relocalise=False, kf_min_parallax_px=15, grid_size=16), seed=0)
    assert len({k.segment for k in vo.keyframes}) == 2
    return seq, vo


def _scales(seq, vo) -> list[float]:
    """GT scale of each segment (metres per map unit) from its own Sim(3) alignment."""
    seg = np.array([k.segment for k in vo.keyframes])
    return [s.scale for s in ate_segments(seq.gt, vo.traj_kf, seg).segments]


def test_an_exact_network_continues_the_scale_within_5_percent(two_segments):
    seq, vo = two_segments
    und = Undistorter(seq.intrinsics)

    def gt_depth(kf_id: int) -> np.ndarray:  # an exact "network": GT depth, here at half resolution
        d = und.depth(seq.load_depth(vo.keyframes[kf_id].frame_index))
        return d[::2, ::2]

    first = next(k.id for k in vo.keyframes if k.segment == 1)
    s0, s1 = _scales(seq, vo)
    assert abs(s1 / s0 - 1) > 0.1  # the segments really are in different units
    moved, b = bridge_segment(vo, first, gt_depth, seq.load_gray, seq.intrinsics)
    t0, t1 = _scales(seq, moved)
    assert abs(t1 / t0 - 1) < 0.05, (t0, t1)
    assert b.segment == 1
    assert b.onto == 0
    assert b.n_new >= 10
    assert b.n_prev >= 10
    assert b.rotation_from == "images"
    assert b.last_frame < b.frame
    # one map: a single Sim(3) now fits both segments far better than before the bridge
    assert ate(seq.gt, moved.traj_kf).rmse < 0.3 * ate(seq.gt, vo.traj_kf).rmse
    # the old segment did not move; the moved one's points follow their hosts
    old = [k.id for k in vo.keyframes if k.segment == 0]
    np.testing.assert_array_equal(np.stack([moved.keyframes[k].pose for k in old]),
                                  np.stack([vo.keyframes[k].pose for k in old]))
    hosted = np.isin(vo.points.host, [k.id for k in vo.keyframes if k.segment == 1])
    np.testing.assert_allclose(moved.points.inv_depth[hosted] * b.scale, vo.points.inv_depth[hosted])


def test_no_depth_on_a_side_leaves_the_segment_apart(two_segments):
    seq, vo = two_segments
    first = next(k.id for k in vo.keyframes if k.segment == 1)
    zeros = lambda k: np.zeros((120, 160))  # noqa: E731 - a predictor with nothing positive
    assert bridge_segment(vo, first, zeros, seq.load_gray, seq.intrinsics) is None
    assert bridge_segment(vo, 0, zeros, seq.load_gray, seq.intrinsics) is None  # the first segment stays


def test_scale_motion_stretches_rotation_and_translation():
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([[0.0, 0.03, 0.01]]))[0]
    T[:3, 3] = [0.02, -0.01, 0.005]
    np.testing.assert_allclose(scale_motion(T, 1.0), T, atol=1e-12)
    np.testing.assert_allclose(scale_motion(T, 2.0)[:3, :3], T[:3, :3] @ T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(scale_motion(T, 0.0), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(scale_motion(T, 2.0)[:3, 3], 2 * T[:3, 3])


def test_ratios_spread_too_wide_leave_the_segment_apart_and_say_why(two_segments):
    """A network whose depth is off by a random factor per pixel (log-normal, σ = 1) gives ratios whose
    median cannot be trusted to 10 %: the bridge is refused, with the spread in its reason."""
    seq, vo = two_segments
    und = Undistorter(seq.intrinsics)
    rng = np.random.default_rng(0)

    def noisy(kf_id: int) -> np.ndarray:
        d = und.depth(seq.load_depth(vo.keyframes[kf_id].frame_index))
        return d * np.exp(rng.normal(0.0, 1.0, d.shape))

    first = next(k.id for k in vo.keyframes if k.segment == 1)
    b = plan_bridge(vo, first, noisy, seq.load_gray, seq.intrinsics)
    assert b is not None
    assert "spread too wide" in b.refused
    assert b.segment == 1
    assert b.onto == 0
    assert bridge_segment(vo, first, noisy, seq.load_gray, seq.intrinsics) is None
    assert bridged(vo, [b]) is vo  # a refused bridge joins nothing


def test_units_follow_the_bridges_that_were_made():
    """A bridged map carries its units (VOResult.units): the segments the made bridges joined share one, a refused
    bridge joins nothing, and a bridge onto a joined segment joins its whole unit."""
    def made_(segment: int, onto: int, refused: str = "") -> Bridge:
        return Bridge(segment, onto, 0, 0.0, -1, 1.0, 1.0, 1.0, 0, 0, 0.0, "none", R=np.eye(3).tolist(),
                      t=[0.0, 0.0, 0.0], refused=refused)

    kfs = [Keyframe(k, k, 0.1 * k, np.eye(4), k) for k in range(5)]
    pts = MapPoints(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), [], [])
    vo = VOResult(kfs, pts, Intrinsics(100.0, 100.0, 32.0, 24.0, 64, 48), Trajectory(np.zeros(0), np.zeros((0, 4, 4))),
                  np.full(5, -1))
    units = bridged(vo, [made_(1, 0), made_(3, 2), made_(4, 3, refused="spread")]).unit_of_segment()
    assert units[0] == units[1] != units[2] == units[3] != units[4]
    assert units[4] == 4
    units = bridged(vo, [made_(1, 0), made_(3, 2), made_(2, 1)]).unit_of_segment()
    assert len(set(units[s] for s in range(4))) == 1
    assert units[4] == 4

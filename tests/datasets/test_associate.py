"""TUM text readers/writers, greedy association and GT interpolation (datasets/associate.py)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from mutualslam_cli.datasets.associate import (
    MAX_DT,
    associate,
    poses_at,
    read_list_file,
    read_tum_trajectory,
    stamps_match,
    write_tum_trajectory,
)
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import pose_from_tq, rot_to_quat
from mutualslam_cli.types import Trajectory


def _rz(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _random_traj(rng: np.random.Generator, n: int = 6) -> Trajectory:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = rng.normal(size=(n, 3))
    return Trajectory(np.cumsum(rng.uniform(0.01, 0.05, n)) + 1305031105.0, pose_from_tq(t, q))


# ----------------------------------------------------------------------------- association
def test_associate_hand_computed_example():
    a = [1.000, 1.030, 1.048, 1.300]
    b = [1.005, 1.040, 1.200]
    # candidates within 0.02: (0,0) .005, (2,1) .008, (1,1) .010 -> (1,1) loses b[1] to a[2]
    assert associate(a, b) == [(0, 0), (2, 1)]


def test_associate_each_element_used_once():
    a = np.array([0.0, 0.004, 0.008, 0.012])
    b = np.array([0.005])
    pairs = associate(a, b)
    assert pairs == [(1, 0)]  # nearest |dt| = 0.001 wins, b used once
    pairs = associate(b, a)
    assert pairs == [(0, 1)]


def test_associate_unique_on_random_streams(rng):
    a = np.sort(rng.uniform(0, 3, 90))
    b = np.sort(rng.uniform(0, 3, 90))
    pairs = associate(a, b, max_dt=0.02)
    ia, ib = zip(*pairs)
    assert len(set(ia)) == len(ia)
    assert len(set(ib)) == len(ib)
    assert all(abs(a[i] - b[j]) <= 0.02 for i, j in pairs)
    assert list(ia) == sorted(ia)  # sorted by the first stream's timestamp


def test_associate_window_and_offset():
    assert associate([0.0], [0.025]) == []
    assert associate([0.0], [0.025], max_dt=0.03) == [(0, 0)]
    assert associate([0.0], [1.01], offset=-1.0) == [(0, 0)]
    assert associate([], [1.0]) == []


def test_associate_window_keeps_a_pair_exactly_max_dt_apart():
    # the package's one rule (stamps_match): inclusive, as evo's matching
    assert associate([1.0], [1.03125], max_dt=0.03125) == [(0, 0)]  # exact binary fractions
    assert associate([1.03125], [1.0], max_dt=0.03125) == [(0, 0)]
    assert associate([1.0], [1.03125 + 1e-9], max_dt=0.03125) == []
    assert stamps_match(-0.03125, 0.03125)
    assert not stamps_match(0.0312501, 0.03125)
    assert MAX_DT == 0.02


def test_associate_result_sorted_by_first_timestamp_for_unsorted_input():
    a = [3.0, 1.0, 2.0]
    b = [1.001, 2.001, 3.001]
    assert associate(a, b) == [(1, 0), (2, 1), (0, 2)]


# ----------------------------------------------------------------------------- list files
def test_read_list_file_skips_comments_and_keeps_line_numbers():
    text = "# color images\n# timestamp filename\n1.5 rgb/1.5.png\n\n2.5 rgb/2.5.png\n"
    lf = read_list_file(io.StringIO(text))
    np.testing.assert_array_equal(lf.timestamps, [1.5, 2.5])
    assert lf.paths == ["rgb/1.5.png", "rgb/2.5.png"]
    assert lf.lines == [3, 5]


def test_read_list_file_malformed_names_file_and_line(tmp_path):
    p = tmp_path / "rgb.txt"
    p.write_text("# c\n1.0 rgb/a.png\nabc rgb/b.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:3: expected 'timestamp path'"):
        read_list_file(p)


# ----------------------------------------------------------------------------- trajectories
def test_trajectory_round_trip_stringio_full_precision(rng):
    traj = _random_traj(rng)
    buf = io.StringIO()
    write_tum_trajectory(buf, traj)
    back = read_tum_trajectory(io.StringIO(buf.getvalue()))
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-12)


def test_write_trajectory_to_path_is_atomic_and_readable(tmp_path, rng):
    traj = _random_traj(rng)
    out = tmp_path / "sub" / "traj.txt"
    write_tum_trajectory(out, traj)
    assert sorted(p.name for p in out.parent.iterdir()) == ["traj.txt"]  # no temp file left
    np.testing.assert_allclose(read_tum_trajectory(out).positions, traj.positions, atol=1e-12)


def test_write_trajectory_header_comments_and_fixed_decimals():
    traj = Trajectory(np.array([0.0, 1 / 30]), np.stack([np.eye(4)] * 2))
    traj.poses[1, :3, 3] = [1.0, -2.0, 0.5]
    buf = io.StringIO()
    write_tum_trajectory(buf, traj, comments=("ground truth", "made by a test"), time_format=".6f", value_format=".9f")
    assert buf.getvalue() == (
        "# ground truth\n# made by a test\n# timestamp tx ty tz qx qy qz qw\n"
        "0.000000 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 1.000000000\n"
        "0.033333 1.000000000 -2.000000000 0.500000000 0.000000000 0.000000000 0.000000000 1.000000000\n"
    )


def test_trajectory_malformed_line_names_file_and_line(tmp_path):
    p = tmp_path / "groundtruth.txt"
    p.write_text("# ground truth\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError) as e:
        read_tum_trajectory(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:3: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got")
    with pytest.raises(DatasetError, match=r"<stream>:1: expected 8 numbers"):
        read_tum_trajectory(io.StringIO("1.0 0 0 x 0 0 0 1\n"))


def test_trajectory_sorted_and_quaternion_order_is_xyzw():
    text = "2.0 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n1.0 0 0 0 0 0 0 1\n"
    traj = read_tum_trajectory(io.StringIO(text))
    np.testing.assert_array_equal(traj.timestamps, [1.0, 2.0])
    np.testing.assert_allclose(traj.poses[1, :3, :3], _rz(90), atol=1e-12)
    np.testing.assert_allclose(traj.poses[1, :3, 3], [1, 2, 3])


# ----------------------------------------------------------------------------- interpolation
def test_poses_at_exact_samples_and_midpoint_slerp():
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[:3, :3] = _rz(90)
    T1[:3, 3] = [1.0, 2.0, 0.0]
    gt = Trajectory([10.0, 10.05], np.stack([T0, T1]))
    p = poses_at(gt, [10.0, 10.05, 10.025])
    np.testing.assert_allclose(p[0], T0)
    np.testing.assert_allclose(p[1], T1)
    np.testing.assert_allclose(p[2][:3, :3], _rz(45), atol=1e-12)
    np.testing.assert_allclose(p[2][:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rot_to_quat(p[2][:3, :3]), [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)], atol=1e-12)


def test_poses_at_gap_and_outside_span_give_none():
    gt = Trajectory([0.0, 0.11, 0.5], np.stack([np.eye(4)] * 3))
    p = poses_at(gt, [-0.01, 0.055, 0.3, 0.51], max_gap=0.1)
    assert p[0] is None
    assert p[3] is None
    assert p[1] is not None  # 0.11 s hole: both samples within 0.1 s of the image
    assert p[2] is None  # 0.39 s hole
    exact = poses_at(gt, [0.11, 0.2], max_gap=0.0)  # ICL frame numbers: exact only
    assert exact[0] is not None
    assert exact[1] is None

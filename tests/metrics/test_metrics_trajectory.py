"""Closed-form checks of metrics.trajectory (STYLE §4): Sim(3) recovery, degeneracy, association."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.errors import ConfigError, DatasetError, MslamError, ShapeError
from mutualslam_cli.geometry import quat_to_rot
from mutualslam_cli.metrics.trajectory import (
    GeometryError,
    associate_indices,
    associate_trajectories,
    ate,
    ate_segments,
    path_length,
    umeyama,
)
from mutualslam_cli.types import Trajectory


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return quat_to_rot(rng.normal(size=4))


def random_trajectory(rng: np.random.Generator, n: int = 60, dt: float = 1 / 30) -> Trajectory:
    """A smooth-ish random walk with random orientations, timestamps 1000 + k·dt."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    poses[:, :3, :3] = quat_to_rot(rng.normal(size=(n, 4)))
    return Trajectory(1000.0 + dt * np.arange(n), poses)


def apply_sim3(traj: Trajectory, R: np.ndarray, t: np.ndarray, s: float, dt: float = 0.0) -> Trajectory:
    """World-frame similarity S·T_wc: positions s·R·p + t, orientations R·R_wc."""
    poses = traj.poses.copy()
    poses[:, :3, 3] = s * traj.positions @ R.T + t
    poses[:, :3, :3] = R @ traj.poses[:, :3, :3]
    return Trajectory(traj.timestamps + dt, poses)


@pytest.mark.parametrize("seed", range(5))
def test_sim3_of_trajectory_gives_zero_ate_and_recovers_scale(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref = random_trajectory(rng)
    R, t, s = random_rotation(rng), rng.normal(size=3) * 3, float(rng.uniform(0.2, 5.0))
    est = apply_sim3(ref, R, t, s, dt=0.004)  # est = S·ref, so aligning est→ref needs S⁻¹
    res = ate(ref, est, "sim3")
    assert res.n_pairs == len(ref)
    assert res.rmse < 1e-9
    assert res.max < 1e-9
    assert res.scale == pytest.approx(1.0 / s, rel=1e-10)
    # the transform maps est positions onto ref positions and has rotation part R^T
    p = est.positions @ res.transform[:3, :3].T + res.transform[:3, 3]
    np.testing.assert_allclose(p, ref.positions, atol=1e-9)
    np.testing.assert_allclose(res.transform[:3, :3] / res.scale, R.T, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_umeyama_recovers_known_transform(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(20, 3))
    R, t, s = random_rotation(rng), rng.normal(size=3), 0.7
    dst = s * src @ R.T + t
    R2, t2, s2 = umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    assert s2 == pytest.approx(s, rel=1e-12)
    assert np.linalg.det(R2) == pytest.approx(1.0)
    _, _, s3 = umeyama(src, dst, with_scale=False)
    assert s3 == 1.0


def test_se3_alignment_of_scaled_trajectory_is_not_zero() -> None:
    rng = np.random.default_rng(7)
    ref = random_trajectory(rng)
    est = apply_sim3(ref, random_rotation(rng), rng.normal(size=3), 2.5)
    res = ate(ref, est, "se3")
    assert res.scale == 1.0
    assert res.rmse > 0.1 * path_length(ref) / len(ref)  # scale error stays
    assert ate(ref, est, "sim3").rmse < 1e-9


@pytest.mark.parametrize("seed", range(3))
def test_se3_alignment_removes_rigid_change_of_world_frame(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref = random_trajectory(rng)
    noisy = Trajectory(ref.timestamps, ref.poses.copy())
    noisy.poses[:, :3, 3] += rng.normal(scale=0.01, size=(len(ref), 3))
    base = ate(ref, noisy, "se3").rmse
    moved = apply_sim3(noisy, random_rotation(rng), rng.normal(size=3), 1.0)
    assert base > 1e-3
    assert ate(ref, moved, "se3").rmse == pytest.approx(base, rel=1e-9)
    assert ate(ref, moved, "none").rmse > 10 * base  # without alignment the frame change shows


def test_no_alignment_measures_raw_offset() -> None:
    rng = np.random.default_rng(1)
    ref = random_trajectory(rng)
    shift = np.array([0.3, -0.4, 0.0])  # |shift| = 0.5
    est = apply_sim3(ref, np.eye(3), shift, 1.0)
    res = ate(ref, est, "none")
    np.testing.assert_allclose(res.errors, 0.5, atol=1e-12)
    assert res.rmse == pytest.approx(0.5)
    assert res.std == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(res.transform, np.eye(4))


def test_statistics_of_errors() -> None:
    ref = Trajectory(np.arange(4.0), np.tile(np.eye(4), (4, 1, 1)))
    est = Trajectory(np.arange(4.0), np.tile(np.eye(4), (4, 1, 1)))
    est.poses[:, 0, 3] = [0.0, 1.0, 2.0, 3.0]
    res = ate(ref, est, "none")
    assert res.rmse == pytest.approx(np.sqrt(14 / 4))
    assert (res.mean, res.median, res.max, res.min) == pytest.approx((1.5, 1.5, 3.0, 0.0))
    assert res.std == pytest.approx(np.std([0, 1, 2, 3]))


def test_identical_poses_raise() -> None:
    ref = random_trajectory(np.random.default_rng(0), n=10)
    est = Trajectory(ref.timestamps, np.tile(np.eye(4), (10, 1, 1)))
    with pytest.raises(GeometryError, match="degenerate"):
        ate(ref, est, "sim3")
    with pytest.raises(GeometryError, match="degenerate"):
        ate(ref, est, "se3")
    assert issubclass(GeometryError, MslamError)


def test_collinear_and_too_few_points_raise() -> None:
    line = np.outer(np.arange(6.0), [1.0, 2.0, 3.0])
    with pytest.raises(GeometryError, match="rank"):
        umeyama(line, line + 1.0, with_scale=True)
    with pytest.raises(GeometryError, match="at least 3"):
        umeyama(np.eye(3)[:2], np.eye(3)[:2], with_scale=False)
    with pytest.raises(ShapeError):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)), with_scale=False)
    bad = np.random.default_rng(0).normal(size=(5, 3))
    bad[2, 1] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        umeyama(bad, bad, with_scale=False)


def test_association_with_jitter_and_cutoff() -> None:
    rng = np.random.default_rng(3)
    ref = random_trajectory(rng, n=100, dt=0.01)  # 100 Hz GT
    idx = np.arange(0, 100, 3)  # 30 Hz estimate
    jitter = rng.uniform(-0.004, 0.004, size=len(idx))  # < half the GT spacing: nearest is idx
    t_est = ref.timestamps[idx] + jitter
    far = np.arange(len(idx)) % 5 == 0
    t_est[far] = ref.timestamps[-1] + 0.5 + np.arange(far.sum())  # outside any window
    est = Trajectory(np.sort(t_est), ref.poses[idx][np.argsort(t_est)])
    ref_sub, est_sub = associate_trajectories(ref, est, max_dt=0.02)
    assert len(ref_sub) == (~far).sum()
    np.testing.assert_array_equal(ref_sub.timestamps, ref.timestamps[idx[~far]])
    assert np.all(np.abs(ref_sub.timestamps - est_sub.timestamps) <= 0.004)
    # a window smaller than some jitters drops exactly those pairs
    i_ref, _ = associate_indices(ref.timestamps, est.timestamps, max_dt=0.002)
    assert len(i_ref) == int(np.sum(np.abs(jitter[~far]) <= 0.002))


def test_nearest_matches_like_evo_unique_is_one_to_one() -> None:
    ref_t = np.array([1.006, 3.0, 4.0, 5.0])  # longer trajectory (4 poses)
    est_t = np.array([1.0, 1.01, 5.0])  # shorter: each takes its nearest ref stamp
    i_ref, i_est = associate_indices(ref_t, est_t, 0.02, "nearest")
    assert i_ref.tolist() == [0, 0, 3]
    assert i_est.tolist() == [0, 1, 2]
    i_ref, i_est = associate_indices(ref_t, est_t, 0.02, "unique")
    assert i_ref.tolist() == [0, 3]
    assert i_est.tolist() == [1, 2]
    with pytest.raises(ConfigError, match="nearest, unique"):
        associate_indices(ref_t, est_t, 0.02, "closest")  # type: ignore[arg-type]


def test_tie_goes_to_earlier_stamp_and_window_is_inclusive() -> None:
    long_t = np.array([1.0, 1.015625, 1.03125, 2.0])  # exact binary fractions
    i_long, i_short = associate_indices(long_t, np.array([1.0078125, 1.0625]), 0.03125)
    assert i_long.tolist() == [0, 2]
    assert i_short.tolist() == [0, 1]


def test_unique_and_nearest_share_the_inclusive_window() -> None:
    # one pair exactly max_dt apart (exact binary fractions): both methods keep it (one rule, stamps_match)
    ref_t, est_t = np.array([1.0, 2.0, 3.0]), np.array([1.03125, 2.0])
    assert [a.tolist() for a in associate_indices(ref_t, est_t, 0.03125, "nearest")] == [[0, 1], [0, 1]]
    assert [a.tolist() for a in associate_indices(ref_t, est_t, 0.03125, "unique")] == [[0, 1], [0, 1]]
    assert [a.tolist() for a in associate_indices(ref_t, est_t + 1e-6, 0.03125, "unique")] == [[1], [1]]


def test_no_overlap_raises_with_spans() -> None:
    rng = np.random.default_rng(0)
    ref = random_trajectory(rng, n=10)
    est = Trajectory(ref.timestamps + 100.0, ref.poses)
    with pytest.raises(DatasetError, match=r"no timestamps of est within 0.02 s of ref: est spans 1100\.0+–"):
        ate(ref, est)
    with pytest.raises(DatasetError, match=r"ref spans 1000.000000–1000.3"):
        ate_segments(ref, est, np.zeros(10, dtype=int))


def test_unknown_alignment_lists_valid_ones() -> None:
    ref = random_trajectory(np.random.default_rng(0), n=5)
    with pytest.raises(ConfigError, match="sim3, se3, none"):
        ate(ref, ref, "sim2")  # type: ignore[arg-type]


def test_segments_are_aligned_separately() -> None:
    rng = np.random.default_rng(5)
    ref = random_trajectory(rng, n=62)
    seg = np.repeat([0, 1, 2], [30, 30, 2])
    parts = []
    for sid, s in zip(range(3), (0.5, 3.0, 1.0)):
        part = ref.subset(seg == sid)
        parts.append(apply_sim3(part, random_rotation(rng), rng.normal(size=3), s).poses)
    est = Trajectory(ref.timestamps, np.concatenate(parts))
    res = ate_segments(ref, est, seg)
    assert res.rmse < 1e-9
    assert res.n_pairs == 60
    assert (res.n_segments, res.n_skipped, res.n_pairs_skipped) == (3, 1, 2)
    scales = {s.segment: s.scale for s in res.segments}
    assert scales[0] == pytest.approx(2.0)
    assert scales[1] == pytest.approx(1 / 3)
    assert res.segments[2].skipped
    assert np.isnan(res.segments[2].rmse)
    assert "separately" in res.note
    assert res.summary()["per_segment_alignment"] is True
    assert ate(ref, est, "sim3").rmse > 0.01  # one global Sim(3) cannot fit both scales
    with pytest.raises(ShapeError):
        ate_segments(ref, est, seg[:-1])


def test_segments_all_skipped_raise() -> None:
    ref = random_trajectory(np.random.default_rng(0), n=6)
    with pytest.raises(GeometryError, match="none of 3 segments"):
        ate_segments(ref, ref, np.array([0, 0, 1, 1, 2, 2]))


def test_path_length_of_square() -> None:
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]]
    assert path_length(Trajectory(np.arange(5.0), poses)) == pytest.approx(4.0)
    assert path_length(Trajectory(np.arange(1.0), poses[:1])) == 0.0


def test_summary_is_plain_values() -> None:
    ref = random_trajectory(np.random.default_rng(2), n=10)
    summ = ate(ref, ref, "sim3").summary()
    assert set(summ) >= {"rmse", "mean", "median", "max", "n_pairs", "scale", "align"}
    assert all(isinstance(v, (int, float, str)) for v in summ.values())

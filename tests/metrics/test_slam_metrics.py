"""The trajectory figures of a run: one Sim(3) as the headline, each segment on its own as a named second."""

from __future__ import annotations

import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.metrics.slam import evaluate_trajectory
from mutualslam_cli.results.summary import Summary, flatten
from mutualslam_cli.stages.ate_keys import set_ate
from mutualslam_cli.types import Trajectory


def _vo(seq, segment_of_frame: np.ndarray, moves: dict[int, tuple[float, np.ndarray]]) -> VOResult:
    """GT poses of every frame, each segment moved by its own (scale, translation): what a front end
    that restarted in segments, each at its own origin and unit, would hand on."""
    poses = []
    for i, f in enumerate(seq.frames):
        s, t = moves[int(segment_of_frame[i])]
        T = f.pose.copy()
        T[:3, 3] = s * T[:3, 3] + t
        poses.append(T)
    ts = np.array([f.timestamp for f in seq.frames])
    kfs = [Keyframe(i, i, ts[i], poses[i], int(segment_of_frame[i])) for i in range(0, len(seq), 3)]
    empty = MapPoints(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), [], [])
    return VOResult(kfs, empty, seq.intrinsics, Trajectory(ts, np.stack(poses)), segment_of_frame.astype(np.int64))


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return load_sequence(make_tum_dir(tmp_path_factory.mktemp("traj"), scene="room", n=30, width=64, height=48))


def test_two_segments_pay_in_the_headline_and_not_in_the_per_segment_figure(seq):
    seg = (np.arange(len(seq)) >= 15).astype(int)
    vo = _vo(seq, seg, {0: (1.0, np.zeros(3)), 1: (0.5, np.array([1.0, -2.0, 0.3]))})
    r = evaluate_trajectory(seq, vo)
    assert r["segments"] == 2
    assert r["kf"].rmse > 0.005
    assert r["all"].rmse > 0.005
    assert r["kf_per_segment"].rmse < 1e-6
    assert r["all_per_segment"].rmse < 1e-6
    s = Summary()
    set_ate(s, r, {"kf": "vo", "all": "all_frames"})
    flat = flatten(s.to_dict(required=()))
    assert flat["trajectory.ate_rmse_m.vo"] == pytest.approx(r["kf"].rmse)
    assert flat["trajectory.ate_rmse_m_per_segment.vo"] == pytest.approx(r["kf_per_segment"].rmse)
    assert "aligned separately" in flat["notes"]["trajectory.ate_rmse_m_per_segment.vo"]
    assert "trajectory.ate_rmse_m.vo" not in flat["notes"]


def test_one_segment_has_one_figure(seq):
    vo = _vo(seq, np.zeros(len(seq), int), {0: (0.7, np.array([0.2, 0.0, 0.0]))})
    r = evaluate_trajectory(seq, vo)
    assert r["segments"] == 1
    assert r["kf"].rmse < 1e-6
    assert r["kf_per_segment"] is None
    s = Summary()
    set_ate(s, r, {"kf": "vo", "all": "all_frames"})
    flat = flatten(s.to_dict(required=()))
    assert flat["trajectory.ate_rmse_m_per_segment.vo"] == flat["trajectory.ate_rmse_m.vo"]

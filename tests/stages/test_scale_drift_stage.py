"""The scale-drift stage of a run: keys per map, ``scale_drift.csv`` and ``.png``; null with a reason without GT,
with too few keyframes, or without the map."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
from synth import make_tum_dir

from mutualslam_cli.config import load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.results.summary import flatten
from mutualslam_cli.stages import scale_drift
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.types import Trajectory


def _vo(seq, unit_of_frame: np.ndarray, segment_of_frame: np.ndarray | None = None) -> VOResult:
    """Every frame a keyframe at its GT pose, its position in a map unit of ``unit_of_frame[i]`` per metre
    (accumulated along the path: a unit that drifts), each segment restarting at its own origin."""
    n = len(seq)
    seg = np.zeros(n, np.int64) if segment_of_frame is None else segment_of_frame
    gt = np.stack([f.pose for f in seq.frames])
    steps = np.diff(gt[:, :3, 3], axis=0) * unit_of_frame[1:, None]
    pos = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    poses = gt.copy()
    poses[:, :3, 3] = pos + 3.0 * seg[:, None]  # a restart: its own origin
    ts = np.array([f.timestamp for f in seq.frames])
    kfs = [Keyframe(i, i, ts[i], poses[i], int(seg[i])) for i in range(n)]
    empty = MapPoints(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), [], [])
    return VOResult(kfs, empty, seq.intrinsics, Trajectory(ts, poses), seg)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return load_sequence(make_tum_dir(tmp_path_factory.mktemp("sd"), scene="room", n=40, width=64, height=48))


def _run(seq, tmp_path) -> RunContext:
    return RunContext(seq, load_config(None), tmp_path, tmp_path)


def test_each_map_gets_its_keys_a_table_and_a_figure(seq, tmp_path):
    run = _run(seq, tmp_path)
    held = _vo(seq, np.full(len(seq), 0.5))
    drifting = _vo(seq, np.linspace(0.6, 1.2, len(seq)))
    out = scale_drift.run_stage(run, {"vo": drifting, "ba": held})
    flat = flatten(run.summary.to_dict(required=()))
    assert flat["trajectory.local_scale.ba.max_over_min"] == pytest.approx(1.0, abs=1e-6)
    assert flat["trajectory.local_ate_m.ba"] < 1e-6
    assert flat["trajectory.local_scale.vo.max_over_min"] > 1.3  # a unit going from 0.6 to 1.2 per metre
    assert flat["trajectory.local_scale.vo.min"] < 1.0 < flat["trajectory.local_scale.vo.max"]
    assert "windows of 15 keyframes" in flat["notes"]["trajectory.local_scale.vo.max_over_min"]
    table = pd.read_csv(tmp_path / "scale_drift.csv")
    assert list(table.columns) == list(scale_drift.COLUMNS)
    assert (table["map"].value_counts() == len(seq) - 15 + 1).all()
    vo_rows = table[table["map"] == "vo"]
    assert vo_rows["relative_scale"].max() == pytest.approx(out["vo"].max)
    assert (vo_rows["end_kf"] - vo_rows["start_kf"] == 14).all()
    png = (tmp_path / "scale_drift.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(png) > 10_000


def test_windows_stay_within_a_segment(seq, tmp_path):
    run = _run(seq, tmp_path)
    seg = (np.arange(len(seq)) >= 20).astype(np.int64)
    unit = np.where(seg == 1, 0.25, 1.0)  # the second segment in a unit of its own
    out = scale_drift.run_stage(run, {"vo": _vo(seq, unit, seg)})
    r = out["vo"]
    assert r.n_crossing == 14
    assert np.max(r.local_rmse) < 1e-6
    assert r.max_over_min == pytest.approx(1.0, abs=1e-6)  # each segment against its own unit
    table = pd.read_csv(tmp_path / "scale_drift.csv")
    assert set(table["segment"]) == {0, 1}
    ref = table.groupby("segment")["ref_scale"].first()
    assert ref[1] / ref[0] == pytest.approx(4.0, rel=1e-6)


def test_absent_with_reasons_never_zero(seq, tmp_path):
    run = _run(dataclasses.replace(seq, gt=None), tmp_path)
    scale_drift.run_stage(run, {"vo": _vo(seq, np.ones(len(seq))), "ba": None}, {"ba": "disabled (ba.enabled=false)"})
    s = run.summary.to_dict(required=())
    flat = flatten(s)
    for k in scale_drift.keys("vo"):
        assert flat[k] is None
        assert s["notes"][k] == "sequence has no GT poses"
    for k in scale_drift.keys("ba"):
        assert flat[k] is None
        assert s["notes"][k] == "disabled (ba.enabled=false)"
    assert not (tmp_path / "scale_drift.csv").exists()
    assert not (tmp_path / "scale_drift.png").exists()
    short = _run(seq, tmp_path)
    few = _vo(seq, np.ones(len(seq)))
    few = VOResult(few.keyframes[:10], few.points, few.intrinsics, few.traj_all, few.frame_segment)
    scale_drift.run_stage(short, {"vo": few})
    s = short.summary.to_dict(required=())
    assert flatten(s)["trajectory.local_ate_m.vo"] is None
    assert "10 keyframes with GT < 15" in s["notes"]["trajectory.local_ate_m.vo"]

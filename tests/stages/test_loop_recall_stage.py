"""The loop-recall stage: keys, reasons and ``loop_recall.csv`` from what a loop closer recorded, GT associated
to keyframes by timestamp; null with reasons without GT or without loop closure."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from synth import make_tum_dir

from mutualslam_cli.config import load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.results.summary import Summary, flatten
from mutualslam_cli.stages import loop_recall
from mutualslam_cli.stages.adaptation_summary import summarise_no_loops
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.types import Trajectory

N = 80  # keyframes: two laps of 40 on a 1 m circle (15.7 cm apart)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    """A sequence of N frames whose GT goes round a circle twice, looking outwards, sampled at 2× the frames."""
    s = load_sequence(make_tum_dir(tmp_path_factory.mktemp("lr"), scene="room", n=N, width=64, height=48))
    ts = np.array([f.timestamp for f in s.frames])
    t_gt = np.sort(np.concatenate([ts, ts + 0.5 * np.diff(ts).min()]))
    a = np.interp(t_gt, ts, np.linspace(0, 4 * np.pi, N, endpoint=False))
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, 0, 3], T[:, 1, 3] = np.cos(a), np.sin(a)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    return dataclasses.replace(s, gt=Trajectory(t_gt, T))


def _vo(seq) -> VOResult:
    """Every frame a keyframe (poses: anything; the recall reads GT only)."""
    ts = np.array([f.timestamp for f in seq.frames])
    kfs = [Keyframe(i, i, ts[i], np.eye(4), 0) for i in range(N)]
    empty = MapPoints(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), [], [])
    return VOResult(kfs, empty, seq.intrinsics, Trajectory(ts, np.tile(np.eye(4), (N, 1, 1))), np.zeros(N, np.int64))


def _closer():
    """What a loop closer recorded: keyframe 40 closed onto 0, 41..69 skipped (within min_gap of it), the rest
    queried, proposing the keyframe 40 before (a true partner) from 70 on, verified from 75 on."""
    queries = []
    for kf in range(30, N):
        if 41 <= kf < 70:
            continue
        pool = np.arange(0, kf - 29)
        partner = kf - 40 if kf >= 40 else 0
        cands = [partner, 5] if kf == 40 or kf >= 70 else [5, 6]
        verified = partner if kf == 40 or kf >= 75 else None
        queries.append({"kf": kf, "pool": pool, "candidates": cands,
                        "geometry": {partner: "passed"} if verified is not None else {c: "refuted by verification"
                                                                                      for c in cands},
                        "verified": verified, "outcome": "loop" if kf == 40 else "scale uncertain"})
    skipped = {kf: "not queried: within loop.min_gap (30) keyframes of the loop closed at keyframe 40"
               for kf in range(41, 70)}
    return SimpleNamespace(detector=SimpleNamespace(queries=queries), loops=[SimpleNamespace(query=40, match=0)],
                           skipped=skipped)


def test_recall_counts_reasons_and_table(seq, tmp_path):
    cfg = load_config(None, ["loop.enabled=true", "loop.min_gap=30"])
    run = RunContext(seq, cfg, tmp_path, tmp_path)
    rows = loop_recall.run_stage(run, _closer(), _vo(seq))
    s = run.summary.to_dict(required=())
    flat = flatten(s)
    # the second lap (40..79) revisits the first; 39 (the first lap's end) is 1 step from 0 but only 39 apart ≥ 30
    assert flat["loop.recall.revisits"] == len(rows) == 41
    assert flat["loop.recall.closed"] == 1
    assert flat["loop.recall.found"] == 1 + 10
    assert flat["loop.recall.verified"] == 1 + 5
    assert flat["loop.recall.refused"] == 40
    notes = s["notes"]["loop.recall.refused"]
    assert "not queried: within loop.min_gap (30) keyframes of the loop closed at keyframe 40: 29" in notes
    assert "scale uncertain: 5" in notes
    assert "geometry: refuted by verification: 5" in notes
    table = pd.read_csv(tmp_path / "loop_recall.csv")
    assert list(table.columns) == list(loop_recall.COLUMNS)
    assert len(table) == 41
    r40 = table[table["kf"] == 40].iloc[0]
    assert r40["partner"] == 0
    assert r40["closed"]
    assert r40["dist_m"] < 1e-6
    assert r40["frame"] == 40
    assert (table["dist_m"] <= 0.30).all()
    assert (table["angle_deg"] <= 30).all()


def test_absent_without_gt_or_without_loop_closure(seq, tmp_path):
    cfg = load_config(None, ["loop.enabled=true"])
    run = RunContext(dataclasses.replace(seq, gt=None), cfg, tmp_path, tmp_path)
    assert loop_recall.run_stage(run, _closer(), _vo(seq)) is None
    s = run.summary.to_dict(required=())
    for k in loop_recall.RECALL_KEYS:
        assert flatten(s)[k] is None
        assert s["notes"][k] == "sequence has no GT poses"
    assert not (tmp_path / "loop_recall.csv").exists()
    off = Summary()
    summarise_no_loops(off, "loop.enabled=false (the paper: no loop closure)")
    d = off.to_dict(required=())
    for k in loop_recall.RECALL_KEYS:
        assert flatten(d)[k] is None
        assert d["notes"][k].startswith("loop.enabled=false")


def test_a_run_with_loop_closure_and_gt_writes_its_recall(tiny_run, tmp_path):
    """End to end on a 24-frame room: the recall keys are counts (0 revisits is a count, not an absence), the
    table is written; the scale drift of its few keyframes is null with the reason."""
    import json

    from synth import make_tum_dir

    from mutualslam_cli.config import CONFIG_DIR
    from mutualslam_cli.pipeline import run_sequence

    tmp, _ = tiny_run
    seq_dir = make_tum_dir(tmp_path / "seq", scene="room", n=24, width=320, height=240)
    cfg = load_config(CONFIG_DIR / "smoke.yaml", [f"net.weights={tmp / 'weights'}", "vo.mode=svo", "loop.enabled=true",
                                                  "loop.min_gap=2"])
    r = run_sequence(seq_dir, cfg, out=tmp_path / "out")
    assert r.summary.get("vo.keyframes") >= 2
    s = json.loads((r.folder / "summary.json").read_text())
    flat = flatten(s)
    for k in loop_recall.RECALL_KEYS:
        assert isinstance(flat[k], int), k
    assert flat["loop.recall.closed"] <= flat["loop.recall.verified"] <= flat["loop.recall.found"] \
        <= flat["loop.recall.revisits"]
    table = pd.read_csv(r.folder / "loop_recall.csv")
    assert len(table) == flat["loop.recall.revisits"]
    assert flat["trajectory.local_scale.vo.max_over_min"] is None
    assert "keyframes with GT < 15" in s["notes"]["trajectory.local_scale.vo.max_over_min"]

"""A causal run end to end with our VO: the front end is lost, the new segment is bridged by the network of its
time and tracked on in that unit, Algorithm 1's global BA reaches the front end, and a run that reads the
journal cache (resumed from a resumption point, checked event by event) is the uncached run, bit for bit."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from synth import make_tum_dir, plant_tracking_failures

from mutualslam_cli.adapt.depthnet import DepthNet, predict_depth
from mutualslam_cli.adapt.weights import save_monodepth2
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.online import loop as online_loop
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.stages import adaptation, frontend
from mutualslam_cli.stages.frontend import run_frontend
from mutualslam_cli.vo.journal_cache import cache_path, load_entry


@pytest.fixture(scope="module")
def lost(tmp_path_factory):
    """100 rendered frames, black at 40–44: with relocalisation off, two segments (the second from frame 45)."""
    tmp = tmp_path_factory.mktemp("online_run")
    torch.manual_seed(0)
    save_monodepth2(DepthNet(), tmp / "weights", 64, 96)
    root = plant_tracking_failures(make_tum_dir(tmp, scene="room", n=100, width=320, height=240, seed=2),
                                   blackout=(40, 44))
    return tmp, root


def _cfg(tmp: Path, *extra: str):
    return load_config(CONFIG_DIR / "smoke.yaml", [
        f"net.weights={tmp / 'weights'}", "vo.mode=svo", "vo.relocalise=false", "vo.kf_min_parallax_px=8",
        "vo.grid_size=16", "adapt.steps_per_keyframe=1", "adapt.validate_every=10", "adapt.patience=1",
        "adapt.tau_val=1e9", "ba.d_max=0.2", "eval.stride=5", "eval.export_frames=0", *extra])


@pytest.fixture(scope="module")
def causal(lost):
    """The causal run, uncached (a fresh results root, and the front end alone run without the cache, which it
    would fill), watched: the bridge's network and the loop's steps."""
    tmp, root = lost
    seen, loops = [], []
    mp = pytest.MonkeyPatch()
    plan, run_loop, alone = online_loop.plan_bridge, adaptation.OnlineLoop.run_loop, frontend.front_end_alone

    def spy_loop(self):
        loops.append(self)
        return run_loop(self)

    def spy_plan(snap, kf, depth_of, *a):
        loop = loops[-1]
        now = predict_depth(loop.net, loop.load(kf)[None], False)[0]
        seen.append({"kf": kf, "frame": loop.source.frame, "steps": len(loop.adapter.step_ms),
                     "depth_of": depth_of(kf), "now": now})
        return plan(snap, kf, depth_of, *a)

    mp.setattr(adaptation.OnlineLoop, "run_loop", spy_loop)
    mp.setattr(online_loop, "plan_bridge", spy_plan)
    mp.setattr(frontend, "front_end_alone", lambda seq, cfg, cache_dir=None: alone(seq, cfg, None))
    try:
        r = run_sequence(root, _cfg(tmp), out=tmp / "a", command=["test"])
    finally:
        mp.undo()
    return r, seen, loops[-1]


def test_a_lost_front_end_is_bridged_then_and_goes_on_in_that_unit(lost, causal):
    tmp, root = lost
    r, seen, loop = causal
    flat = r.summary.flat()
    assert flat["adaptation.labels"] == "causal"
    assert flat["vo.segments"] == 2
    assert flat["vo.bridges"] >= 1
    assert flat["ba.runs"] >= 1
    assert flat["ba.requested"] >= 1
    for name in ("traj_kf_bridged.txt", "traj_all_bridged.txt", "traj_kf.txt", "traj_kf_ba.txt"):
        assert (r.folder / name).is_file(), name
    # the bridge was made when the segment appeared, by the network as adapted up to then
    (b,) = seen
    state = loop.state
    first = next(k for k in range(state.n_keyframes) if state.segment(k) == 1)
    assert b["kf"] == first
    assert b["frame"] == state.created_at[first] < len(load_sequence(root)) - 1
    np.testing.assert_array_equal(b["depth_of"], b["now"])
    rows = pd.read_csv(r.folder / "keyframes.csv")
    before = rows[rows["kf_id"] < first]["steps"].sum()
    assert b["steps"] == before
    assert 0 < before < rows["steps"].sum()
    # the front end went on in the bridged unit: segment 1's later keyframes lie s times as far from its first
    # keyframe as in the front end run alone (tracking, seeds and their promotion all in the new unit)
    s = json.loads((r.folder / "manifest.json").read_text())["bridges"][0]["scale"]
    assert abs(s - 1) > 0.1

    def spread(vo) -> dict[int, float]:
        seg1 = [k for k in vo.keyframes if k.segment == 1]
        return {k.frame_index: float(np.linalg.norm(k.pose[:3, 3] - seg1[0].pose[:3, 3]))
                for k in seg1 if k.frame_index > b["frame"]}

    alone, _ = run_frontend(load_sequence(root), _cfg(tmp))
    ours, theirs = spread(loop.source.result()), spread(alone)
    common = sorted(set(ours) & set(theirs))
    assert len(common) >= 3
    ratio = sum(ours[f] for f in common) / sum(theirs[f] for f in common)
    assert ratio == pytest.approx(s, rel=0.1), (ratio, s)


def test_online_scores_are_the_model_of_their_time(causal):
    r, _, loop = causal
    table = pd.read_csv(r.folder / "per_frame.csv")
    created = np.array(loop.state.created_at)
    for f, k in zip(table["frame"], table["online_kf"]):
        before = np.flatnonzero(created < f)  # a keyframe's own frame: scored before the model trains on it
        assert k == (before.max() if len(before) else -1), (f, k)


def test_a_cached_run_is_the_uncached_run(lost, causal):
    """The first run stored its front end's journal (the front end on its own, to the end, with resumption
    points); the second replays it up to its first change (a global BA), resumes the front end from a
    resumption point, re-runs the frames after it checking every event, and goes on live."""
    tmp, root = lost
    r, _, _ = causal
    seq = load_sequence(root)
    entry = load_entry(cache_path(tmp / "a" / "_cache" / "vo", seq, _cfg(tmp)))
    assert entry is not None
    assert entry.complete
    assert entry.checkpoints
    first = tmp / "first"
    shutil.copytree(r.folder, first)
    again = run_sequence(root, _cfg(tmp), out=tmp / "a", command=["test"], force=True)
    a, b = r.summary.flat(), again.summary.flat()
    assert a["vo.frames_from_cache"] == 0
    assert min(entry.checkpoints) < b["vo.frames_from_cache"] < len(seq)
    skip = ("timing.", "vo.from_cache", "vo.frames_from_cache", "notes.timing")
    differ = [k for k in a if not k.startswith(skip) and a[k] != b.get(k)
              and not (isinstance(a[k], float) and np.isnan(a[k]) and np.isnan(b[k]))]
    assert not differ, differ
    for name in ("traj_kf.txt", "traj_all.txt", "traj_kf_bridged.txt", "traj_kf_ba.txt", "per_frame.csv"):
        assert (first / name).read_bytes() == (again.folder / name).read_bytes(), name
    ka, kb = pd.read_csv(first / "keyframes.csv"), pd.read_csv(again.folder / "keyframes.csv")
    timing = [c for c in ka.columns if c in ("ms",) or c.endswith("_s") or c.startswith("rt_")]
    pd.testing.assert_frame_equal(ka.drop(columns=timing), kb.drop(columns=timing))


def test_the_bridged_credit_is_the_front_end_alone_and_its_own_bridges(lost, causal):
    """Algorithm 1's global BA moved poses of the first segment before the bridge; Table 4's "bridged" column is
    the front end alone, joined by a bridge planned on its own map of then with the weights of then: its first
    segment is the front end's, untouched by the BA, and its bridge is the one planned there."""
    from mutualslam_cli.adapt.inputs import keyframe_images
    from mutualslam_cli.backend.bridges import plan_bridge
    from mutualslam_cli.online.labels import depth_predictor
    from mutualslam_cli.vo.source import FrontEndSource

    tmp, root = lost
    r, _, loop = causal
    state, cfg, seq = loop.state, _cfg(tmp), load_sequence(root)
    first = next(k for k in range(state.n_keyframes) if state.segment(k) == 1)
    rows = pd.read_csv(r.folder / "keyframes.csv").set_index("kf_id")
    assert rows.loc[:first - 1, "ba_s"].notna().any()  # a BA before the bridge …
    alone, _ = run_frontend(seq, cfg)
    seg0 = [k for k in alone.keyframes if k.segment == 0]
    moved = [np.abs(state.pose(k.id) - k.pose).max() for k in seg0 if k.id < state.n_keyframes]
    assert max(moved) > 1e-4  # … moved the live map's first segment
    kf_alone = np.loadtxt(r.folder / "traj_kf.txt")
    kf_bridged = np.loadtxt(r.folder / "traj_kf_bridged.txt")
    n0 = len(seg0)
    np.testing.assert_array_equal(kf_bridged[:n0], kf_alone[:n0])  # the bridged column does not see it
    assert not np.allclose(kf_bridged[n0:, 1:4], kf_alone[n0:, 1:4])  # its second segment was moved
    (credit,) = json.loads((r.folder / "manifest.json").read_text())["bridges_credit"]
    # the same bridge planned again: the front end alone at the segment's first keyframe, the weights of then
    src = FrontEndSource(seq, cfg)
    kf, at = next((kfs[0], f) for f, kfs in ((f, [k for k in ks if src.state.segment(k) == 1])
                                             for f, ks in src.timeline()) if kfs)
    assert src.state.map.kf_frame[kf] == credit["frame"]
    net = loop.net
    net.load_state_dict(loop.weights_at.kept[at])
    load = keyframe_images(seq, lambda k: src.state.map.kf_frame[k], cfg.net.width, cfg.net.height)
    b = plan_bridge(src.state.snapshot(seq.frames, covisibility=False), kf, depth_predictor(net, load, False),
                    seq.load_gray, seq.intrinsics)
    src.close()
    assert b.scale == pytest.approx(credit["scale"], rel=1e-9)
    assert credit["R"] == b.R
    assert b.t == credit["t"]

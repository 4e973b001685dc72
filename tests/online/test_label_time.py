"""Tests that would catch a leak from the future (DESIGN §5): L_val reads the labels of its time; the same
keyframe's labels read at t and at t + k are the two maps' depths; each online score comes from the weights
of its frame's time (which weights, not only which keyframe the bookkeeping names)."""

from __future__ import annotations

import numpy as np
import torch
from test_online_loop import H, ScriptedSource, TinyNet, W, _cfg, _map_at, oracle  # noqa: F401

from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.geometry import pinhole
from mutualslam_cli.map.journal import Event
from mutualslam_cli.map.state import MapState
from mutualslam_cli.online.labels import MapLabels
from mutualslam_cli.online.loop import OnlineLoop
from mutualslam_cli.stages.context import RunContext


def _moved_script(seq, events):
    """The oracle's events, with the points keyframe 2 (created at frame 4) hosts moved to 1.5× their depth at
    frame 5: keyframe 2's labels at frame 4 and at frame 8 differ."""
    before = _map_at(seq, events, 4)
    hosted = np.array(sorted(p for p in before.map.kf_points[2] if before.map.host[p] == 2), np.int64)
    rho = np.array([before.map.rho[p] for p in hosted])
    change = [Event("depth", 5, {"pids": hosted, "rho": rho / 1.5}), Event("refresh", 5, {"pids": hosted})]
    return sorted(events + change, key=lambda e: e.frame)


def fingerprint(net: torch.nn.Module) -> float:
    return float(sum(p.detach().double().sum() for p in net.parameters()))


def test_map_labels_read_at_t_and_at_t_plus_k_are_the_two_maps(oracle):  # noqa: F811
    seq, _vo, events = oracle
    script = _moved_script(seq, events)
    state = MapState(pinhole(seq.intrinsics), len(seq))
    labels = MapLabels(state, W, H)
    read = {}
    for frame in range(len(seq)):
        for e in (e for e in script if e.frame == frame):
            state.apply(e)
        if frame in (4, 8):
            read[frame] = labels.sparse(2)[1].numpy()
    at4, at8 = (_map_at(seq, script, f).sparse_depth(2)[1] for f in (4, 8))
    np.testing.assert_allclose(read[4], at4, rtol=1e-6)
    np.testing.assert_allclose(read[8], at8, rtol=1e-6)
    n = min(len(at4), len(at8))
    assert not np.allclose(at4[:n], at8[:n])  # the two maps differ: a reader of either one is caught


def test_l_val_uses_the_labels_of_its_time(oracle, monkeypatch, tmp_path):  # noqa: F811
    """Validation keyframes 2 (frame 4) and 4 (frame 8), L_val over every validation keyframe: keyframe 2's
    sparse depths in L_val at frame 4 are the map of frame 4, at frame 8 the map of frame 8 (moved at 5)."""
    seq, _vo, events = oracle
    script = _moved_script(seq, events)
    source = ScriptedSource(seq, script)
    seen: list[tuple[int, list[int], list[np.ndarray]]] = []  # (frame, ids, each val_fn call's depths)
    orig = OnlineAdapter.per_keyframe_val_loss

    def spy(self, ids=None, chunk=4):
        calls: list[np.ndarray] = []
        val_fn = self.val_fn

        def watched(depth, uv, d, mask):
            calls.append(d[0].numpy().copy())
            return val_fn(depth, uv, d, mask)

        self.val_fn = watched
        try:
            out = orig(self, ids, chunk)
        finally:
            self.val_fn = val_fn
        seen.append((source.frame, [k for k in out if not np.isnan(out[k])], calls))
        return out

    monkeypatch.setattr(OnlineAdapter, "per_keyframe_val_loss", spy)
    torch.manual_seed(0)
    loop = OnlineLoop(RunContext(seq, _cfg(scheme="replay", validate_every=2), tmp_path, tmp_path), source,
                      TinyNet(), False)
    loop.run_loop()
    by_frame = {f: dict(zip(ids, calls)) for f, ids, calls in seen}
    assert 2 in by_frame[4]
    assert 2 in by_frame[8]
    for f in (4, 8):
        for k, d in by_frame[f].items():
            np.testing.assert_allclose(d, source.labels_at[f][k], rtol=1e-6)
    n = min(len(by_frame[4][2]), len(by_frame[8][2]))
    assert not np.allclose(by_frame[4][2][:n], by_frame[8][2][:n])


def test_each_online_score_comes_from_the_weights_of_its_time(oracle, monkeypatch, tmp_path):  # noqa: F811
    """Fixed schedule: a frame after keyframe k's frame, up to keyframe k+1's own frame, is scored with the weights
    right after k's training — the weights themselves, compared by a fingerprint taken when each keyframe's
    training ended. A keyframe's own frame is scored before the model trains on it (until 2026-12 it was scored
    after: this test failed on that rule at every keyframe's frame)."""
    seq, _vo, events = oracle

    class Scores:
        def __init__(self) -> None:
            self.seen: dict[int, float] = {}
            self.seconds = 0.0

        def score_until(self, net, frame_index, kf) -> None:
            for f in range(len(self.seen), min(frame_index, len(seq))):
                self.seen[f] = fingerprint(net)

    torch.manual_seed(0)
    source = ScriptedSource(seq, events)
    loop = OnlineLoop(RunContext(seq, _cfg(steps_per_keyframe=2), tmp_path, tmp_path), source, TinyNet(), False,
                      scorer=Scores())
    after: dict[int, float] = {-1: fingerprint(loop.net)}
    train = loop.adapter.train_pending

    def watched(steps):
        info = train(steps)
        if info is not None:
            after[info.kf_id] = fingerprint(loop.net)
        return info

    monkeypatch.setattr(loop.adapter, "train_pending", watched)
    loop.run_loop()
    loop.scorer.score_until(loop.net, len(seq), -2)
    created = np.array(loop.state.created_at)
    assert len(set(after.values())) >= 4  # the weights moved keyframe after keyframe
    for f in range(len(seq)):
        k = int(np.flatnonzero(created < f).max()) if (created < f).any() else -1  # strictly before f
        k = max((j for j in after if j <= k), default=-1)  # keyframes without a batch leave the weights as they were
        assert loop.scorer.seen[f] == after[k], f
    assert set(created) & set(range(len(seq)))  # the keyframes' own frames are among those checked

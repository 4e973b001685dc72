"""Algorithm 1 over the front end's events, on one clock (stages/adaptation.py): every label a training step
reads is the map as it stood at that step, never a later one (DESIGN §5)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from synth import make_tum_dir

from mutualslam_cli.adapt import losses
from mutualslam_cli.backend.ba.global_ba import GlobalBAResult
from mutualslam_cli.config import RunConfig, VOConfig, with_overrides
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import pinhole
from mutualslam_cli.map.journal import Event
from mutualslam_cli.map.refinement import MapRefinement, apply_refinement
from mutualslam_cli.map.state import MapState, events_from_result
from mutualslam_cli.online.loop import OnlineLoop
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.vo.depth_oracle import run_oracle

W, H = 96, 64


class TinyNet(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.c = torch.nn.Conv2d(3, 1, 3, padding=1)

    def predict(self, x):
        return 1.0 / (0.1 + torch.sigmoid(self.c(x)))


class ScriptedSource:
    """A front end played from a script: ``events`` in frame order into :attr:`state`; changes from the
    network's side go to the state (no live front end). ``hindsight``: every event applied before the loop."""

    def __init__(self, seq, events: list[Event], hindsight: bool = False) -> None:
        self.state = MapState(pinhole(seq.intrinsics), len(seq))
        self.n, self.events, self.hindsight = len(seq), events, hindsight
        self.frame, self.refined = -1, []
        self.labels_at: dict[int, dict[int, np.ndarray]] = {}  # frame → keyframe → sparse depths then

    def timeline(self):
        if self.hindsight:
            for e in self.events:
                self.state.apply(e)
        seen = 0
        for i in range(self.n):
            if not self.hindsight:
                for e in (e for e in self.events if e.frame == i):
                    self.state.apply(e)
            self.frame = i
            self.labels_at[i] = {k: self.state.sparse_depth(k)[1] for k in range(self.state.n_keyframes)}
            new = [k for k in range(seen, self.state.n_keyframes) if self.state.created_at[k] <= i]
            seen += len(new)
            yield i, new

    def settle(self) -> None:
        pass

    def transform_segment(self, segment, S, onto) -> None:
        self.state.transform_segment(segment, S, onto)

    def refine(self, r: MapRefinement) -> None:
        self.refined.append((self.frame, r))
        apply_refinement(self.state, r)


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    """12 rendered frames; GT poses and sparse GT depth, a keyframe every 2 frames (created at frames 0, 2, …, 10)."""
    seq = load_sequence(make_tum_dir(tmp_path_factory.mktemp("loop"), n=12, width=W, height=H))
    vo = run_oracle(seq, VOConfig(mode="gt-depth", gt_kf_every=2, gt_max_points=40))
    return seq, vo, events_from_result(vo, len(seq))


def _cfg(**adapt) -> RunConfig:
    return with_overrides(RunConfig(), threads=1, net={"width": W, "height": H, "fast": "off"},
                          adapt={"scheme": "recent", "steps_per_keyframe": 1, "validate_every": 100, **adapt},
                          eval={"online": False})


def _spy(monkeypatch) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each L_train call's sparse labels ``(d (B, M), mask (B, M))``."""
    calls, orig = [], losses.train_loss

    def spy(depth, target, sources, K, T, uv, d, mask, *a):
        calls.append((d.clone(), mask.clone()))
        return orig(depth, target, sources, K, T, uv, d, mask, *a)

    monkeypatch.setattr(losses, "train_loss", spy)
    return calls


def _run(seq, source, cfg, tmp_path, ba=None) -> OnlineLoop:
    torch.manual_seed(0)
    loop = OnlineLoop(RunContext(seq, cfg, tmp_path, tmp_path), source, TinyNet(), False, ba)
    loop.run_loop()
    return loop


def _labels(calls, loop) -> dict[tuple[int, int], np.ndarray]:
    """``(trained keyframe, keyframe in its batch) → the sparse depths it trained on``."""
    trained = [r.to_row() for r in loop.rows if r.trained]
    assert len(trained) == len(calls)
    out = {}
    for r, (d, mask) in zip(trained, calls):
        for b, k in enumerate(int(x) for x in str(r["batch"]).split()):
            out[(int(r["kf_id"]), k)] = d[b][mask[b]].numpy()
    return out


def _map_at(seq, events, frame) -> MapState:
    st = MapState(pinhole(seq.intrinsics), len(seq))
    for e in events:
        if e.frame <= frame:
            st.apply(e)
    return st


@pytest.mark.parametrize("hindsight", [False, True])
def test_a_step_trains_on_the_map_as_it_stood(oracle, monkeypatch, tmp_path, hindsight):
    """Keyframe 2 (created at frame 4) is trained on at once; at frame 5 the points it hosts move to 1.5×
    their depth; keyframe 3's batch (3, 2) replays it with the map of frame 6, the new depths in it. Hindsight
    labels are the final map's at both — labels from the future, which the causal loop never reads."""
    seq, _vo, events = oracle
    before = _map_at(seq, events, 4)
    hosted = np.array(sorted(p for p in before.map.kf_points[2] if before.map.host[p] == 2), np.int64)
    assert len(hosted) >= 10
    rho = np.array([before.map.rho[p] for p in hosted])
    change = [Event("depth", 5, {"pids": hosted, "rho": rho / 1.5}), Event("refresh", 5, {"pids": hosted})]
    script = sorted(events + change, key=lambda e: e.frame)  # stable: frame 5's own events first
    at4, at6, final = (_map_at(seq, script, f).sparse_depth(2)[1] for f in (4, 6, len(seq)))
    assert not np.allclose(at6, _map_at(seq, events, 6).sparse_depth(2)[1])  # the change is in the labels
    calls = _spy(monkeypatch)
    loop = _run(seq, ScriptedSource(seq, script, hindsight), _cfg(), tmp_path)
    got = _labels(calls, loop)
    np.testing.assert_allclose(got[(2, 2)], final if hindsight else at4, rtol=1e-6)
    np.testing.assert_allclose(got[(3, 2)], final if hindsight else at6, rtol=1e-6)
    assert len(at4) < len(final)  # later keyframes add what keyframe 2 sees: hindsight knows them early


class FakeBA:
    """``run_ba`` of a BA stage that 'refines': depths of points hosted ≤ the request ×1.1, poses moved (the
    :class:`~mutualslam_cli.backend.refine.MapBA` face: ``frames``, ``window``, ``run_ba``)."""

    def __init__(self, frames) -> None:
        self.frames, self.window = frames, 0
        self.calls = []

    def run_ba(self, v, kf_id, depth_of, val_loss, bridges=None):
        assert depth_of(kf_id).shape == (H, W)
        assert set(val_loss) == set(range(kf_id + 1))
        self.calls.append(kf_id)
        pts = v.points
        inv = np.where(pts.host <= kf_id, pts.inv_depth / 1.1, pts.inv_depth)
        kfs = []
        for k in v.keyframes:
            pose = k.pose.copy()
            pose[0, 3] += 0.01 * (k.id > 0)
            kfs.append(dataclasses.replace(k, pose=pose))
        out = dataclasses.replace(v, keyframes=kfs, points=dataclasses.replace(pts, inv_depth=inv))
        return GlobalBAResult(out, np.ones(len(pts), bool), np.zeros(len(pts), bool))


def test_a_global_ba_reaches_later_batches_and_not_earlier_ones(oracle, monkeypatch, tmp_path):
    seq, _vo, events = oracle
    calls = _spy(monkeypatch)
    cfg = _cfg(validate_every=3, patience=1, tau_val=1e9)  # one request: validation keyframe t = 3
    source, ba = ScriptedSource(seq, events), FakeBA(seq.frames)
    loop = _run(seq, source, cfg, tmp_path, ba)
    assert ba.calls == [3]
    assert [r.kf_id for r in loop.rows if r.run_global_ba] == [3]
    assert "ba_s" in loop.rows[3].seconds
    assert [f for f, _ in source.refined] == [6]  # at keyframe 3's creation frame
    got = _labels(calls, loop)
    created = source.state.created_at
    for (trained, k), d in got.items():  # every label: the map at the trained keyframe's frame, BA included
        np.testing.assert_allclose(d, source.labels_at[created[trained]][k], rtol=1e-6)
    pre, post = source.labels_at[4][2], source.labels_at[8][2]
    assert not np.allclose(post[:len(pre)], pre)  # the BA changed keyframe 2's labels …
    np.testing.assert_allclose(got[(2, 2)], pre, rtol=1e-6)  # … after keyframe 2 trained on the old ones
    assert any(k[0] > 3 and k[1] <= 3 for k in got)  # a batch after the BA replayed a refined keyframe


def test_a_segment_no_bridge_joins_is_never_trained_on(oracle, monkeypatch, tmp_path):
    """Keyframes from frame 6 on start a second segment; its bridge is refused (ratios too spread): the
    network goes on in its first unit only — the second segment's keyframes are neither trained on nor
    replayed nor validated, and the run counts them."""
    from mutualslam_cli.backend.bridges import Bridge
    from mutualslam_cli.online import loop as online_loop

    seq, _vo, events = oracle
    script = []
    for e in events:  # the same stream, with a new tracking segment from frame 6
        if e.kind in ("keyframe", "frame") and e.frame >= 6:
            e = Event(e.kind, e.frame, {**e.data, "segment": 1})
        script.append(e)
    refused = []

    def refuse(snap, kf, depth_of, *a):
        refused.append(kf)
        return Bridge(1, 0, 6, 0.6, -1, float("nan"), 1.0, 1.0, 40, 40, 0.0, "none", refused="spread too wide")

    monkeypatch.setattr(online_loop, "plan_bridge", refuse)
    calls = _spy(monkeypatch)
    loop = _run(seq, ScriptedSource(seq, script), _cfg(scheme="replay", validate_every=2), tmp_path)
    second = [k for k in range(loop.state.n_keyframes) if loop.state.segment(k) == 1]
    assert refused == [second[0]]
    assert loop.refused
    assert not loop.bridges
    assert loop.other_unit == second
    assert second
    assert {r.kf_id for r in loop.rows}.isdisjoint(second)
    got = _labels(calls, loop)
    assert got
    assert all(k not in second for _, k in got)
    assert set(loop.adapter.buffer.all_ids).isdisjoint(second)  # nor are they stored for replay or L_val

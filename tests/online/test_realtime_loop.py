"""``adapt.schedule: realtime`` through :class:`~mutualslam_cli.online.loop.OnlineLoop`, with a clock
that charges fixed costs: every effect takes hold when its charged work ends — a step's weights for the front
end and the online scores, a global BA's refinement for the front end and the labels — checked frame by frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_online_loop import FakeBA, ScriptedSource, TinyNet, _cfg, _spy, oracle  # noqa: F401

from mutualslam_cli.config import with_overrides
from mutualslam_cli.online.loop import OnlineLoop
from mutualslam_cli.online.realtime import RealtimeClock
from mutualslam_cli.stages.context import RunContext


def batch_labels(calls, loop) -> dict[tuple[int, int], np.ndarray]:
    """``(trained keyframe, keyframe in its batch) → the sparse depths of its steps`` (one batch, many steps)."""
    out, i = {}, 0
    for r in (r.to_row() for r in loop.rows if r.trained):
        group = calls[i:i + int(r["steps"])]
        i += len(group)
        for d, mask in group[1:]:  # every step of a keyframe trains on the one batch assembled at its tick
            assert torch.equal(d, group[0][0])
            assert torch.equal(mask, group[0][1])
        for b, k in enumerate(int(x) for x in str(r["batch"]).split()):
            out[(int(r["kf_id"]), k)] = group[0][0][b][group[0][1][b]].numpy()
    assert i == len(calls)
    return out


def fingerprint(net: torch.nn.Module) -> float:
    return float(sum(p.detach().double().sum() for p in net.parameters()))


class WatchedSource(ScriptedSource):
    """A scripted front end that notes, as it takes each frame, the weights the network has then."""

    def __init__(self, *a, **k) -> None:
        super().__init__(*a, **k)
        self.net: torch.nn.Module | None = None
        self.weights_at: dict[int, float] = {}
        self.after_refine: dict[int, np.ndarray] = {}

    def refine(self, r) -> None:
        super().refine(r)
        self.after_refine = {k: self.state.sparse_depth(k)[1] for k in range(self.state.n_keyframes)}

    def timeline(self):
        for i, kfs in super().timeline():
            self.weights_at[i] = fingerprint(self.net)
            yield i, kfs


class Scores:
    """An online scorer that notes which weights scored each frame."""

    def __init__(self) -> None:
        self.seen: dict[int, float] = {}
        self.seconds = 0.0

    def score_until(self, net, frame_index, kf) -> None:
        for f in range(len(self.seen), frame_index):
            self.seen[f] = fingerprint(net)


def test_every_effect_takes_hold_when_its_charged_work_ends(oracle, monkeypatch, tmp_path):  # noqa: F811
    """Frames dt apart, a keyframe every 2 frames; a tick costs 0.1 dt, a step 0.5 dt (at most 3), the global BA
    Algorithm 1 requests at keyframe 3 (frame 6) 2.5 dt. The loop's timeline, in dt:
    kf 0 has nothing to train; kf 1 and 2 train 3 steps each from 0.1 after arrival; kf 3 validates at 6–6.1, its
    BA runs 6.1–8.6; kf 4 arrives at 8 while the loop is busy and starts at 8.6 — with the refined map, which reaches
    the front end then, before frame 9 — and takes steps 8.7–9.2, 9.2–9.7 and 9.7–10.2 (the last started before
    kf 5 arrives at 10); kf 5 starts at 10.2 and trains until the last frame (11): steps 10.3–10.8 and 10.8–11.3."""
    seq, _vo, events = oracle
    dt = 1000.0 * (seq.seconds(1) - seq.seconds(0))
    times = [seq.seconds(i) * 1000.0 for i in range(len(seq))]
    assert np.allclose(np.diff(times), dt, atol=1e-2)  # 30 frames/s, stamps rounded to the µs
    t0 = times[0]
    calls = _spy(monkeypatch)
    cfg = with_overrides(_cfg(validate_every=3, patience=1, tau_val=1e9),
                         adapt={"schedule": "realtime", "step_cost_ms": 0.5 * dt, "max_steps": 3})
    source, ba = WatchedSource(seq, events), FakeBA(seq.frames)
    torch.manual_seed(0)
    reported: list[tuple[int, float]] = []  # (keyframe, the clock when reported)
    run = RunContext(seq, cfg, tmp_path, tmp_path,
                     progress=lambda stage, i: reported.append((i["done"] - 1, loop.clock.now_ms))
                     if stage == "adapt" else None)
    loop = OnlineLoop(run, source, TinyNet(), False, ba, scorer=Scores())
    source.net = loop.net
    loop.clock = RealtimeClock(0.5 * dt, 3, fixed_ms={"tick": 0.1 * dt, "ba": 2.5 * dt, "consolidate": 0.0,
                                                             "merge": 0.0, "loop": 0.0, "bridge": 0.0})
    ends: list[tuple[float, float]] = [(-np.inf, fingerprint(loop.net))]  # (step end ms, weights after it)
    step = loop.adapter.step_pending

    def timed_step():
        out = step()
        ends.append((loop.clock.now_ms + 0.5 * dt, fingerprint(loop.net)))  # the clock books it just after
        return out

    monkeypatch.setattr(loop.adapter, "step_pending", timed_step)
    loop.run_loop()
    loop.scorer.score_until(loop.net, len(seq), loop.trained_kf)

    # the clock, keyframe by keyframe (dt after the first frame)
    rows = {r.kf_id: r.to_row() for r in loop.rows}
    want = {0: (0.0, 0.1, 0), 1: (2.0, 3.6, 3), 2: (4.0, 5.6, 3), 3: (6.0, 8.6, 0), 4: (8.6, 10.2, 3),
            5: (10.2, 11.3, 2)}  # keyframe: (work starts, ends, steps)
    for kf, (start, end, steps) in want.items():
        r = rows[kf]
        assert (r["rt_start_ms"] - t0) / dt == pytest.approx(start, abs=1e-3), kf
        assert (r["rt_end_ms"] - t0) / dt == pytest.approx(end, abs=1e-3), kf
        assert int(r.get("steps") or 0) == steps, kf
    # the adaptation's progress: each keyframe once, in order, when its work ended (the realtime loop reported none)
    assert [kf for kf, _ in reported] == list(range(6))
    for kf, now in reported[:-1]:  # the last one's training runs on to the last frame
        assert now >= rows[kf]["rt_end_ms"], kf
    assert ba.calls == [3]
    assert rows[3]["run_global_ba"]
    # the BA's refinement: made on the map of frame 6, in the front end from frame 9 on (it ended at 8.6)
    assert [f for f, _ in source.refined] == [8]
    pre, post = source.labels_at[8][2], source.labels_at[9][2]
    assert not np.allclose(pre[:len(post)], post[:len(pre)])
    got = batch_labels(calls, loop)
    assert any(k <= 3 for trained, k in got if trained == 4)  # kf 4's batch holds a refined keyframe
    for (trained, k), d in got.items():  # each batch: the map when its work started (kf 4: after the BA)
        frame = {1: 2, 2: 4, 4: 8, 5: 10}[trained]
        want_d = source.labels_at[frame][k] if trained != 4 else source.after_refine[k]
        np.testing.assert_allclose(d, want_d, rtol=1e-6)
    # the weights: frame f sees the last step that ended by its time, in the front end and in its online score
    for f in range(len(seq)):
        visible = [w for e, w in ends if e <= times[f]][-1]
        assert source.weights_at[f] == pytest.approx(visible, abs=0), f
        assert loop.scorer.seen[f] == pytest.approx(visible, abs=0), f
    assert len(ends) - 1 == 3 + 3 + 3 + 2

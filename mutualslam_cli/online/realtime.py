"""``adapt.schedule: realtime``: Algorithm 1's loop on the sequence's clock (DESIGN §10).

The paper's loop runs beside the SLAM thread: a keyframe arrives at its frame's time, and the loop
works on it — its tick (the keyframe image's decode, L_val on a validation keyframe, the batch of a
training one), the bridge, merge, global BA or loop closure it triggers, the optimiser steps, the
regulariser's consolidation (EWC's Fisher, MAS's importance) — then takes the next keyframe.
:class:`RealtimeClock` keeps that loop's time:

- keyframe k's work starts at ``max(its arrival, when the loop became free)``;
- every piece of work is charged: steps at ``step_cost_ms`` each, everything else at its wall time
  on this machine, converted to the modelled machine by ``step_cost_ms`` / the median step measured
  here (``step_cost_ms: measured``: this machine, everything at its wall time);
- k is trained on until k+1 arrives: the steps that *start* before then (a step is not interrupted),
  at most ``max_steps``; none when the loop is still busy at k+1's arrival (it falls behind, and the
  stale keyframe is only stored, as the paper's "get latest keyframe" loop would skip it); the last
  keyframe until the sequence's last frame.

**Every effect takes hold when its charged work ends** (:class:`RealtimeSchedule`): a step's weights from
the frame at or after its end — for the front end's asks (``vo.depth_seeds``), the online scores and
the loop's own later work alike (a frame is scored by the weights of the last step that ended before
it); a bridge's, merge's, BA's or loop's change of the map reaches the live front end and every later
label at the first frame at or after the end of the work that made it (the work runs on a copy of the
map as it stood when it started, :class:`DeferredMap`; keyframes the front end made meanwhile follow
their predecessor's correction). A keyframe's labels are the map as it stood when its work started.
The front end itself runs on its own thread (the paper's SLAM thread) and is not charged: it keeps up
on this CPU (README "Realtime": frames/s against the sequence's rate). Wall times make a realtime run
follow the machine's load: it is not bit-reproducible; ``keyframes.csv`` records each keyframe's
steps and ``rt_start_ms`` / ``rt_end_ms``.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.backend.refine import MapTarget
from mutualslam_cli.map.refinement import MapRefinement, apply_refinement
from mutualslam_cli.map.sim3 import Sim3
from mutualslam_cli.map.state import MapState
from mutualslam_cli.online.credit import WeightsAt
from mutualslam_cli.online.rows import KeyframeRow
from mutualslam_cli.online.run import OnlineRun


class RealtimeClock:
    """The adaptation loop's time, in milliseconds of sequence time (module docstring).

    Args:
        step_cost_ms: cost of one optimiser step on the modelled machine; ``None``: measured here.
        max_steps: cap on one keyframe's steps.
        fixed_ms: a cost per kind of work (``tick``, ``bridge``, ``merge``, ``ba``, ``loop``, ``consolidate``)
            charged instead of its wall time (tests: a clock that does not follow the machine).

    Attributes:
        now_ms: where the loop's work on the current keyframe has got to.
        free_ms: when the loop finished the previous keyframe's work.
    """

    def __init__(self, step_cost_ms: float | None, max_steps: int, fixed_ms: Mapping[str, float] | None = None) -> None:
        self.step_cost_ms, self.max_steps = step_cost_ms, max_steps
        self.fixed_ms = dict(fixed_ms or {})
        self.now_ms = self.free_ms = -math.inf
        self.measured_steps: list[float] = []

    def scale(self) -> float:
        """Modelled ms per ms of wall time here (1 when measured, or before any step was timed)."""
        if self.step_cost_ms is None or not self.measured_steps:  # measured, or nothing timed yet
            return 1.0
        return float(self.step_cost_ms) / float(np.median(self.measured_steps))

    def step_ms(self) -> float:
        """What one step costs on the clock (measured: the median step so far; 0 before the first)."""
        if self.step_cost_ms is not None:  # not measured
            return float(self.step_cost_ms)
        return float(np.median(self.measured_steps)) if self.measured_steps else 0.0

    def arrive(self, t_ms: float) -> float:
        """A keyframe arrives at ``t_ms``: its work starts now or when the loop is free; returns that start."""
        self.now_ms = max(self.free_ms, t_ms)
        return self.now_ms

    def charge(self, wall_ms: float, kind: str = "") -> None:
        """Work of ``kind`` that took ``wall_ms`` here (a tick, a bridge, a BA, a consolidation)."""
        self.now_ms += self.fixed_ms[kind] if kind in self.fixed_ms else self.scale() * wall_ms

    def steps_until(self, t_next_ms: float) -> int:
        """Steps that start before ``t_next_ms`` (the next keyframe's arrival), at most ``max_steps``."""
        if self.now_ms >= t_next_ms:
            return 0
        cost = self.step_ms()
        if cost <= 0:  # nothing measured yet: one step, to measure it
            return min(1, self.max_steps)
        return int(min(self.max_steps, math.ceil((t_next_ms - self.now_ms) / cost)))

    def stepped(self, wall_ms: list[float]) -> None:
        """The steps just taken (their wall times here) go on the clock."""
        self.measured_steps.extend(wall_ms)
        self.now_ms += sum(wall_ms) if self.step_cost_ms is None else len(wall_ms) * float(self.step_cost_ms)

    def done(self) -> None:
        """The current keyframe's work is over."""
        self.free_ms = self.now_ms


class DeferredMap:
    """The map changes of the loop's work, held until the work ends on the clock (module docstring).

    Stands where the loop's work expects the front end's source (``state``, ``settle``, ``transform_segment``,
    ``refine``): a change is made on a copy of the map as it stood when the work started — so the rest of the
    same work (a loop's BA after its pose graph) sees it — and recorded; :meth:`finish` dates the work's changes
    at its end and :meth:`apply_due` hands them to the live source once the sequence's time reaches it.
    """

    def __init__(self, source: MapTarget) -> None:
        self.source = source
        self._copy: MapState | None = None
        self._last_kf = -1  # the newest keyframe when the copy was made
        self._ops: list[tuple[str, tuple]] = []
        self.due: list[tuple[float, int, list[tuple[str, tuple]]]] = []  # (time, newest keyframe, changes)
        self.applied: list[tuple[int, float, str]] = []  # (source frame when applied, due time, kind)

    @property
    def state(self) -> MapState:
        return self._copy if self._copy is not None else self.source.state

    def settle(self) -> None:
        if self._copy is None:  # the front end's own windowed BA, in the live map
            self.source.settle()

    def _shadow(self) -> MapState:
        if self._copy is None:
            self._copy = self.source.state.fork()
            self._last_kf = self._copy.n_keyframes - 1
        return self._copy

    def transform_segment(self, segment: int, S: Sim3, onto: int) -> None:
        self._shadow().transform_segment(segment, S, onto)
        self._ops.append(("transform_segment", (segment, S, onto)))

    def refine(self, r: MapRefinement) -> None:
        apply_refinement(self._shadow(), r)
        self._ops.append(("refine", (r,)))

    def finish(self, end_ms: float) -> None:
        """The work that made the recorded changes ends at ``end_ms``; the copy is dropped."""
        if self._ops:
            self.due.append((end_ms, self._last_kf, self._ops))
        self._copy, self._ops = None, []

    def apply_due(self, t_ms: float) -> None:
        """Every change whose work ended by ``t_ms``, to the live source, in the order made."""
        while self.due and self.due[0][0] <= t_ms:
            end_ms, last_kf, ops = self.due.pop(0)
            for kind, args in ops:
                if kind == "refine":
                    self.source.refine(args[0].carried(self.source.state, last_kf))
                else:
                    self.source.transform_segment(*args)
                self.applied.append((int(getattr(self.source, "frame", -1)), end_ms, kind))


class Loop(Protocol):
    """What :class:`RealtimeSchedule` drives: :class:`~mutualslam_cli.online.loop.OnlineLoop`."""

    run: OnlineRun
    source: Any  # FrontEndSource, or a scripted one in tests
    state: MapState
    net: DepthNet
    adapter: OnlineAdapter | None
    clock: RealtimeClock | None
    writer: MapTarget
    row_of: dict[int, KeyframeRow]
    trained_kf: int
    weights_at: WeightsAt

    def keyframe_work(self, kf: int) -> None: ...

    def score_before(self, frame: int, kf: int) -> None: ...

    def row(self, kf: int) -> KeyframeRow: ...


class RealtimeSchedule:
    """Algorithm 1's loop on the sequence's clock over ``loop``'s front end (module docstring): called once a frame
    by the loop's skeleton (:meth:`~mutualslam_cli.online.loop.OnlineLoop.run_loop`).

    Between two frames the loop does the work that fits before the next one: the current keyframe's steps that
    end by then (each frame before a step's end is scored with the weights before it), the end of its training
    (consolidation) once the next keyframe arrived or ``max_steps`` were taken, and the next keyframes' work
    when it starts before then; the changes that work made reach the front end when it ends."""

    def __init__(self, loop: Loop) -> None:
        assert loop.clock is not None
        assert loop.adapter is not None
        self.loop, self.clock, self.adapter = loop, loop.clock, loop.adapter
        seq = loop.run.seq
        self.times = [seq.seconds(i) * 1000.0 for i in range(len(seq))]
        self.end_ms = self.times[-1]
        self.queue: deque[int] = deque()
        assert isinstance(loop.writer, DeferredMap)  # the realtime loop's map changes wait for their work's end
        self.writer: DeferredMap = loop.writer
        self.taken = 0  # steps the pending keyframe took
        self._done: list[int] = []  # keyframes whose work ended in this frame's window

    def __call__(self, frame: int, keyframes: list[int]) -> list[int]:
        """Frame ``frame`` came with its new ``keyframes``: the work that fits before the next frame; returns the
        keyframes whose work (steps and consolidation included) ended by then, in order."""
        self._done = []
        self.queue.extend(keyframes)
        until = self.times[frame + 1] if frame + 1 < len(self.times) else math.inf
        self._work(min(until, self.end_ms) if until != math.inf else math.inf)
        self.writer.apply_due(until)  # the front end takes the next frame with every change that ended by then
        return self._done

    def _arrival(self, kf: int) -> float:
        return self.times[self.loop.state.created_at[kf]]

    def _work(self, until: float) -> None:
        loop, clock, adapter, queue = self.loop, self.clock, self.adapter, self.queue
        while True:
            if adapter.pending is not None:
                kf = adapter.pending.kf_id
                next_arrival = self._arrival(queue[0]) if queue else math.inf
                if self.taken < clock.max_steps and clock.now_ms < min(next_arrival, self.end_ms):
                    cost = clock.step_ms()
                    if clock.now_ms + cost > until:  # it ends after the next frame: its weights are not seen there
                        return
                    loop.score_before(bisect.bisect_left(self.times, clock.now_ms + cost), loop.trained_kf)
                    n = len(adapter.step_ms)
                    adapter.step_pending()
                    clock.stepped(adapter.step_ms[n:])
                    loop.trained_kf = kf
                    self.taken += 1
                    continue
                if self.taken < clock.max_steps and not queue and clock.now_ms < self.end_ms:
                    return  # the next keyframe may still come: the training goes on
                n = len(adapter.consolidate_ms)
                info = adapter.end_pending()
                assert info is not None  # a batch was pending
                clock.charge(sum(adapter.consolidate_ms[n:]), "consolidate")
                row = loop.row_of[kf]
                row.took(info)
                row.steps, row.rt_end_ms = self.taken, clock.now_ms
                clock.done()
                self._done.append(kf)
                self.taken = 0
                continue
            if not queue:
                return
            start = max(clock.free_ms, self._arrival(queue[0]))
            if start >= until:  # its work starts after the next frame: the map of then
                return
            kf = queue.popleft()
            clock.arrive(self._arrival(kf))
            self.writer.apply_due(clock.now_ms)  # what ended before this work starts is in the map it reads
            loop.keyframe_work(kf)
            if adapter.pending is None:  # a validation keyframe, or nothing to train: its work is over
                loop.row(kf).rt_end_ms = clock.now_ms
                clock.done()
                self._done.append(kf)

"""``adapt.schedule: realtime``: Algorithm 1's loop on the sequence's clock (DESIGN §10).

The paper's loop runs beside the SLAM thread: a keyframe arrives at its frame's time, and the loop
works on it — its tick (L_val on a validation keyframe, the batch of a training one), the bridge or
the global BA it triggers, the optimiser steps, the regulariser's consolidation (EWC's Fisher, MAS's
importance) — then takes the next keyframe. :class:`RealtimeClock` keeps that loop's time:

- keyframe k's work starts at ``max(its arrival, when the loop became free)``;
- every piece of work is charged: steps at ``step_cost_ms`` each, everything else at its wall time
  on this machine, converted to the modelled machine by ``step_cost_ms`` / the median step measured
  here (``step_cost_ms: measured``: this machine, everything at its wall time);
- k is trained on until k+1 arrives: the steps that *start* before then (a step is not interrupted),
  at most ``max_steps``; none when the loop is still busy at k+1's arrival (it falls behind, and the
  stale keyframe is only stored, as the paper's "get latest keyframe" loop would skip it); the last
  keyframe until the sequence's last frame.

The steps of k are therefore known only when k+1 arrives: the loop assembles k's batch at k's
arrival (labels as they stand then) and runs its steps when k+1 arrives (the adapter's
``begin_keyframe`` / ``train_pending``). Wall times make a realtime run follow the machine's load:
it is not bit-reproducible; ``keyframes.csv`` records each keyframe's steps and charged time.
"""

from __future__ import annotations

import math

import numpy as np


class RealtimeClock:
    """The adaptation loop's time, in milliseconds of sequence time (module docstring).

    Args:
        step_cost_ms: cost of one optimiser step on the modelled machine; ``None``: measured here.
        max_steps: cap on one keyframe's steps.

    Attributes:
        now_ms: where the loop's work on the current keyframe has got to.
        free_ms: when the loop finished the previous keyframe's work.
    """

    def __init__(self, step_cost_ms: float | None, max_steps: int) -> None:
        self.step_cost_ms, self.max_steps = step_cost_ms, max_steps
        self.now_ms = self.free_ms = -math.inf
        self.measured_steps: list[float] = []

    @property
    def measured(self) -> bool:
        return self.step_cost_ms is None

    def scale(self) -> float:
        """Modelled ms per ms of wall time here (1 when measured, or before any step was timed)."""
        if self.measured or not self.measured_steps:
            return 1.0
        return float(self.step_cost_ms) / float(np.median(self.measured_steps))

    def step_ms(self) -> float:
        """What one step costs on the clock (measured: the median step so far; 0 before the first)."""
        if not self.measured:
            return float(self.step_cost_ms)
        return float(np.median(self.measured_steps)) if self.measured_steps else 0.0

    def arrive(self, t_ms: float) -> float:
        """A keyframe arrives at ``t_ms``: its work starts now or when the loop is free; returns that start."""
        self.now_ms = max(self.free_ms, t_ms)
        return self.now_ms

    def charge(self, wall_ms: float) -> None:
        """Work that took ``wall_ms`` here (a tick, a bridge, a BA, a consolidation)."""
        self.now_ms += self.scale() * wall_ms

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
        self.now_ms += sum(wall_ms) if self.measured else len(wall_ms) * float(self.step_cost_ms)

    def done(self) -> None:
        """The current keyframe's work is over."""
        self.free_ms = self.now_ms

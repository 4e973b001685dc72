"""What one keyframe did to the online adaptation (:class:`StepInfo`): the record
:class:`~mutualslam_cli.adapt.online.OnlineAdapter` returns for each tick of Algorithm 1 and keeps in its
``history``, from which a run's ``keyframes.csv`` is written (:mod:`~mutualslam_cli.stages.adaptation_summary`);
and what each optimiser step cost, beside the other work around it (:class:`StepLog`, a run's ``steps.csv``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class StepInfo:
    """What one keyframe did to the adaptation.

    Attributes:
        kf_id: keyframe id. t: its arrival index (Alg. 1's t).
        state: FSM mode after the tick (always ``"IDLE"`` in this synchronous loop).
        is_validation: validation keyframe (not trained on).
        trained: an optimiser step was taken.
        batch: keyframe ids of the training batch (newest first).
        sources: photometric sources of the arriving keyframe as its scheme chose them (``luo``:
            its stereo partners, empty when none qualified); empty for validation keyframes.
        loss: ``{"photo", "sparse", "smooth", "total", "penalty"}`` floats (empty if not trained).
        l_val: L_val on validation keyframes (None otherwise; NaN if no sparse points).
        steps: optimiser steps taken on this keyframe's batch.
        n_converged: Alg. 1's counter after the tick.
        run_global_ba: Alg. 1 requested global BA on this tick.
        ms: wall time of the tick, milliseconds.
        health: what the batch did to the network (:mod:`~mutualslam_cli.adapt.health`; empty if not trained).
    """

    kf_id: int
    t: int
    state: str
    is_validation: bool
    trained: bool
    batch: list[int] = field(default_factory=list)
    sources: list[int] = field(default_factory=list)
    loss: dict[str, float] = field(default_factory=dict)
    l_val: float | None = None
    steps: int = 0
    n_converged: int = 0
    run_global_ba: bool = False
    ms: float = 0.0
    health: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class StepTime:
    """One optimiser step of a run.

    Attributes:
        step: its index in the run (0-based). kf_id: the keyframe whose batch it trained on.
        ms: its wall time, milliseconds (forward, backward, regulariser, Adam).
        batch: images in the batch.
        after: the other work done since the step before it, in order (:data:`WORK`).
    """

    step: int
    kf_id: int
    ms: float
    batch: int
    after: tuple[str, ...] = ()


#: What else may run between two optimiser steps: the front end's frames, a keyframe's tick (its decode, L_val or
#: batch), the regulariser's consolidation (EWC's Fisher, MAS's importance), online scoring and the OpenVINO
#: predictor's weight refresh, a bridge, a merge, a culling + global BA, a loop closure.
WORK = ("frontend", "tick", "l_val", "consolidate", "score", "refresh", "bridge", "merge", "ba", "loop")


class StepLog:
    """Every optimiser step's time and what else ran since the step before it (``steps.csv``; the run's
    ``timing.step_ms.*``): where a slow step stands among the work around it."""

    def __init__(self) -> None:
        self.steps: list[StepTime] = []
        self._since: list[str] = []

    def mark(self, kind: str) -> None:
        """Work of ``kind`` (:data:`WORK`) has just been done."""
        if kind not in self._since:
            self._since.append(kind)

    def step(self, kf_id: int, ms: float, batch: int) -> None:
        """An optimiser step of ``ms`` milliseconds on keyframe ``kf_id``'s batch of ``batch`` images."""
        self.steps.append(StepTime(len(self.steps), kf_id, ms, batch, tuple(self._since)))
        self._since = []

    def rows(self) -> list[dict[str, str | int | float]]:
        """``steps.csv``: ``step, kf_id, ms, batch, after`` (the kinds of work joined by ``+``, empty for none)."""
        return [{"step": s.step, "kf_id": s.kf_id, "ms": s.ms, "batch": s.batch, "after": "+".join(s.after)}
                for s in self.steps]

    def stats(self) -> dict[str, float]:
        """``median``, ``p90``, ``p99``, ``max`` of the step times (ms) and ``sum_over_median``: the steps' sum over
        steps × median (1 when every step takes the median; a stall shows above it). Empty without a step."""
        if not self.steps:
            return {}
        ms = np.array([s.ms for s in self.steps])
        med = float(np.median(ms))
        return {"median": med, "p90": float(np.percentile(ms, 90)), "p99": float(np.percentile(ms, 99)),
                "max": float(ms.max()), "sum_over_median": float(ms.sum() / (len(ms) * med)) if med > 0 else math.nan}

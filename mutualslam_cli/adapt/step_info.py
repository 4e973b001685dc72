"""What one keyframe did to the online adaptation (:class:`StepInfo`): the record
:class:`~mutualslam_cli.adapt.online.OnlineAdapter` returns for each tick of Algorithm 1 and keeps in its
``history``, from which a run's ``keyframes.csv`` is written (:mod:`~mutualslam_cli.stages.adaptation_summary`)."""

from __future__ import annotations

from dataclasses import dataclass, field


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

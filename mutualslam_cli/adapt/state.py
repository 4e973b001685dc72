"""Algorithm 1 of the paper (online adaptation framework as a finite-state machine).

The machine is a *pure* transition function ``step(state, event, params) -> (state, actions)``;
the caller (:mod:`mutualslam_cli.adapt.online`) performs the actions (fine-tune, run global BA)
and feeds the results back as events. Nothing here touches a network.

Paper (Alg. 1), with ``m = 5``, ``n = 3``, ``τ_val = 0.2``::

    IDLE:      run_global_ba = false
               if t > 0 and t % m == 0:   compute L_val
                                          n_converged = n_converged + 1 if L_val < τ_val else 0
                                          run_global_ba = n_converged > 0 and n_converged % n == 0
               else:                      state = FINE_TUNE
    FINE_TUNE: fine-tune the CNN; state = IDLE
    t += 1

**Ticks.** In the paper's loop ``t`` counts loop iterations, and a training keyframe costs two of
them (IDLE → FINE_TUNE, then the FINE_TUNE tick), so "every m-th tick" would not be "every m-th
keyframe". The text says the network is validated "once every m incoming keyframes" (§III-B), so
here **one tick = one keyframe arrival** and ``t`` is the 0-based arrival index of the keyframe:

- keyframe ``t`` with ``t > 0 and t % m == 0`` is a *validation keyframe* (never trained on); the
  caller computes ``L_val`` and sends :class:`ValidationKeyframe`;
- any other keyframe is a *training keyframe*: :class:`TrainingKeyframe` moves IDLE → FINE_TUNE
  and returns the ``FINE_TUNE`` action (fine-tune on this keyframe, i.e. the paper's next tick);
  the caller then sends :class:`FineTuneDone`, which returns to IDLE.

``t`` is incremented when a keyframe is consumed (on the keyframe event). ``run_global_ba`` of
the paper is the :data:`RUN_GLOBAL_BA` action (it is reset on every IDLE tick in the paper, so it
is a one-shot signal, not state). A NaN ``L_val`` (no sparse points) is "not below τ_val" and
resets ``n_converged``, exactly as the comparison in Alg. 1 would.

A keyframe event while FINE_TUNE, or :class:`FineTuneDone` while IDLE, is a caller bug and raises
:class:`TransitionError` (an asynchronous caller must queue keyframes while fine-tuning).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum

from mutualslam_cli.errors import ConfigError, TransitionError


class Mode(str, Enum):
    """The two states of Algorithm 1."""

    IDLE = "IDLE"
    FINE_TUNE = "FINE_TUNE"


class Action(str, Enum):
    """What the caller must do after a transition."""

    FINE_TUNE = "fine_tune"
    RUN_GLOBAL_BA = "run_global_ba"


@dataclass(frozen=True)
class FsmParams:
    """Constants of Algorithm 1.

    Attributes:
        m: validate every m-th keyframe (paper: 5).
        n: patience, global BA after every n consecutive converged validations (paper: 3).
        tau_val: validation threshold on ``L_val`` (paper: 0.2, inverse map units).
    """

    m: int = 5
    n: int = 3
    tau_val: float = 0.2

    def __post_init__(self) -> None:
        if self.m < 1 or self.n < 1:
            raise ConfigError(f"FsmParams: m (adapt.validate_every) and n (adapt.patience) must be >= 1, "
                              f"got m={self.m}, n={self.n}")


@dataclass(frozen=True)
class FsmState:
    """State of Algorithm 1.

    Attributes:
        mode: IDLE or FINE_TUNE.
        t: number of keyframes consumed so far (= arrival index of the next keyframe).
        n_converged: consecutive validations with ``L_val < τ_val``.
    """

    mode: Mode = Mode.IDLE
    t: int = 0
    n_converged: int = 0


@dataclass(frozen=True)
class TrainingKeyframe:
    """A keyframe whose index is not a validation index arrived."""


@dataclass(frozen=True)
class ValidationKeyframe:
    """A validation keyframe arrived; ``l_val`` is L_val (Eq. 9) with the current model."""

    l_val: float


@dataclass(frozen=True)
class FineTuneDone:
    """The caller finished (or skipped) the fine-tuning requested by :data:`Action.FINE_TUNE`."""


Event = TrainingKeyframe | ValidationKeyframe | FineTuneDone


def is_validation_index(t: int, m: int) -> bool:
    """Alg. 1: keyframe ``t`` is a validation keyframe iff ``t > 0 and t % m == 0``."""
    return t > 0 and t % m == 0


def step(state: FsmState, event: Event, params: FsmParams = FsmParams()) -> tuple[FsmState, tuple[Action, ...]]:
    """One transition of Algorithm 1.

    Args:
        state: current state.
        event: what happened (see module docstring for the tick mapping).
        params: m, n, τ_val.

    Returns:
        ``(new_state, actions)``; ``actions`` is a tuple of :class:`Action` for the caller.

    Raises:
        TransitionError: the event is not allowed in ``state`` (e.g. a training keyframe at a
            validation index, or a keyframe while fine-tuning).
    """
    val_tick = is_validation_index(state.t, params.m)
    if state.mode is Mode.IDLE:
        if isinstance(event, ValidationKeyframe):
            if not val_tick:
                raise TransitionError(f"keyframe t={state.t} is a training keyframe (m={params.m}), "
                                      "got a validation event")
            l_val = float(event.l_val)
            # Alg. 1: n_converged += 1 if L_val < τ_val else 0 (NaN compares False → reset)
            n_conv = state.n_converged + 1 if (not math.isnan(l_val) and l_val < params.tau_val) else 0
            run_ba = n_conv > 0 and n_conv % params.n == 0  # Alg. 1: run_global_ba condition
            new = replace(state, t=state.t + 1, n_converged=n_conv)
            return new, ((Action.RUN_GLOBAL_BA,) if run_ba else ())
        if isinstance(event, TrainingKeyframe):
            if val_tick:
                raise TransitionError(f"keyframe t={state.t} is a validation keyframe (m={params.m}), "
                                      "got a training event")
            return replace(state, mode=Mode.FINE_TUNE, t=state.t + 1), (Action.FINE_TUNE,)
        if isinstance(event, FineTuneDone):
            raise TransitionError("FineTuneDone while IDLE: no fine-tuning was requested")
    elif state.mode is Mode.FINE_TUNE:
        if isinstance(event, FineTuneDone):
            return replace(state, mode=Mode.IDLE), ()
        if isinstance(event, (TrainingKeyframe, ValidationKeyframe)):
            raise TransitionError(f"{type(event).__name__} while FINE_TUNE: send FineTuneDone first (queue keyframes)")
    raise TransitionError(f"unknown event {event!r} in state {state.mode}")

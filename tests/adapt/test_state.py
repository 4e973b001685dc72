"""Algorithm 1 state machine: full transition table and the paper's schedule (m=5, n=3, τ=0.2)."""

from __future__ import annotations

import math

import pytest

from mutualslam_cli import errors
from mutualslam_cli.adapt.state import (
    Action,
    FineTuneDone,
    FsmParams,
    FsmState,
    Mode,
    TrainingKeyframe,
    TransitionError,
    ValidationKeyframe,
    is_validation_index,
    step,
)

P = FsmParams(m=5, n=3, tau_val=0.2)
LOW, HIGH = 0.1, 0.3  # below / above τ_val

# (state, event, expected new state or TransitionError, expected actions)
TABLE = [
    # IDLE, training index (t=0 and t=7): a training keyframe → FINE_TUNE, t+1
    (FsmState(Mode.IDLE, 0, 0), TrainingKeyframe(), FsmState(Mode.FINE_TUNE, 1, 0), (Action.FINE_TUNE,)),
    (FsmState(Mode.IDLE, 7, 2), TrainingKeyframe(), FsmState(Mode.FINE_TUNE, 8, 2), (Action.FINE_TUNE,)),
    (FsmState(Mode.IDLE, 7, 2), ValidationKeyframe(LOW), TransitionError, None),
    (FsmState(Mode.IDLE, 7, 2), FineTuneDone(), TransitionError, None),
    # IDLE, validation index t=5
    (FsmState(Mode.IDLE, 5, 0), ValidationKeyframe(LOW), FsmState(Mode.IDLE, 6, 1), ()),
    (FsmState(Mode.IDLE, 5, 1), ValidationKeyframe(LOW), FsmState(Mode.IDLE, 6, 2), ()),
    (FsmState(Mode.IDLE, 5, 2), ValidationKeyframe(LOW), FsmState(Mode.IDLE, 6, 3), (Action.RUN_GLOBAL_BA,)),
    (FsmState(Mode.IDLE, 5, 5), ValidationKeyframe(LOW), FsmState(Mode.IDLE, 6, 6), (Action.RUN_GLOBAL_BA,)),
    (FsmState(Mode.IDLE, 5, 3), ValidationKeyframe(LOW), FsmState(Mode.IDLE, 6, 4), ()),
    (FsmState(Mode.IDLE, 5, 2), ValidationKeyframe(HIGH), FsmState(Mode.IDLE, 6, 0), ()),
    (FsmState(Mode.IDLE, 5, 2), ValidationKeyframe(0.2), FsmState(Mode.IDLE, 6, 0), ()),  # strict <
    (FsmState(Mode.IDLE, 5, 2), ValidationKeyframe(math.nan), FsmState(Mode.IDLE, 6, 0), ()),
    (FsmState(Mode.IDLE, 5, 0), TrainingKeyframe(), TransitionError, None),
    (FsmState(Mode.IDLE, 5, 0), FineTuneDone(), TransitionError, None),
    # FINE_TUNE (t already advanced by the keyframe event)
    (FsmState(Mode.FINE_TUNE, 8, 2), FineTuneDone(), FsmState(Mode.IDLE, 8, 2), ()),
    (FsmState(Mode.FINE_TUNE, 5, 2), FineTuneDone(), FsmState(Mode.IDLE, 5, 2), ()),
    (FsmState(Mode.FINE_TUNE, 8, 2), TrainingKeyframe(), TransitionError, None),
    (FsmState(Mode.FINE_TUNE, 8, 2), ValidationKeyframe(LOW), TransitionError, None),
    (FsmState(Mode.FINE_TUNE, 10, 2), ValidationKeyframe(LOW), TransitionError, None),
]


@pytest.mark.parametrize(("state", "event", "expected", "actions"), TABLE)
def test_transition_table(state, event, expected, actions):
    if expected is TransitionError:
        with pytest.raises(TransitionError):
            step(state, event, P)
    else:
        new, acts = step(state, event, P)
        assert new == expected
        assert acts == actions


def test_validation_indices_follow_alg1():
    assert [t for t in range(21) if is_validation_index(t, 5)] == [5, 10, 15, 20]
    assert not is_validation_index(0, 1)  # t > 0 required even for m = 1


def _drive(l_vals: dict[int, float], n_kf: int, params: FsmParams) -> tuple[list[int], list[int], list[int]]:
    """Feed n_kf keyframes; return (trained t's, validated t's, t's where BA is requested)."""
    s = FsmState()
    trained, validated, ba = [], [], []
    for t in range(n_kf):
        assert s.t == t
        assert s.mode is Mode.IDLE
        if is_validation_index(t, params.m):
            s, acts = step(s, ValidationKeyframe(l_vals.get(t, 0.0)), params)
            validated.append(t)
            if Action.RUN_GLOBAL_BA in acts:
                ba.append(t)
        else:
            s, acts = step(s, TrainingKeyframe(), params)
            assert acts == (Action.FINE_TUNE,)
            assert s.mode is Mode.FINE_TUNE
            trained.append(t)
            s, acts = step(s, FineTuneDone(), params)
            assert acts == ()
    return trained, validated, ba


def test_schedule_paper_constants():
    # converged at every validation except t=20 → BA at the 3rd and 6th consecutive convergence
    l_vals = {20: 0.5}
    trained, validated, ba = _drive(l_vals, 46, P)
    assert validated == [5, 10, 15, 20, 25, 30, 35, 40, 45]
    assert len(trained) == 46 - len(validated)
    assert ba == [15, 35]  # n_conv 1,2,3 at 5,10,15; reset at 20; 1,2,3 at 25,30,35; 4,5 at 40,45


def test_never_converged_never_ba():
    _, _, ba = _drive({t: 1.0 for t in range(100)}, 100, P)
    assert ba == []


def test_params_reject_bad_m():
    with pytest.raises(errors.ConfigError, match="validate_every"):
        FsmParams(m=0)
    with pytest.raises(errors.ConfigError, match="patience"):
        FsmParams(n=0)


def test_transition_error_is_a_bug_not_a_user_error():
    """Lives in errors.py, still importable from adapt.state, and keeps its traceback in the CLI."""
    assert TransitionError is errors.TransitionError
    assert issubclass(TransitionError, RuntimeError)
    assert not issubclass(TransitionError, errors.MslamError)

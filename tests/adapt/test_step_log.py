"""The step log: every optimiser step's time beside the work done since the step before it."""

from __future__ import annotations

import pytest

from mutualslam_cli.adapt.step_info import StepLog


def test_each_step_carries_the_work_since_the_step_before() -> None:
    log = StepLog()
    log.mark("tick")
    log.step(3, 100.0, 2)
    log.step(3, 110.0, 2)
    log.mark("consolidate")
    log.mark("frontend")
    log.mark("consolidate")  # once is enough
    log.mark("ba")
    log.step(5, 500.0, 2)
    assert [s.after for s in log.steps] == [("tick",), (), ("consolidate", "frontend", "ba")]
    assert [r["after"] for r in log.rows()] == ["tick", "", "consolidate+frontend+ba"]
    assert [r["step"] for r in log.rows()] == [0, 1, 2]


def test_the_stats_show_a_stall() -> None:
    assert StepLog().stats() == {}
    log = StepLog()
    for _ in range(99):
        log.step(0, 100.0, 2)
    log.step(1, 5100.0, 2)  # one stalled step: 50 steps' worth
    s = log.stats()
    assert s["median"] == 100.0
    assert s["max"] == 5100.0
    assert s["p90"] == 100.0
    assert s["p99"] == pytest.approx(100.0 + 0.01 * 5000.0)  # numpy's linear interpolation at 99 %
    assert s["sum_over_median"] == pytest.approx((99 * 100 + 5100) / (100 * 100))

"""Loop recall against GT (metrics.loop_recall): true revisits by GT distance and angle, and each query's stage
(found / verified / closed) with the reason it went no further."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.metrics.loop_recall import (
    Partner,
    classify,
    counts,
    rotation_angle_deg,
    true_revisits,
)


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _circle(n: int, laps: float = 1.0, radius: float = 1.0) -> np.ndarray:
    """``(n, 4, 4)`` a camera going round a circle ``laps`` times, looking outwards (yaw = heading)."""
    a = np.linspace(0.0, 2 * np.pi * laps, n, endpoint=False)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3], T[:, 1, 3] = radius * np.cos(a), radius * np.sin(a)
    T[:, :3, :3] = np.stack([_rz(np.degrees(x)) for x in a])
    return T


def test_rotation_angle():
    assert rotation_angle_deg(_rz(10), _rz(45)) == pytest.approx(35.0)
    assert rotation_angle_deg(np.eye(3), np.eye(3)) == pytest.approx(0.0, abs=1e-6)


def test_a_second_lap_revisits_the_first_and_nothing_else_does():
    n = 100  # 50 keyframes a lap: 12.6 cm between neighbours on a 1 m circle, 7.2° apart
    T = _circle(n, laps=2.0)
    rev = true_revisits(T, np.arange(n), min_gap=30)
    # every keyframe of the second lap; of the first, only its last two, back near keyframes 0 and 1
    assert set(rev) == set(range(48, 100))
    assert [p.kf for p in rev[49]] == [0, 1]
    for j, ps in ((j, ps) for j, ps in rev.items() if j >= 50):
        assert ps[0].kf == j - 50
        assert ps[0].dist_m == pytest.approx(0.0, abs=1e-9)
        assert all(p.dist_m <= 0.30 and p.angle_deg <= 30.0 and j - p.kf >= 30 for p in ps)
        assert [p.dist_m for p in ps] == sorted(p.dist_m for p in ps)
    # the neighbours 2 keyframes away are 25 cm and 14.4° apart: partners; 3 away (38 cm): not
    assert {p.kf for p in rev[75]} == {23, 24, 25, 26, 27}


def test_the_angle_matters_and_keyframes_without_gt_are_never_partners():
    T = _circle(100, laps=2.0)
    T[50:, :3, :3] = T[50:, :3, :3] @ _rz(90)  # the second lap looks sideways: the same spot, another view
    rev = true_revisits(T, np.arange(100), min_gap=30)
    assert set(rev) == {48, 49, 98, 99}  # only the closing of each lap onto its own start
    assert all((j < 50) == (p.kf < 50) for j, ps in rev.items() for p in ps)
    T = _circle(100, laps=2.0)
    T[:50] = np.nan  # the first lap has no GT
    assert set(true_revisits(T, np.arange(100), min_gap=30)) == {98, 99}


def _q(kf, pool, candidates, geometry=None, verified=None, outcome="geometry: no candidate passed"):
    return {"kf": kf, "pool": np.array(pool), "candidates": candidates, "geometry": geometry or {},
            "verified": verified, "outcome": outcome}


def test_each_query_reaches_its_stage_with_the_reason_it_stopped():
    p = [Partner(10, 0.05, 3.0), Partner(11, 0.12, 6.0)]
    revisits = {k: p for k in (40, 41, 42, 43, 44, 45, 46, 47, 48)}
    pool = list(range(0, 20))
    queries = {
        40: _q(40, pool, [3, 11, 5], {3: "no geometric match", 11: "passed"}, 11, "loop"),   # closed
        41: _q(41, pool, [3, 4, 5], {3: "x", 4: "x", 5: "x"}),                              # not found
        42: _q(42, pool, [10, 4], {10: "refuted by verification", 4: "no geometric match"}),  # found, refuted
        43: _q(43, pool, [10, 4], {10: "passed"}, 10, "scale uncertain"),                    # verified, not closed
        44: _q(44, [15, 16], []),                                                             # partners not in pool
        45: _q(45, pool, [4, 10], {4: "passed"}, 4, "loop"),                                  # a wrong one first
        46: _q(46, pool, [10], {10: "passed"}, 10, "already closed"),
        48: _q(48, pool, [10], {10: "passed"}, 10, "loop"),
    }
    closed = {40: 11, 45: 4}
    skipped = {47: "not queried: within loop.min_gap (30) keyframes of the loop closed at keyframe 40"}
    rows = {r.kf: r for r in classify(revisits, queries, closed, skipped, n_candidates=3)}
    stage = {k: (r.found, r.verified, r.closed) for k, r in rows.items()}
    assert stage == {40: (True, True, True), 41: (False, False, False), 42: (True, False, False),
                     43: (True, True, False), 44: (False, False, False), 45: (True, False, False),
                     46: (True, True, False), 47: (False, False, False), 48: (True, True, False)}
    assert rows[40].reason == ""
    assert rows[40].closed_kf == 11
    assert rows[40].partner == 10
    assert rows[41].reason == "appearance: no true partner among the 3 best candidates"
    assert rows[42].reason == "geometry: refuted by verification"
    assert rows[43].reason == "scale uncertain"
    assert rows[44].reason.startswith("true partners outside its map unit")
    assert rows[45].reason == "geometry: keyframe 4 (no true partner) passed before a true partner was tried"
    assert rows[46].reason == "already closed"
    assert rows[47].reason.startswith("not queried: within loop.min_gap")
    assert rows[48].reason == "verified, not closed"
    c = counts(list(rows.values()))
    assert (c["revisits"], c["found"], c["verified"], c["closed"], c["refused"]) == (9, 6, 4, 1, 8)
    assert sum(c["reasons"].values()) == 8
    assert c["reasons"]["scale uncertain"] == 1
    assert rows[41].record()["candidates"] == "3 4 5"


def test_no_keyframe_no_revisit():
    assert true_revisits(np.zeros((0, 4, 4)), np.zeros(0, np.int64), min_gap=30) == {}
    assert counts([]) == {"revisits": 0, "found": 0, "verified": 0, "closed": 0, "refused": 0, "reasons": {}}

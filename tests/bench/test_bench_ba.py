"""The global-BA benchmark's problem is well posed: a small instance of its loop scene has real
baselines and parallax, its cost's minimum is the true state, and LM from the benchmark's
perturbation converges to it (the full 100-keyframe benchmark is the slow test)."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.backend.ba.photometric import solve
from mutualslam_cli.bench import ba as bench


@pytest.fixture(scope="module")
def small():
    """12 keyframes of the benchmark's loop scene at its resolution (6–8 cm apart, 1200 points)."""
    prob, _ = bench.synthetic_problem(**{**bench.BENCH_PROBLEM, "n_kf": 12, "n_points": 1200, "extent": 0.2})
    return prob


def test_geometry_is_not_degenerate(small):
    info = bench.problem_info(small)
    assert info["spacing_cm_min"] >= 2.0
    assert info["spacing_cm_median"] <= 10.0
    assert info["parallax_px_p10"] >= 5.0
    assert info["baseline_cm_median"] >= 3.0
    assert info["targets_per_point"] >= 4.0
    depth = 1.0 / small.inv_depth
    assert np.quantile(depth, 0.9) - np.quantile(depth, 0.1) > 0.3  # several planes, not one
    # the path turns: rotations differ by more than a degree between keyframes
    tr = np.einsum("ij,kij->k", small.T_cw[0, :3, :3], small.T_cw[:, :3, :3])
    assert np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1))).max() > 1.0


def test_accuracy_of_the_truth_is_zero(small):
    acc = bench.accuracy(small, small.T_cw, small.inv_depth)
    assert max(abs(v) for v in acc.values()) < 1e-6


def test_minimum_is_the_true_state(small):
    """Started 0.1 mm / 0.001° / 0.1 % off, LM settles next to the truth: the interpolation
    error of the renders moves the cost's minimum by far less than a millimetre."""
    start = bench.perturb(small, np.random.default_rng(5), trans=1e-4, rot_deg=1e-3, rho_rel=1e-3)
    res = solve(start, iterations=10)
    acc = bench.accuracy(small, res.T_cw, res.inv_depth)
    assert acc["centre_mm_max"] < 0.3
    assert acc["rot_deg_max"] < 0.01


@pytest.mark.parametrize("seed", [1, 2])
def test_lm_converges_from_the_benchmark_start(small, seed):
    start = bench.perturb(small, np.random.default_rng(seed), **bench.BENCH_PERTURBATION)
    before = bench.accuracy(small, start.T_cw, start.inv_depth)
    # 2 mm per keyframe, then rescaled about keyframe 0 to the true extent (the BA's scale anchor)
    assert 1.5 < before["centre_mm_max"] < 3.0
    assert abs(before["scale_pct"]) < 0.05
    assert before["rho_rel_median"] == pytest.approx(0.03)
    res = solve(start, iterations=10)
    acc = bench.accuracy(small, res.T_cw, res.inv_depth)
    assert acc["centre_mm_max"] < 1.0
    assert acc["centre_sim3_mm_max"] < 1.0
    assert acc["rot_deg_max"] < 0.01
    assert acc["rho_rel_median"] < 0.002
    assert acc["rho_rel_p95"] < 0.01
    st = res.stats
    assert st["cost"] < 1e-2 * st["cost0"]
    assert st["accepted"] >= 3


@pytest.mark.slow
def test_full_benchmark_recovers_the_map():
    r = bench.bench_ba(runs=1)
    p = r["ba_problem"]
    assert (p["keyframes"], p["points"]) == (100, 10_000)
    assert p["targets_per_point"] > 4.5
    assert r["ba_after"]["centre_sim3_mm_max"] < 1.0
    assert abs(r["ba_after"]["scale_pct"]) < 1.0
    assert r["ba_after"]["rho_rel_median"] < 0.01
    assert r["ba_cost"] < 1e-2 * r["ba_cost0"]
    assert bench.report(r).count("\n") == 11  # header, rule, 8 accuracy rows, cost, steps

"""Paired comparisons of two variants on the same sequences and seeds (report/paired.py) and ``mslam report --pair``."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.report.paired import (
    DOES_NOT_HOLD,
    HOLDS,
    MIN_PAIRS,
    UNDECIDED,
    better_of,
    bootstrap_ci,
    pair_runs,
    paired_stats,
    parse_pair,
    sign_test,
)


def test_sign_test_is_the_exact_two_sided_binomial():
    assert sign_test(6, 0) == pytest.approx(2 / 64)
    assert sign_test(5, 0) == pytest.approx(2 / 32)  # 5 of 5 is not enough at 0.05
    assert sign_test(0, 6) == sign_test(6, 0)
    assert sign_test(3, 3) == 1.0
    assert sign_test(0, 0) == 1.0
    assert sign_test(10, 2) == pytest.approx(2 * sum(math.comb(12, i) for i in range(3)) / 2 ** 12)


def test_bootstrap_ci_is_seeded_and_brackets_the_mean():
    d = np.array([1.0, 2.0, 3.0, 4.0, 10.0])
    assert bootstrap_ci(d, seed=3) == bootstrap_ci(d, seed=3)
    lo, hi = bootstrap_ci(d)
    assert lo < d.mean() < hi
    assert lo >= d.min()
    assert hi <= d.max()
    assert all(math.isnan(x) for x in bootstrap_ci(np.array([1.0])))


def _pairs(diffs, seqs=None) -> pd.DataFrame:
    diffs = np.asarray(diffs, float)
    b = np.arange(len(diffs), dtype=float)  # distinct runs: nothing collapses
    seqs = seqs or [f"s{i}" for i in range(len(diffs))]
    return pd.DataFrame({"sequence": seqs, "seed": 0, "a": b + diffs, "b": b, "diff": diffs, "broadcast": False})


@pytest.mark.parametrize(("diffs", "better", "want"), [
    ([1, 2, 1.5, 3, 0.5, 2, 1, 2.5], "higher", HOLDS),
    ([-1, -2, -1.5, -3, -0.5, -2, -1, -2.5], "higher", DOES_NOT_HOLD),
    ([-1, -2, -1.5, -3, -0.5, -2, -1, -2.5], "lower", HOLDS),       # an ATE that fell: a better
    ([1, 2, 1.5, 3, 0.5], "higher", UNDECIDED),                       # 5 of 5: fewer than MIN_PAIRS
    ([1, -2, 1.5, -3, 0.5, 2, -1, 0.1], "higher", UNDECIDED),         # mixed
    ([5, 5, 5, 5, 5, 5, 5, -30], "higher", UNDECIDED),                # 7 of 8 wins but the CI reaches below 0
])
def test_the_verdict_rule(diffs, better, want):
    r = paired_stats(_pairs(diffs), better)
    assert r.verdict == want, r
    assert r.n == len(diffs)
    assert r.wins + r.ties + r.losses == r.n


def test_identical_runs_count_once_and_the_counts_follow_the_direction():
    # a scheme without replay gives the same numbers for every seed: three seeds of one sequence are one sample
    p = pd.DataFrame({"sequence": ["x"] * 3 + ["y"] * 2, "seed": [0, 1, 2, 0, 1], "a": [3.0, 3.0, 3.0, 1.0, 2.0],
                      "b": [1.0, 1.0, 1.0, 2.0, 2.0], "broadcast": False})
    p["diff"] = p["a"] - p["b"]
    r = paired_stats(p, "higher")
    assert (r.n, r.collapsed, r.wins, r.ties, r.losses) == (3, 2, 1, 1, 1)
    r = paired_stats(p, "lower")
    assert (r.wins, r.losses) == (1, 1)
    assert r.mean == pytest.approx(np.mean([2.0, -1.0, 0.0]))


def _runs() -> pd.DataFrame:
    """Two configs (threads 1 and 2), two schemes, two sequences, three seeds; replay+ewc = replay + 1 + seed."""
    rows = []
    for threads in (1, 2):
        for seq in ("s1", "s2"):
            for seed in (0, 1, 2):
                for scheme, gain in (("replay", 0.0), ("replay+ewc", 1.0 + seed)):
                    rows.append({"sequence.name": seq, "scheme": scheme, "seed": seed, "config.threads": threads,
                                 "config.ba.final": "always", "folder": f"{threads}/{seq}/{scheme}/{seed}",
                                 "depth.pcd.lsq.adapted": 40.0 + 10 * threads + seed + gain,
                                 "depth.pcd.lsq.pretrained": 20.0})
    return pd.DataFrame(rows)


def test_pairs_are_made_within_the_settings_the_arms_share():
    a, b = parse_pair("replay+ewc vs replay", "depth.pcd.lsq.adapted")
    p = pair_runs(_runs(), a, b)
    assert len(p) == 12  # 2 configs × 2 sequences × 3 seeds: never a threads=1 run against a threads=2 one
    assert (p["diff"] == 1.0 + p["seed"]).all()
    a, b = parse_pair("replay@depth.pcd.lsq.adapted vs replay@depth.pcd.lsq.pretrained", "x")
    p = pair_runs(_runs(), a, b)
    assert len(p) == 12
    assert (p["folder_a"] == p["folder_b"]).all()
    a, b = parse_pair("replay+ewc,threads=2 vs replay,threads=1", "depth.pcd.lsq.adapted")
    p = pair_runs(_runs(), a, b)
    assert len(p) == 6
    assert (p["diff"] == 11.0 + p["seed"]).all()


def test_a_single_seed_stands_for_every_seed_only_when_asked():
    runs = _runs()
    runs = runs[(runs["scheme"] == "replay+ewc") | (runs["seed"] == 0)]
    a, b = parse_pair("replay+ewc vs replay", "depth.pcd.lsq.adapted")
    assert len(pair_runs(runs, a, b)) == 4
    p = pair_runs(runs, a, b, broadcast=True)
    assert len(p) == 12
    assert p["broadcast"].sum() == 8
    assert paired_stats(p, "higher").broadcast == 8


@pytest.mark.parametrize("text", ["replay+ewc replay", "a=@k vs b", "=x vs b"])
def test_malformed_pairs_are_one_line(text):
    with pytest.raises(ConfigError):
        parse_pair(text, "depth.pcd.lsq.adapted")


def test_the_direction_of_a_key():
    assert better_of("trajectory.credit.ba") == "lower"
    assert better_of("map.esi.ba") == "lower"
    assert better_of("depth.pcd.lsq.adapted") == "higher"
    assert better_of("timing.total_s") == "lower"


def _write_runs(root, n_seq=3, n_seed=3):
    """Result folders as ``mslam ablate`` writes them (summary.json, config.yaml): replay+ewc ahead by 2 + seed."""
    for q in range(n_seq):
        for seed in range(n_seed):
            for scheme, gain in (("replay", 0.0), ("replay+ewc", 2.0 + seed)):
                f = root / f"seq{q}" / scheme / f"seed{seed}"
                f.mkdir(parents=True)
                summary = {"sequence": {"name": f"seq{q}"}, "scheme": scheme, "seed": seed,
                           "depth": {"pcd": {"lsq": {"adapted": 40.0 + q + gain, "pretrained": 20.0}}}}
                (f / "summary.json").write_text(json.dumps(summary))
                (f / "config.yaml").write_text(yaml.safe_dump({"seed": seed, "adapt": {"scheme": scheme, "lr": 1e-3}}))


def test_report_pair_writes_the_paired_table_and_every_pair(tmp_path):
    _write_runs(tmp_path / "res")
    r = CliRunner().invoke(app, ["report", str(tmp_path / "res"), "--out", str(tmp_path / "rep"),
                                 "--pair", "replay+ewc vs replay"])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "rep" / "paired.csv")
    total = t[t["sequence"] == "all"].iloc[0]
    assert total["N"] == 9 >= MIN_PAIRS
    assert total["wins / ties / losses"] == "9 / 0 / 0"
    assert total["verdict"] == HOLDS
    assert total["mean a − b"] == pytest.approx(3.0)
    assert total["sign p"] == pytest.approx(2 / 2 ** 9)
    pairs = pd.read_csv(tmp_path / "rep" / "paired_pairs.csv")
    assert len(pairs) == 9
    assert set(pairs["diff"]) == {2.0, 3.0, 4.0}
    assert "Paired comparisons" in (tmp_path / "rep" / "report.md").read_text()


def test_report_pair_without_a_pair_is_one_line(tmp_path):
    _write_runs(tmp_path / "res", n_seq=1, n_seed=1)
    r = CliRunner().invoke(app, ["report", str(tmp_path / "res"), "--out", str(tmp_path / "rep"),
                                 "--pair", "recent vs replay"])
    assert r.exit_code == 1
    assert "no pair of runs" in r.output

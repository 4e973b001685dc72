"""The OpenMP spin setting and the contention benchmark's figures (what they are, never how fast)."""

from __future__ import annotations

import os
import subprocess
import sys

import mutualslam_cli
from mutualslam_cli.bench.contention import contention
from mutualslam_cli.machine import cpu_kind

SHOW = "import mutualslam_cli, os, torch; print(os.environ['GOMP_SPINCOUNT'])"


def test_the_package_sets_a_short_openmp_spin_unless_the_environment_does() -> None:
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    out = subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == mutualslam_cli.OMP_SPINCOUNT == "10000"
    out = subprocess.run([sys.executable, "-c", SHOW], env={**env, "GOMP_SPINCOUNT": "123"}, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "123"


def test_the_contention_benchmark_reports_both_steps_their_ratio_and_the_cpu() -> None:
    r = contention(threads=1, repeats=1, width=96, height=64)
    assert r["threads"] == 1
    assert r["quiet_ms"] > 0
    assert r["contended_ms"] > 0
    assert r["ratio"] == r["contended_ms"] / r["quiet_ms"]
    assert r["fair"] >= 1.0
    assert r["gomp_spincount"] == os.environ.get("GOMP_SPINCOUNT")
    assert r["cpu_kind"] == cpu_kind(r["cpu_flags"])

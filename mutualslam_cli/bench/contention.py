"""The optimiser step on a shared machine: a step's time alone and beside one CPU-bound process
(``mslam bench contention``).

With as many torch threads as cores, another busy process takes one of them: fair sharing would make a step
about ``cores / (cores − 1)`` times slower (2× on 2 cores), but OpenMP threads that spin while they wait at a
barrier lose far more with GNU OpenMP's default spin count (the tail of a run's steps: one keyframe's steps several
times the median). mslam sets a short spin (:data:`mutualslam_cli.OMP_SPINCOUNT`) before torch is loaded; this
benchmark shows the stall if it comes back: ``ratio`` well above ``fair``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from typing import TypedDict

from mutualslam_cli.adapt.depthnet import fast_path_supported
from mutualslam_cli.bench.finetune import bench_finetune_step
from mutualslam_cli.config import load_config
from mutualslam_cli.machine import cpu_info


class Contention(TypedDict):
    """:func:`contention`'s figures: the median step alone and beside a busy process (ms), their ratio, the fair
    ratio, the OpenMP wait settings in force and the CPU."""

    threads: int
    quiet_ms: float
    contended_ms: float
    ratio: float
    fair: float
    gomp_spincount: str | None
    omp_wait_policy: str | None
    cpu_kind: str
    cpu_flags: list[str] | None


def contention(threads: int | None = None, repeats: int = 5, width: int = 640, height: int = 192) -> Contention:
    """The default config's fine-tuning step (:func:`~mutualslam_cli.bench.finetune.bench_finetune_step`: the fast
    path where the CPU has it, the default trust region) alone, then while one busy-looping Python process runs
    beside it."""
    cores = len(os.sched_getaffinity(0))
    threads = threads or cores
    fast, trust = fast_path_supported(), load_config().adapt.trust

    def step() -> float:
        return bench_finetune_step(width, height, repeats, fast=fast, threads=threads, trust=trust)["ms"]

    quiet = step()
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        contended = step()
    finally:
        busy.kill()
        busy.wait()
    cpu = cpu_info()
    return {"threads": threads, "quiet_ms": quiet, "contended_ms": contended, "ratio": contended / quiet,
            "fair": threads / max(1, min(threads, cores - 1)) if cores > 1 else 2.0,
            "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "cpu_kind": cpu["cpu_kind"], "cpu_flags": cpu["cpu_flags"]}

"""The global BA on a whole sequence: 2,000 synthetic frames of the room that keeps returning to
where it started, our front end's map, the final BA's time and memory (slow: run by hand)."""

from __future__ import annotations

import resource
import time
from pathlib import Path

import pytest

from mutualslam_cli.backend.ba.global_ba import run_global_ba
from mutualslam_cli.backend.refine import ba_images
from mutualslam_cli.config import BAConfig, RunConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.synthetic import iter_render, write_tum
from mutualslam_cli.machine import cpu_info
from mutualslam_cli.metrics.trajectory import ate
from mutualslam_cli.stages.frontend import run_frontend


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


@pytest.mark.slow
def test_ba_of_2000_frames_fits_in_time_and_memory(tmp_path: Path):
    root = write_tum(iter_render("room", 2000, 640, 480, seed=0), tmp_path / "room2000", scene="room", seed=0)
    seq = load_sequence(root)
    vo, _ = run_frontend(seq, RunConfig())
    assert len(vo.keyframes) > 100
    assert len({k.segment for k in vo.keyframes}) == 1
    base = _peak_rss_mb()
    t = time.perf_counter()
    r = run_global_ba(vo, ba_images(seq, vo), None, None, BAConfig(), cull=False)
    seconds = time.perf_counter() - t
    grew = _peak_rss_mb() - base
    before, after = ate(seq.gt, vo.traj_kf).rmse, ate(seq.gt, r.vo.traj_kf).rmse
    print(f"2000 frames: {len(vo.keyframes)} keyframes, {len(vo.points)} points; BA {seconds:.1f} s, peak RSS "
          f"+{grew:.0f} MB; keyframe ATE {1000 * before:.2f} -> {1000 * after:.2f} mm; "
          f"{r.stats.n_nearby_targets} nearby targets, {r.stats.n_dropped} dropped")
    # the README's figures within 1.5x, for the kind of CPU it runs on (the BA is numpy: the CPU matters, 2.3x
    # between these two; an AVX2-only CPU has no figure yet and gets the slower one); time depends on the
    # machine's load, so run it on an idle machine
    seconds_readme = {"AVX512-BF16": 4.5, "AMX": 10.0}.get(cpu_info()["cpu_kind"], 10.0)
    assert seconds < 1.5 * seconds_readme
    assert grew < 1.5 * 744
    assert after <= before

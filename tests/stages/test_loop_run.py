"""Loop closure in a whole run (slow: run by hand or `make test-all`): 2,000 rendered frames of a room the
camera circles more than once, our VO, the pre-trained network (no fine-tuning: the SLAM parts alone), the
front end alone / bridged / after BA / after BA, merges and loop closure, one Sim(3) each on the same frames."""

from __future__ import annotations

import resource
import time
from pathlib import Path

import pytest

from mutualslam_cli.config import load_config
from mutualslam_cli.datasets.synthetic import iter_render, write_tum
from mutualslam_cli.pipeline import run_sequence


@pytest.mark.slow
def test_a_loop_closed_over_2000_frames_lowers_the_ate(tmp_path: Path):
    root = write_tum(iter_render("room", 2000, 320, 240, seed=0), tmp_path / "room2000", scene="room", seed=0)
    out = {}
    for loop in (False, True):
        cfg = load_config(None, ["adapt.scheme=none", "threads=1", "net.width=320", "net.height=96",
                                 "eval.online=false", "eval.export_frames=0", "eval.stride=10", "ba.final=always",
                                 f"loop.enabled={str(loop).lower()}", f"vo.merge_segments={str(loop).lower()}"])
        t = time.perf_counter()
        r = run_sequence(root, cfg, out=tmp_path / f"loop_{loop}")
        out[loop] = (r.summary, time.perf_counter() - t)
    (off, t_off), (on, t_on) = out[False], out[True]
    c_off, c_on = off["trajectory"]["credit"], on["trajectory"]["credit"]
    print(f"2000 frames: VO {c_off['vo']:.4f} bridged {c_off['bridged']:.4f} BA {c_off['ba']:.4f} m; with loop "
          f"closure {c_on['ba']:.4f} m ({on['loop']}); {t_off:.0f} / {t_on:.0f} s; peak RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    assert on["loop"]["accepted"] >= 1
    assert off["loop"]["accepted"] is None
    # the same front end alone until the first loop: its correction reaches the live front end (causal feedback)
    assert c_on["vo"] == pytest.approx(c_off["vo"], rel=0.01)
    # measured 2026-12-07: without loops the front end 2.94 cm and + BA 3.10 cm (on the code before issue one-map3,
    # 26.3 and 1.65 cm); with loops 2.51 cm (before, 12.8 cm: the loops made it worse), bounded within 1.5x
    assert c_on["ba"] < 0.9 * c_off["ba"]
    assert c_on["ba"] < 0.0377

"""The whole-run figure of `make bench` (bench/whole_run.py): stages from a run's summary, per frame."""

from __future__ import annotations

import pytest

from mutualslam_cli.bench.whole_run import STAGES, split_by_stage, table_lines, whole_run_figures

SUMMARY = {
    "timing": {"total_s": 134.2, "finetune_ms": 800.0, "finetune_steps_s": 80.7, "finetune_consolidate_s": 11.6,
               "online_scoring_s": 11.3,
               "stage_s": {"frontend": 6.4, "adaptation": 97.2, "ba": 0.0, "evaluation": 28.1, "other": 2.5}},
    "adaptation": {"steps": 96},
    "depth": {"pcd": {"lsq": {"adapted": 57.9, "pretrained": 25.8}}},
}


def test_stages_split_the_run_s_stages_without_loss():
    s = split_by_stage(SUMMARY["timing"])
    assert tuple(s) == STAGES
    assert s["adaptation_other"] == pytest.approx(97.2 - 80.7 - 11.6)
    assert s["final_eval"] == pytest.approx(28.1 - 11.3)
    stage = SUMMARY["timing"]["stage_s"]
    assert sum(s.values()) == pytest.approx(sum(stage.values()))  # the parts add up to the run's stages


def test_figures_per_frame_and_total_over_steps():
    f = whole_run_figures(SUMMARY, frames=100)
    assert f["total_vs_steps"] == pytest.approx(134.2 / (96 * 0.8))
    assert f["stage_s_per_frame"]["steps"] == pytest.approx(0.807)
    assert f["evaluation_share"] == pytest.approx(28.1 / 134.2)
    assert f["pcd_lsq_adapted"] == 57.9
    lines = table_lines({"whole_run_seq": "w", "whole_run_threads": 1, "cpu_kind": "AVX512-BF16",
                         **{f"whole_run_{k}": v for k, v in f.items()}})
    assert "1.75" in lines[0]
    assert "AVX512-BF16" in lines[0]
    assert any(line.startswith("| steps | 80.7 | 0.807 |") for line in lines)


def test_a_run_without_steps_has_no_ratio():
    f = whole_run_figures({"timing": {"total_s": 10.0, "stage_s": {"frontend": 10.0}}}, frames=10)
    assert f["total_vs_steps"] is None
    assert f["stage_s"]["frontend"] == 10.0

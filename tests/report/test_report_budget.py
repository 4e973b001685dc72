"""The budget table and frontier figure of ``mslam report`` on runs of several fine-tuning budgets."""

from __future__ import annotations

import pandas as pd
import pytest

from mutualslam_cli.report.budget import budget_table, frontier_figure, short_label


def _runs() -> pd.DataFrame:
    rows = []
    # config → (PCD per sequence, adaptation s per run, steps per run); seq "c" only in the first config
    plan = {"adapt.steps_per_keyframe=8": ({"a": 40.0, "b": 50.0, "c": 99.0}, 100.0, 80),
            "adapt.steps_per_keyframe=4": ({"a": 30.0, "b": 40.0}, 50.0, 40),
            "adapt.steps_per_keyframe=4, adapt.lr=0.0002": ({"a": 20.0, "b": 30.0}, 60.0, 40)}
    for config, (pcd, secs, steps) in plan.items():
        for seq, v in pcd.items():
            for seed in (0, 1):
                rows.append({"scheme": "replay+ewc", "config": config, "sequence.name": seq,
                             "depth.pcd.lsq.adapted": v + seed, "depth.pcd.median.adapted": v,
                             "adaptation.steps": steps, "timing.finetune_ms": 500.0 if "=8" in config else 250.0,
                             "timing.stage_s.adaptation": secs, "timing.total_s": secs + 10})
    return pd.DataFrame(rows)


def test_budget_rows_compare_the_same_sequences_and_mark_the_frontier(tmp_path):
    t = budget_table(_runs()).set_index("config")
    assert (t["sequences"] == 2).all()
    assert t.loc["paper values", "runs"] == 4
    eight = t.loc["paper values"]
    assert eight["PCD lsq"] == pytest.approx(45.5)
    assert eight["adaptation s"] == 200
    assert eight["steps"] == 160
    assert eight["step ms × steps (s)"] == pytest.approx(80.0)
    assert t["frontier"].to_dict() == {"steps_per_keyframe=4": True, "paper values": True,
                                       "steps_per_keyframe=4 lr=0.0002": False}
    assert frontier_figure(budget_table(_runs()), tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 0


def test_no_budget_table_without_differing_configs(tmp_path):
    one = _runs().query("config == 'adapt.steps_per_keyframe=8'")
    assert budget_table(one) is None
    assert not frontier_figure(None, tmp_path / "f.png")


def test_short_labels_drop_the_paper_values():
    assert short_label("adapt.lr=0.001, adapt.steps_per_keyframe=4, adapt.train_width=0") == "steps_per_keyframe=4"
    assert short_label("adapt.train_width=0, ba.window=30") == "ba.window=30"
    assert short_label("adapt.lr=0.001") == "paper values"
    assert short_label("adapt.lr=0.0001") == "lr=0.0001"  # configs/tuned.yaml's: not the paper's

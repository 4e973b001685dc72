"""``mslam report``'s scale-drift and loop-recall tables and the runs' ``scale_drift.png``, from hand-made run
folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mutualslam_cli.report.tables import build_tables, collect, to_markdown, write_report
from mutualslam_cli.results.run_folder import run_dir, write_json, write_yaml
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.scale_drift import figure


def _run(root: Path, seq: str, seed: int, values: dict, loop: bool = False) -> Path:
    folder = run_dir(root, seq, "none", seed)
    folder.mkdir(parents=True)
    write_yaml(folder / "config.yaml", {"seed": seed, "out": str(root), "adapt": {"scheme": "none"},
                                        "loop": {"enabled": loop}})
    s = Summary()
    for k, v in values.items():
        s.set(k, v, "hand-made: absent")
    for k, v in (("sequence.name", seq), ("scheme", "none"), ("seed", seed)):
        s.set(k, v)
    write_json(folder / "summary.json", s.to_dict())
    return folder


def _scale(vo: float, ba: float | None, ate: float) -> dict:
    return {"trajectory.local_scale.vo.max_over_min": vo, "trajectory.local_scale.vo.min": 1 / np.sqrt(vo),
            "trajectory.local_scale.vo.max": np.sqrt(vo), "trajectory.local_ate_m.vo": ate,
            "trajectory.ate_rmse_m.vo": 3 * ate, "trajectory.local_scale.ba.max_over_min": ba}


def test_scale_drift_table_and_figure(tmp_path: Path):
    a0 = _run(tmp_path / "r", "seqA", 0, _scale(1.4, 1.1, 0.01))
    _run(tmp_path / "r", "seqA", 1, _scale(1.6, None, 0.03))
    n = 20  # the run's figure, drawn as the run draws it
    figure(pd.DataFrame({"map": "vo", "start_s": np.arange(n) * 0.1, "segment": 0,
                         "relative_scale": np.linspace(0.8, 1.2, n), "local_rmse_m": 0.01, "global_rmse_m": 0.03}),
           a0 / "scale_drift.png", "seqA")
    rep = build_tables(collect([tmp_path / "r"]))
    t = rep.tables["scale_drift"]
    row = t.iloc[0]
    assert row["scale max/min VO"] == pytest.approx(1.5)
    assert row["local ATE VO"] == pytest.approx(0.02)
    assert row["global ATE VO"] == pytest.approx(0.06)
    assert row["scale max/min BA"] == pytest.approx(1.1)  # the seed without a BA map is left out, not 0
    assert np.isnan(row["local ATE BA"])
    assert "—" in to_markdown(t)
    assert rep.tables["trajectory"].iloc[0]["scale max/min VO"] == pytest.approx(1.5)
    assert "loop_recall" not in rep.tables  # no run has loop recall
    files = write_report(rep, tmp_path / "out")
    names = {p.relative_to(tmp_path / "out").as_posix() for p in files}
    assert "scale_drift.md" in names
    assert "scale_drift/scale_drift_seqA_none_seed0.png" in names
    md = (tmp_path / "out" / "report.md").read_text()
    assert "Scale drift" in md
    assert "](scale_drift/scale_drift_seqA_none_seed0.png)" in md


def test_loop_recall_table_when_a_run_has_it(tmp_path: Path):
    recall = {"loop.recall.revisits": 40, "loop.recall.found": 12, "loop.recall.verified": 6,
              "loop.recall.closed": 1, "loop.accepted": 1, "loop.candidates": 90}
    _run(tmp_path / "r", "seqA", 0, recall, loop=True)
    _run(tmp_path / "r", "seqB", 0, {"loop.recall.revisits": None}, loop=False)
    t = build_tables(collect([tmp_path / "r"])).tables["loop_recall"]
    a = t[t["sequence"] == "seqA"].iloc[0]
    assert (a["revisits"], a["found"], a["verified"], a["closed"]) == (40, 12, 6, 1)
    assert np.isnan(t[t["sequence"] == "seqB"].iloc[0]["revisits"])  # loop closure off: absent, not 0

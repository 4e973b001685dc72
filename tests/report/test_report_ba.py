"""Paper Tables 4 and 5 and the map figure of ``mslam report``, from hand-made run folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mutualslam_cli.errors import DatasetError
from mutualslam_cli.report.tables import build_tables, collect, to_markdown, write_report
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import run_dir, write_json, write_yaml
from mutualslam_cli.results.summary import Summary


def _run(root: Path, seq: str, seed: int, culling: bool, values: dict[str, float | None],
         max_fts: int = 500, scheme: str = "replay+ewc", loop: bool = False) -> Path:
    """A complete run folder: ``config.yaml`` (the keys the report reads) and ``summary.json``."""
    folder = run_dir(root, seq, scheme, seed)
    folder.mkdir(parents=True)
    write_yaml(folder / "config.yaml", {"seed": seed, "out": str(root), "vo": {"max_fts": max_fts},
                                            "adapt": {"scheme": scheme},
                                            "ba": {"enabled": True, "culling": culling}, "loop": {"enabled": loop}})
    s = Summary()
    for k, v in values.items():
        s.set(k, v, "hand-made: absent")
    if not culling:
        s.absent("map.points.culled", "disabled (ba.culling=false): BA without culling")
        s.absent("map.esi.culled", "disabled (ba.culling=false): BA without culling")
    s.set("sequence.name", seq)
    s.set("scheme", scheme)
    s.set("seed", seed)
    write_json(folder / "summary.json", s.to_dict())
    return folder


def _vals(ate_vo, ate_ba, vo, culled, ba, bridged=None):
    """Summary values: ATEs (Table 4's credit columns: front end, bridged, after BA) and (points, e_si) of
    the VO, culled and BA maps."""
    out = {"trajectory.ate_rmse_m.vo": ate_vo, "trajectory.ate_rmse_m.ba": ate_ba,
           "trajectory.credit.vo": ate_vo, "trajectory.credit.ba": ate_ba,
           "trajectory.credit.bridged": ate_vo if bridged is None else bridged}
    for stage, pe in (("vo", vo), ("culled", culled), ("ba", ba)):
        if pe is not None:
            out[f"map.points.{stage}"], out[f"map.esi.{stage}"] = pe
    return out


@pytest.fixture
def roots(tmp_path: Path) -> tuple[Path, Path]:
    cull, nocull = tmp_path / "cull", tmp_path / "nocull"
    _run(cull, "seqA", 0, True, _vals(0.020, 0.010, (1000, 0.50), (600, 0.40), (600, 0.30)))
    _run(cull, "seqA", 1, True, _vals(0.030, 0.020, (1200, 0.60), (800, 0.50), (800, 0.40)))
    _run(cull, "seqB", 0, True, _vals(0.050, 0.060, (500, 0.70), (300, 0.55), (300, None)))
    # the same front end as cull/seqA/seed0 (the VO map is shared), BA on the whole map
    _run(nocull, "seqA", 0, False, _vals(0.020, 0.015, (1000, 0.50), None, (1000, 0.45)))
    return cull, nocull


def test_table4_credits_each_part_on_seeds_paired(roots):
    cull, _ = roots
    _run(cull, "seqA", 2, True, _vals(0.040, None, (900, 0.5), None, None, bridged=0.035))  # no BA requested
    _run(cull, "seqC", 0, True, _vals(0.010, None, (900, 0.5), None, None))  # none of its seeds has BA
    rep = build_tables(collect(list(roots)))
    t = rep.tables["ate_ba"]
    assert list(t.columns) == ["Sequence", "config", "VO", "bridged", "+ culling + BA", "n"]
    assert list(t["config"]) == ["ba.culling=False"] * 2 + ["ba.culling=True"] * 4  # never averaged together
    nc, c = t[t["config"] == "ba.culling=False"], t[t["config"] == "ba.culling=True"]
    assert list(c["Sequence"]) == ["seqA", "seqB", "seqC", "Average (2 of 3)"]
    a = c.iloc[0]  # seeds 0 and 1 have every column; seed 2 (no BA) is left out of every column alike
    assert a["VO"] == pytest.approx(0.025)
    assert a["+ culling + BA"] == pytest.approx(0.015)
    assert a["n"] == 2
    assert a["bridged"] == pytest.approx(0.025)
    sc = c.iloc[2]  # no seed with a BA: its BA cell is missing, the others over every seed
    assert sc["VO"] == pytest.approx(0.01)
    assert np.isnan(sc["+ culling + BA"])
    assert sc["n"] == 1
    avg = c.iloc[3]
    assert avg["VO"] == pytest.approx((0.025 + 0.05) / 2)
    assert avg["+ culling + BA"] == pytest.approx(0.0375)
    assert nc.iloc[0]["+ culling + BA"] == pytest.approx(0.015)
    # best (lower) in bold in LaTeX: seqA with BA, seqB without
    rows = {r.split(" & ")[0]: r for r in _latex(rep, "ate_ba").splitlines() if " & " in r}
    assert r"\textbf{0.015}" in rows["seqA"]
    assert r"\textbf{0.05}" in rows["seqB"]
    assert r"\textbf{0.025}" not in rows["seqA"]
    assert "—" in to_markdown(t)  # missing shown as missing


def _latex(rep, name: str) -> str:
    from mutualslam_cli.report.tables import to_latex

    return to_latex(rep.tables[name], rep.titles[name], rep.bold.get(name))


def test_table5_map_points_and_esi(roots):
    rep = build_tables(collect(list(roots)))
    t = rep.tables["map_ba"]
    assert "config" not in t  # ba.culling is a row of this table, not a separate experiment
    assert list(t.columns) == ["BA", "MP culling", "max_fts", "seqA points", "seqA e_si", "seqB points",
                               "seqB e_si", "n"]
    rows = {(r["BA"], r["MP culling"]): r for _, r in t.iterrows()}
    assert set(t["max_fts"]) == {"500"}
    assert len(t) == 4
    vo = rows[("", "")]  # seqA seed 0 counted once although two runs share its front end
    assert vo["seqA points"] == 1100
    assert vo["seqA e_si"] == pytest.approx(0.55)
    assert vo["n"] == "2/1"
    assert rows[("", "✓")]["seqA points"] == 700
    assert rows[("", "✓")]["seqB e_si"] == pytest.approx(0.55)
    ba_only = rows[("✓", "")]
    assert ba_only["seqA points"] == 1000
    assert ba_only["seqA e_si"] == pytest.approx(0.45)
    assert np.isnan(ba_only["seqB points"])
    assert ba_only["n"] == "1/0"
    both = rows[("✓", "✓")]
    assert both["seqA e_si"] == pytest.approx(0.35)
    assert both["seqB points"] == 300
    assert np.isnan(both["seqB e_si"])
    md = to_markdown(t)
    line = next(ln for ln in md.splitlines() if ln.startswith("| ✓ |  |"))
    assert line.count("—") == 2
    assert " 0 " not in line
    tex = _latex(rep, "map_ba")
    assert r"\checkmark" in tex
    assert "--" in tex


def test_table5_blocks_per_max_fts_and_missing_config(tmp_path: Path, roots):
    other = tmp_path / "fts120"
    _run(other, "seqA", 0, True, _vals(0.02, 0.01, (700, 0.6), (400, 0.5), (400, 0.45)), max_fts=120)
    t = build_tables(collect([*roots, other])).tables["map_ba"]
    assert list(t["max_fts"]) == ["120"] * 4 + ["500"] * 4
    assert t.iloc[0]["seqA points"] == 700
    assert np.isnan(t.iloc[0]["seqB points"])
    damaged = roots[0] / "seqA" / "replay+ewc" / "seed0"
    (damaged / "config.yaml").write_text("vo: [unclosed\n")
    notes: list[str] = []
    runs = collect(list(roots), notes)  # the damaged run is skipped with its reason, the others reported
    assert str(damaged) not in set(runs["folder"])
    assert len(runs) == 3
    assert len(notes) == 1
    assert notes[0].startswith(f"skipped, damaged: {damaged / 'config.yaml'}:2: not valid YAML")
    with pytest.raises(DatasetError, match=r"config.yaml"):
        collect([damaged])  # nothing left to report


def test_map_figure_is_written_and_listed(roots, tmp_path: Path):
    folder = roots[0] / "seqA" / "replay+ewc" / "seed0"
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(400, 3)) * [1.0, 0.5, 0.3] + [0, 0, 3]
    err = rng.normal(scale=0.3, size=400)
    err[::7] = np.nan
    keep = rng.random(400) < 0.6
    write_ply(folder / "map_vo.ply", pts, err)
    write_ply(folder / "map_culled.ply", pts[keep], err[keep])
    write_ply(folder / "map_ba.ply", pts[keep] * 1.01, err[keep] * 0.8)
    (folder / "traj_kf.txt").write_text("0 0 0 0 0 0 0 1\n1 0.1 0 0 0 0 0 1\n2 0.2 0.05 0 0 0 0 1\n")
    nc = roots[1] / "seqA" / "replay+ewc" / "seed0"  # BA without culling: no map_culled.ply
    write_ply(nc / "map_vo.ply", pts, err)
    write_ply(nc / "map_ba.ply", pts, err)
    out = tmp_path / "rep"
    files = write_report(build_tables(collect(list(roots))), out)
    maps = sorted(f.name for f in files if f.parent.name == "maps")
    assert maps == ["maps_seqA_replay+ewc_ba.culling=False_seed0.png", "maps_seqA_replay+ewc_ba.culling=True_seed0.png"]
    for f in maps:
        assert (out / "maps" / f).stat().st_size > 10_000
        assert f"(maps/{f})" in (out / "report.md").read_text()
    assert "Paper Table 4" in (out / "report.md").read_text()
    assert (out / "map_ba.tex").is_file()
    assert yaml.safe_load((folder / "config.yaml").read_text())["ba"]["culling"] is True


def test_table4_average_without_any_ba(tmp_path: Path):
    """Runs without BA (none requested, or ba.enabled=false): "+ culling + BA" is missing, the Average still
    averages what there is."""
    _run(tmp_path, "seqA", 0, True, _vals(0.02, None, (10, 0.1), None, None))
    _run(tmp_path, "seqB", 0, True, _vals(0.04, None, (10, 0.1), None, None))
    t = build_tables(collect([tmp_path])).tables["ate_ba"]
    avg = t.iloc[-1]
    assert avg["Sequence"] == "Average"
    assert avg["VO"] == pytest.approx(0.03)
    assert np.isnan(avg["+ culling + BA"])
    assert "| Average | 0.03 | 0.03 | — |  |" in to_markdown(t)


def test_runs_with_different_thread_counts_are_not_averaged():
    """The numbers follow the thread count, so `threads` separates runs like any other setting."""
    import pandas as pd

    from mutualslam_cli.report.tables import config_labels

    runs = pd.DataFrame({"config.threads": [1, 1, 2], "config.seed": [0, 1, 0], "config.adapt.lr": [1e-3] * 3})
    assert config_labels(runs).tolist() == ["threads=1", "threads=1", "threads=2"]
    assert config_labels(runs.iloc[:2]).tolist() == ["", ""]  # seeds alone are one experiment


def test_table4_takes_loop_closure_from_the_loop_runs_of_the_same_config_paired_by_seed(tmp_path: Path):
    off, on = tmp_path / "off", tmp_path / "on"
    for seed, (vo, ba, lc) in enumerate([(0.03, 0.02, 0.008), (0.05, 0.04, 0.012), (0.04, 0.03, None)]):
        _run(off, "seqA", seed, True, _vals(vo, ba, (100, 0.5), (90, 0.4), (90, 0.3)))
        _run(on, "seqA", seed, True, _vals(vo, lc, (100, 0.5), (90, 0.4), (90, 0.3)), loop=True)
    t = build_tables(collect([off, on])).tables["ate_ba"]
    assert "config" not in t  # loop.enabled makes a column, not a block
    assert list(t.columns) == ["Sequence", "VO", "bridged", "+ culling + BA", "+ loop closure", "n"]
    a = t.iloc[0]  # seed 2 had no loop-closure value: every column over seeds 0 and 1
    assert a["n"] == 2
    assert a["VO"] == pytest.approx(0.04)
    assert a["+ culling + BA"] == pytest.approx(0.03)
    assert a["+ loop closure"] == pytest.approx(0.01)

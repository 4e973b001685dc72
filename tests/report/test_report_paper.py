"""The paper's tables in the paper's shape: mean ± std over seeds, the paper's numbers beside ours."""

from __future__ import annotations

import pandas as pd
import pytest

from mutualslam_cli.report import paper_numbers
from mutualslam_cli.report.paper import (
    cell,
    paper_tables,
    table1,
    table1_scalings,
    table2,
    table3,
    table4,
    table5,
    table6,
)


@pytest.mark.parametrize(("ours", "theirs"), [
    ("icl_lr_kt2", "ICL/living2"), ("living_room_kt0", "ICL/living0"), ("icl_of_kt1", "ICL/office1"),
    ("tum_fr3_long_office_household", "TUM/seq1"), ("rgbd_dataset_freiburg3_nostructure_texture_near_withloop",
                                                    "TUM/seq2"),
    ("tum_fr3_structure_texture_far", "TUM/seq3"), ("lab1", "Lab1"), ("Lab2_long", "Lab2"),
    ("tum_fr1_xyz", None), ("icl_of_kt3", None), ("redkitchen_7scenes", None)])
def test_paper_names(ours, theirs):
    assert paper_numbers.paper_name(ours) == theirs


def _runs() -> pd.DataFrame:
    rows = []
    for seq, pre, ad in (("icl_lr_kt2", 20.0, 40.0), ("tum_fr1_xyz", 25.0, 50.0)):
        for seed in (0, 1, 2):
            for scheme, gain in (("recent", -5.0), ("replay+ewc", 0.0)):
                rows.append({"sequence.name": seq, "scheme": scheme, "seed": seed, "config": "",
                             "depth.pcd.lsq.pretrained": pre, "depth.pcd.lsq.adapted": ad + gain + seed,
                             "depth.esi.pretrained": 0.3, "depth.esi.adapted": 0.2 + 0.01 * seed,
                             "trajectory.ate_rmse_m.vo": 0.02, "trajectory.ate_rmse_m.ba": 0.01 if seed else None,
                             "trajectory.credit.vo": 0.02 + 0.01 * (seed == 0), "trajectory.credit.bridged": 0.02,
                             "trajectory.credit.ba": 0.01 if seed else None,
                             "map.points.vo": 100.0, "map.points.ba": 90.0, "map.esi.vo": 0.2, "map.esi.ba": 0.15})
    return pd.DataFrame(rows)


def test_table1_mean_std_average_bold_and_paper_column():
    t = table1(_runs())
    d = t.display.set_index("Sequence")
    assert list(d.index) == ["icl_lr_kt2 (ICL/living2)", "tum_fr1_xyz", "Average"]
    assert d.loc["icl_lr_kt2 (ICL/living2)", "Ours"] == cell(41.0, 1.0, 3, 2) == "41.00 ± 1.00"
    assert d.loc["icl_lr_kt2 (ICL/living2)", "Pre-trained"] == "20.00 ± 0.00"  # one value per seed, not per scheme
    assert d.loc["icl_lr_kt2 (ICL/living2)", "paper: Ours"] == "25.16"
    assert d.loc["tum_fr1_xyz", "paper: Ours"] == "—"
    assert d.loc["Average", "Ours"] == "46.00"  # mean of the sequence means (41, 51)
    assert (0, "Ours") in t.bold
    assert (2, "Ours") in t.bold
    n = t.numeric.set_index("sequence")
    assert n.loc["tum_fr1_xyz", "Ours mean"] == pytest.approx(51.0)
    assert n.loc["tum_fr1_xyz", "Ours std"] == pytest.approx(1.0)
    assert n.loc["tum_fr1_xyz", "Ours n"] == 3


def test_missing_values_are_dashes_not_zeros_and_lower_is_better_for_ate():
    t = table4(_runs())
    d = t.display.set_index("Sequence")
    assert d.loc["tum_fr1_xyz", "With BA"] == "0.0100 ± 0.0000"  # seed 0 had no BA value: 2 of 3 seeds
    assert d.loc["tum_fr1_xyz", "VO"] == "0.0200 ± 0.0000"  # paired: seed 0 (VO 0.03) is left out of VO too
    n = t.numeric.set_index("sequence")
    assert n.loc["tum_fr1_xyz", "With BA n"] == n.loc["tum_fr1_xyz", "VO n"] == 2
    assert (1, "With BA") in t.bold  # lower ATE is better
    r = _runs().drop(columns="trajectory.credit.ba")
    d = table4(r).display.set_index("Sequence")
    assert set(d["With BA"]) == {"—"}
    assert d.loc["tum_fr1_xyz", "VO"] == "0.0233 ± 0.0058"


def test_table3_has_a_column_per_present_scheme_and_table6_methods_as_rows():
    t = table3(_runs())
    assert [c for c in t.display.columns if not c.startswith("paper")] == [
        "Sequence", "Pre-trained", "(a) recent", "(c) replay+ewc"]
    assert t.display.set_index("Sequence").loc["icl_lr_kt2 (ICL/living2)", "paper: (a)"] == "9.11"
    t6 = table6(_runs())
    assert list(t6.display["Method"]) == ["Pre-trained", "Ours"]
    assert t6.display.set_index("Method").loc["Ours", "tum_fr1_xyz"] == "0.210 ± 0.010"
    assert (1, "tum_fr1_xyz") in t6.bold


def test_table5_rows_from_culling_variants_and_max_fts():
    r = _runs()
    r = r[r["scheme"] == "replay+ewc"]
    off = r.assign(**{"config.ba.culling": False, "map.points.ba": 100.0, "map.esi.ba": 0.21})
    on = r.assign(**{"config.ba.culling": True})
    fts = on.assign(**{"config.vo.max_fts": 120})
    t = table5(pd.concat([on.assign(**{"config.vo.max_fts": 500}), off.assign(**{"config.vo.max_fts": 500}), fts]))
    d = t.display
    assert list(zip(d["BA"], d["MP culling"], d["max_fts"])) == [
        ("", "", "120"), ("✓", "✓", "120"), ("", "", "500"), ("✓", "", "500"), ("✓", "✓", "500")]
    assert d.iloc[3]["tum_fr1_xyz e_si"] == "0.210 ± 0.000"
    assert d.iloc[4]["tum_fr1_xyz points"] == "90 ± 0"


def test_paper_tables_skip_tables_without_values_and_split_config_groups():
    r = _runs().drop(columns=[f"trajectory.credit.{k}" for k in ("vo", "bridged", "ba")])
    names = [t.name for t in paper_tables(r)]
    assert "table4_ate_ba" not in names
    assert {"table1_pcd", "table3_schemes", "table6_esi"} <= set(names)
    r2 = pd.concat([r, r.assign(config="adapt.lr=0.0001")])
    titles = [t.title for t in paper_tables(r2) if t.name.startswith("table1_pcd")]
    assert len(titles) == 2
    assert any("adapt.lr=0.0001" in x for x in titles)
    assert cell(float("nan"), 0.0, 0, 2) == "—"
    assert cell(1.0, float("nan"), 1, 1) == "1.0"


def test_average_over_the_sequences_that_have_a_value_says_so():
    r = _runs()
    r.loc[r["sequence.name"] == "tum_fr1_xyz", "trajectory.credit.vo"] = None
    d = table4(r).display
    assert d.iloc[-1]["Sequence"] == "Average (1 of 2 sequences)"
    assert d.iloc[-1]["VO"] == "0.0200"
    assert table1(_runs()).display.iloc[-1]["Sequence"] == "Average"


def _with_external() -> pd.DataFrame:
    """_runs() plus an external model (mslam eval-depth) on both sequences and one on a Lab sequence only."""
    ext = [{"sequence.name": seq, "scheme": "midas", "seed": 0, "config": "", "external.model": "midas",
            "depth.pcd.lsq.pretrained": None, "depth.pcd.lsq.adapted": v, "depth.pcd.median.adapted": v - 1.0,
            "depth.esi.pretrained": None, "depth.esi.adapted": 0.1}
           for seq, v in (("icl_lr_kt2", 60.0), ("tum_fr1_xyz", 70.0))]
    ext.append({"sequence.name": "lab1", "scheme": "dpt", "seed": 0, "config": "", "external.model": "dpt",
                "depth.esi.adapted": 0.05})
    return pd.concat([_runs(), pd.DataFrame(ext)], ignore_index=True)


def test_external_models_are_columns_of_tables_1_and_2_and_rows_of_table_6():
    r = _with_external()
    d1 = table1(r).display.set_index("Sequence")
    assert d1.loc["tum_fr1_xyz", "midas (external, no adaptation)"] == "70.00"
    assert d1.loc["icl_lr_kt2 (ICL/living2)", "Pre-trained"] == "20.00 ± 0.00"  # the external nulls change nothing
    assert d1.loc["tum_fr1_xyz", "Ours"] == "51.00 ± 1.00"
    assert table2(r).display.set_index("Sequence").loc["icl_lr_kt2 (ICL/living2)",
                                                       "midas (external, no adaptation)"] == "59.00"
    t6 = table6(r)
    d6 = t6.display.set_index("Method")
    assert list(d6.index) == ["Pre-trained", "Ours", "dpt (external, no adaptation)",
                              "midas (external, no adaptation)"]
    assert d6.loc["midas (external, no adaptation)", "tum_fr1_xyz"] == "0.100"
    assert d6.loc["dpt (external, no adaptation)", "lab1 (Lab1)"] == "0.050"
    assert d6.loc["dpt (external, no adaptation)", "paper: Lab1"] == "—"
    assert d6.loc["Ours", "paper: Lab1"] == "0.235"
    assert (2, "lab1 (Lab1)") in t6.bold
    assert (3, "tum_fr1_xyz") in t6.bold
    assert "midas" not in " ".join(table3(r).display.columns)  # not an adaptation scheme


def test_without_external_models_the_tables_are_unchanged():
    assert list(table1(_runs()).display.columns) == ["Sequence", "Pre-trained", "Ours", "paper: Luo pre-trained",
                                                    "paper: Luo", "paper: Pre-trained", "paper: Ours"]
    assert list(table6(_runs()).display["Method"]) == ["Pre-trained", "Ours"]


def test_comoda_runs_add_a_column_to_tables_1_2_6_and_their_posenet_ate_to_table_4():
    r = _runs()
    com = r[r["scheme"] == "recent"].assign(scheme="comoda")
    com["trajectory.ate_rmse_m.posenet"] = 0.25
    com["depth.pcd.median.adapted"] = 12.5
    r = pd.concat([r, com])
    assert "CoMoDa-style (comoda)" in table1(r).display.columns
    d2 = table2(r).display.set_index("Sequence")
    assert list(d2.columns[:3]) == ["Pre-trained", "CoMoDa-style (comoda)", "Ours"]
    assert d2["CoMoDa-style (comoda)"].iloc[0].startswith("12.50")
    d4 = table4(r).display
    assert d4["PoseNet, all frames (comoda)"].iloc[0].startswith("0.2500")
    assert "CoMoDa-style (comoda)" in set(table6(r).display["Method"])
    assert "PoseNet, all frames (comoda)" not in table4(_runs()).display.columns


def test_table1_has_a_luo_style_column_when_luo_ran_and_the_papers_luo_numbers():
    r = _runs()
    r = pd.concat([r, r[r["scheme"] == "recent"].assign(scheme="luo")])
    d = table1(r).display.set_index("Sequence")
    assert list(d.columns[:3]) == ["Pre-trained", "Luo-style (luo)", "Ours"]
    assert d.loc["icl_lr_kt2 (ICL/living2)", "paper: Luo"] == "21.00"  # 20.995 in the paper
    assert "Luo-style (luo)" not in table1(_runs()).display.columns


def test_scalings_table_shows_each_scaling_beside_both_paper_tables():
    r = _runs().assign(**{"depth.pcd.seq_lsq.pretrained": 11.0, "depth.pcd.seq_lsq.adapted": 33.0})
    t = table1_scalings(r)
    assert {"Pre-trained lsq/sequence", "Ours lsq/sequence", "Pre-trained median/frame",
            "paper: T1 pre-trained", "paper: T2 pre-trained"} <= set(t.display.columns)
    assert "scale per sequence" in t.title
    assert "median" in t.title
    row = t.display.iloc[0]
    assert row["Pre-trained lsq/sequence"].startswith("11.00")
    assert row["Ours lsq/sequence"].startswith("33.00")
    assert row["Ours online lsq/frame"] == "—"  # no run has online scores: shown as absent, never 0
    icl = t.display[t.display["Sequence"].str.contains("icl_lr_kt2")].iloc[0]
    assert icl["paper: T1 pre-trained"] == "13.51"
    assert icl["paper: T2 pre-trained"] == "21.61"

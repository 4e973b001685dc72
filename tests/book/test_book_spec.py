"""Reading a book file strictly, and the refusals made before any work: a tuned preset on its own tuning data, a
variant folder whose runs were made under another config, an entry that does not exist."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from mutualslam_cli.book.plan import STAMP, config_hash, plan_book
from mutualslam_cli.book.spec import load_book
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.errors import ConfigError

SMOKE = CONFIG_DIR / "book_smoke.yaml"


def _book(tmp_path: Path, edit) -> Path:
    data = yaml.safe_load(SMOKE.read_text())
    edit(data)
    p = tmp_path / "book.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_the_smoke_book_reads():
    spec = load_book(SMOKE)
    assert spec.name == "smoke"
    assert set(spec.grids) == {"schemes", "slam"}
    assert spec.grids["slam"].variants["parts"] == ("ba.enabled=false",)
    assert spec.grids_for(["table4"]) == ["slam"]
    assert spec.grids_for(["T3"]) == ["schemes"]


@pytest.mark.parametrize(("edit", "match"), [
    (lambda d: d["grids"]["schemes"].update(colour="red"), "unknown key"),
    (lambda d: d["tables"]["table1"]["columns"][0].update(scheme="replay"), "not run by grid schemes"),
    (lambda d: d["tables"]["table4"]["columns"][0].update(variant="nope"), "variant 'nope'"),
    (lambda d: d["findings"]["T1"]["comparisons"][0]["a"].update(grid="nope"), "grid 'nope'"),
    (lambda d: d["findings"]["T1"]["comparisons"][0].update(better="more"), "higher or lower"),
    (lambda d: d["bounds"][0].update(column="Theirs"), "no column 'Theirs'"),
    (lambda d: d["grids"]["schemes"].update(seeds=[0, 0]), "seed 0 given twice"),
    (lambda d: d["grids"]["schemes"]["sequences"][0].update(size="big"), "expected WxH"),
    (lambda d: d["tables"]["table1"]["columns"][0].update(paper="table1.Theirs"), "none of the paper's numbers"),
])
def test_a_malformed_book_is_one_line_naming_the_place(tmp_path, edit, match):
    with pytest.raises(ConfigError, match=match):
        load_book(_book(tmp_path, edit))


def test_only_names_an_entry(tmp_path):
    with pytest.raises(ConfigError, match="not an entry"):
        load_book(SMOKE).grids_for(["table9"])


@pytest.mark.parametrize(("preset", "sequence"), [("configs/tuned.yaml", "tum_fr1_xyz"),
                                              ("configs/fast.yaml", "icl_lr_kt2")])
def test_a_tuned_preset_is_refused_on_its_tuning_data(tmp_path, preset, sequence):
    def edit(d):
        d["grids"]["schemes"].update(preset=preset, sequences=[sequence])
    spec = load_book(_book(tmp_path, edit))
    with pytest.raises(ConfigError, match=f"tuned on {sequence}"):
        plan_book(spec, tmp_path / "out", ["schemes"], render=False)


def test_a_preset_that_does_not_say_what_it_was_tuned_on_is_refused_on_real_data(tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("adapt:\n  lr: 1.0e-4\n")

    def edit(d):
        d["grids"]["schemes"].update(preset=str(mine), sequences=["redkitchen_7scenes"])
    with pytest.raises(ConfigError, match="no '# tuned-on:' header"):
        plan_book(load_book(_book(tmp_path, edit)), tmp_path / "out", ["schemes"], render=False)


def test_a_variant_folder_of_another_config_is_refused(tmp_path):
    spec = load_book(SMOKE)
    out = tmp_path / "out"
    plan = plan_book(spec, out, ["slam"])
    part = next(p for p in plan.parts if p.variant == "ba")
    assert json.loads((part.out / STAMP).read_text())["config_hash"] == part.config_hash
    plan_book(spec, out, ["slam"])  # the same config: resumes
    # an override on every grid (the CLI's --set); a variant's own settings come after it (the ba variant keeps 0.2)
    with pytest.raises(ConfigError, match=r"slam/parts: its runs were made under another config \(ba.d_max: 1.5 → 0.3"):
        plan_book(spec, out, ["slam"], overrides=["ba.d_max=0.3"])


def test_the_config_hash_follows_what_changes_numbers_only():
    a = load_config(CONFIG_DIR / "smoke.yaml")
    assert config_hash(a) == config_hash(load_config(CONFIG_DIR / "smoke.yaml", ["out=elsewhere"]))
    assert config_hash(a) != config_hash(load_config(CONFIG_DIR / "smoke.yaml", ["adapt.lr=0.01"]))


def test_the_full_book_reads_and_reports_no_preset_on_its_tuning_data():
    from mutualslam_cli.book.plan import _check_tuning, preset_path

    spec = load_book(CONFIG_DIR / "book.yaml")
    for g in spec.grids.values():
        _check_tuning(g, preset_path(g.preset, spec.path))  # raises on a tuned preset's own data
    assert {"T1", "T3", "T4", "T5", "F4"} <= set(spec.findings)
    assert "tum_fr1_xyz" not in {s.name for s in spec.grids["tuned"].sequences}
    assert {s.name for s in spec.grids["default"].sequences}.isdisjoint({"tum_fr1_xyz", "icl_lr_kt2"})
    assert [s.name for s in spec.grids["fast"].sequences] == ["redkitchen_7scenes"]
    assert len(spec.bounds) >= 10
    assert any(b.ci for b in spec.bounds)
    t4 = [c.label for c in spec.tables["table4"].columns]
    assert t4 == ["front end", "+ bridges", "+ merges", "+ culling + BA", "+ loops"]

"""``mslam book`` end to end on configs/book_smoke.yaml (rendered rooms, the oracle front end): killed midway it
resumes, reusing what completed, and publishes only once every job is complete; every published cell names the
runs it came from, and those runs hold its values."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from mutualslam_cli.book.plan import STAMP
from mutualslam_cli.book.run import read_book, run_book
from mutualslam_cli.book.spec import load_book
from mutualslam_cli.config import CONFIG_DIR
from mutualslam_cli.report.paired import HOLDS, UNDECIDED
from mutualslam_cli.results.summary import flatten

SMOKE = CONFIG_DIR / "book_smoke.yaml"


class Killed(KeyboardInterrupt):
    """What a kill (Ctrl-C, a lost machine) does to the book: it stops between two jobs."""


@pytest.fixture(scope="module")
def book(tmp_path_factory):
    out = tmp_path_factory.mktemp("book")
    spec = load_book(SMOKE)
    seen: list[str] = []

    def kill_after_two(o) -> None:
        seen.append(o.status)
        if len(seen) == 2:
            raise Killed

    with pytest.raises(Killed):
        run_book(spec, out, on_done=kill_after_two)
    first = {"book": (out / "book.json").exists(),
             "complete": sorted(p.parent.relative_to(out).as_posix() for p in (out / "runs").rglob("summary.json"))}
    # a job killed while it ran leaves its staging folder beside its run folder; the resumed book redoes that job
    staging = out / "runs" / "slam" / "ba" / "room10" / "replay+ewc" / ".seed0.staging-killed"
    staging.mkdir(parents=True)
    (staging / "per_frame.csv").write_text("half")
    res = run_book(spec, out)
    return out, first, res, staging


def test_a_killed_book_publishes_nothing_and_resumes_with_what_completed(book):
    out, first, res, staging = book
    assert not first["book"]
    assert len(first["complete"]) == 2
    statuses = {(Path(o.folder).relative_to(out).as_posix() if o.folder else None): o.status for o in res.outcomes}
    assert sorted(k for k, s in statuses.items() if s == "skipped") == first["complete"]
    assert sum(s == "done" for s in statuses.values()) == 6 - 2
    assert not res.failed
    assert not staging.exists()  # the half-written job was redone, its leftovers removed
    assert res.book_json == out / "book.json"
    assert (out / "book.json").is_file()


def test_every_entry_is_written_as_tables_figures_and_reports(book):
    out, _, _res, _ = book
    spec = load_book(SMOKE)
    for name in spec.tables:
        for ext in ("md", "tex", "csv"):
            assert (out / "tables" / f"{name}.{ext}").is_file(), (name, ext)
    assert (out / "tables" / "findings.md").is_file()
    assert (out / "figures" / "running_accuracy.png").is_file()
    for grid in spec.grids:
        assert (out / "reports" / grid / "report.md").is_file()
    t4 = pd.read_csv(out / "tables" / "table4.csv")
    assert {"front end (all) mean", "+ merges (all) mean", "+ culling + BA (KF) mean"} <= set(t4.columns)


def test_each_published_cell_names_its_runs_and_they_hold_its_values(book):
    out, _, _, _ = book
    b = read_book(out / "book.json")
    assert b["book"]["name"] == "smoke"
    assert b["book"]["file"] == "configs/book_smoke.yaml"
    checked = 0
    for t in b["tables"].values():
        for row in t["rows"][:-1]:  # the Average row averages the rows above
            for c in row["cells"]:
                stamp = json.loads((out / "runs" / c["grid"] / c["variant"] / STAMP).read_text())
                assert stamp["config_hash"] == c["config_hash"]
                assert c["schedule"] == "fixed"
                assert c["devices"]
                for v in c["values"]:
                    s = flatten(json.loads((out / "runs" / v["run"] / "summary.json").read_text()))
                    assert s["seed"] == v["seed"]
                    assert s[c["key"]] * c["scale"] == pytest.approx(v["value"])
                    checked += 1
                if c["values"]:
                    assert c["mean"] == pytest.approx(sum(v["value"] for v in c["values"]) / len(c["values"]))
    assert checked >= 20
    assert b["figures"]["running_accuracy"]["runs"]
    assert b["bounds"][0]["value"] > 0


def test_the_findings_are_judged_by_the_rule_on_paired_runs(book):
    out, _, _, _ = book
    f = read_book(out / "book.json")["findings"]
    assert set(f) == {"T1", "T3", "T4", "T5"}
    for finding in f.values():
        (c,) = finding["comparisons"]
        assert c["n"] == len(c["pairs"])
        assert c["wins"] + c["ties"] + c["losses"] == c["n"]
        assert finding["verdict"] == UNDECIDED != HOLDS  # one room, ≤ 2 seeds: never enough pairs for a verdict
        for p in c["pairs"]:
            assert p["diff"] == pytest.approx(p["a"] - p["b"])
    # T1 pairs each run with itself (two keys); T4 pairs a run of each variant, seed by seed
    assert all(p["folder_a"] == p["folder_b"] for p in f["T1"]["comparisons"][0]["pairs"])
    (p,) = f["T4"]["comparisons"][0]["pairs"]
    assert "/ba/" in p["folder_a"]
    assert "/parts/" in p["folder_b"]

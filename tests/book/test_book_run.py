"""``mslam book`` end to end on configs/book_smoke.yaml (rendered rooms, the oracle front end): killed midway it
resumes, reusing what completed, and publishes only once every job is complete; every published cell names the
runs it came from, and those runs hold its values."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from mutualslam_cli.book.build import MIXED
from mutualslam_cli.book.plan import STAMP, data_digest
from mutualslam_cli.book.records import job_state, read_record, write_record
from mutualslam_cli.book.run import read_book, run_book
from mutualslam_cli.book.spec import load_book
from mutualslam_cli.config import CONFIG_DIR
from mutualslam_cli.errors import DamagedRecord
from mutualslam_cli.report.paired import HOLDS, UNDECIDED
from mutualslam_cli.report.paper_numbers import TABLE1
from mutualslam_cli.results.fingerprint import code_fingerprint, code_manifest, fingerprint_of
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
        run_book(spec, out, on_done=kill_after_two, records=out / "records")
    first = {"book": (out / "book.json").exists(),
             "complete": sorted(p.parent.relative_to(out).as_posix() for p in (out / "runs").rglob("summary.json"))}
    # a job killed while it ran leaves its staging folder beside its run folder; the resumed book redoes that job
    staging = out / "runs" / "slam" / "ba" / "room10" / "replay+ewc" / ".seed0.staging-killed"
    staging.mkdir(parents=True)
    (staging / "per_frame.csv").write_text("half")
    res = run_book(spec, out, records=out / "records")
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
        for row in [r for r in t["rows"] if not r["label"].startswith(("Average", "paper:"))]:
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


def test_the_papers_own_numbers_stand_beside_ours(book):
    t = read_book(book[0] / "book.json")["tables"]["table1"]
    label, cells = t["rows"][-1]["label"], t["rows"][-1]["cells"]
    assert label == f"paper: Average ({len(TABLE1)} sequences)"
    ours = cells[t["columns"].index("Ours") - 1]
    assert ours["mean"] == pytest.approx(sum(v["Ours"] for v in TABLE1.values()) / len(TABLE1))
    assert cells[0]["text"] == "—"  # a column without a paper number


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


# --------------------------------------------------------------------------- the records: a book across checkouts


def _copy(book, tmp_path):
    """The finished book's folder, copied (these tests change it)."""
    out = tmp_path / "book"
    shutil.copytree(book[0], out)
    return out


def _records(out):
    return sorted((out / "records" / "smoke").rglob("seed*.json"))


def test_every_job_leaves_a_record_that_holds_its_figures(book):
    out = book[0]
    recs = _records(out)
    assert len(recs) == 6
    for path in recs:
        r = read_record(path)
        assert r.code == code_fingerprint()
        assert r.cpu_kind
        assert r.seconds
        assert r.seconds > 0
        s = flatten(json.loads((out / "runs" / r.grid / r.variant / r.sequence / r.scheme / f"seed{r.seed}"
                                / "summary.json").read_text()))
        assert r.summary["depth.pcd.lsq.adapted"] == pytest.approx(s["depth.pcd.lsq.adapted"])
        assert len(path.read_bytes()) < 40_000  # small enough to commit by the hundred
    assert (out / "records" / "code" / f"{code_fingerprint()}.json").is_file()


def test_a_fresh_checkout_resumes_from_the_records_alone_and_publishes_the_same_book(book, tmp_path):
    out = _copy(book, tmp_path)
    before = read_book(out / "book.json")
    for d in ("runs", "tables", "figures", "reports"):
        shutil.rmtree(out / d)
    (out / "book.json").unlink()
    res = run_book(load_book(SMOKE), out, records=out / "records")
    assert [o.status for o in res.outcomes] == ["skipped"] * 6  # nothing ran again
    after = read_book(out / "book.json")
    assert after["tables"] == before["tables"]
    assert after["findings"] == before["findings"]
    assert (out / "figures" / "running_accuracy.png").is_file()  # drawn from the records' curves


def test_a_record_of_other_code_is_stale_and_says_what_changed(book, tmp_path, monkeypatch):
    out = _copy(book, tmp_path)
    path = _records(out)[0]
    r = read_record(path)
    old = {**code_manifest(), "vo/tracker.py": "0" * 16}
    fp = fingerprint_of(old)
    (out / "records" / "code" / f"{fp}.json").write_text(json.dumps(old))
    write_record(out / "records", dataclasses.replace(r, code=fp))
    state = job_state(out / "records", "smoke", r.grid, r.variant, r.sequence, r.scheme, r.seed, r.config_hash)
    assert state.status == "stale"
    assert "vo/tracker.py" in state.why
    other = job_state(out / "records", "smoke", r.grid, r.variant, r.sequence, r.scheme, r.seed, "f" * 16)
    assert other.status == "stale"
    assert "config" in other.why


def test_a_record_made_on_other_sequence_files_is_stale(book, tmp_path):
    out = _copy(book, tmp_path)
    r = read_record(_records(out)[0])
    assert r.data == data_digest(out / "data" / r.sequence)
    state = job_state(out / "records", "smoke", r.grid, r.variant, r.sequence, r.scheme, r.seed, r.config_hash,
                      data="0" * 16)
    assert state.status == "stale"
    assert "other data" in state.why


def test_a_stale_record_is_run_again_and_replaced(book, tmp_path):
    out = _copy(book, tmp_path)
    path = next(p for p in _records(out) if "/parts/" in p.as_posix())
    r = read_record(path)
    write_record(out / "records", dataclasses.replace(r, code="0" * 16))
    run = out / "runs" / r.grid / r.variant / r.sequence / r.scheme / f"seed{r.seed}"
    man = json.loads((run / "manifest.json").read_text())
    (run / "manifest.json").write_text(json.dumps({**man, "code_fingerprint": "0" * 16}))  # its folder: old code too
    res = run_book(load_book(SMOKE), out, only=["slam"], records=out / "records")
    assert sorted(o.status for o in res.outcomes) == ["done", "skipped"]
    assert (run.parent / ".seed0.stale" / "summary.json").is_file()  # set aside, not deleted
    again = read_record(path)
    assert again.code == code_fingerprint()
    assert again.summary["trajectory.credit.vo"] == pytest.approx(r.summary["trajectory.credit.vo"])  # deterministic
    assert res.book_json is not None


@pytest.mark.parametrize(("edit", "match"), [
    (lambda d: d["summary"].update({"depth.pcd.lsq.adapted": 99.0}), "digest does not match"),
    (lambda d: d.pop("code"), "fields code missing"),
    (lambda d: d.update(format=7), "not a book record of format 1"),
])
def test_a_damaged_or_hand_written_record_is_refused_naming_it(book, tmp_path, edit, match):
    out = _copy(book, tmp_path)
    path = _records(out)[0]
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(DamagedRecord, match=match) as e:
        run_book(load_book(SMOKE), out, records=out / "records")
    assert str(path) in str(e.value)
    assert len(str(e.value).splitlines()) == 1


def test_a_record_in_the_wrong_place_is_refused(book, tmp_path):
    out = _copy(book, tmp_path)
    a, b = _records(out)[:2]
    shutil.copyfile(a, b)
    with pytest.raises(DamagedRecord, match="not of this place"):
        read_record(b)


def test_a_finished_run_without_a_record_is_recorded_not_rerun(book, tmp_path):
    out = _copy(book, tmp_path)
    path = _records(out)[0]
    path.unlink()  # killed between the run's end and its record
    res = run_book(load_book(SMOKE), out, records=out / "records")
    assert [o.status for o in res.outcomes] == ["skipped"] * 6
    assert path.is_file()


def test_cells_whose_seeds_ran_on_two_cpu_kinds_say_so(book, tmp_path):
    out = _copy(book, tmp_path)
    path = next(p for p in _records(out) if "/schemes/" in p.as_posix() and p.name == "seed1.json"
                and "replay+ewc" in p.as_posix())
    write_record(out / "records", dataclasses.replace(read_record(path), cpu_kind="AVX2"))
    run_book(load_book(SMOKE), out, records=out / "records")
    cell = read_book(out / "book.json")["tables"]["table1"]["rows"][0]["cells"][1]
    assert len(cell["cpu_kinds"]) == 2
    assert "AVX2" in cell["cpu_kinds"]
    assert cell["text"].endswith(MIXED)


def test_the_dry_run_counts_the_records_and_says_why_one_is_stale(book, tmp_path):
    from typer.testing import CliRunner

    from mutualslam_cli.cli import app

    out = _copy(book, tmp_path)
    path = next(p for p in _records(out) if "/parts/" in p.as_posix())
    write_record(out / "records", dataclasses.replace(read_record(path), config_hash="0" * 16))
    r = CliRunner().invoke(app, ["book", str(SMOKE), "--out", str(out), "--records", str(out / "records"),
                                 "--dry-run"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "6 jobs in all: 5 complete from the records" in r.output
    assert "slam/parts: 1 jobs, 0 complete, 1 stale, 0 to run" in r.output
    assert "made under config 0000000000000000" in r.output


def test_a_damaged_record_stops_the_command_in_one_line(book, tmp_path):
    from typer.testing import CliRunner

    from mutualslam_cli.cli import app

    out = _copy(book, tmp_path)
    path = _records(out)[0]
    path.write_text(path.read_text()[:-40])
    r = CliRunner().invoke(app, ["book", str(SMOKE), "--out", str(out), "--records", str(out / "records")],
                           env={"COLUMNS": "300"})
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1, r.output
    assert lines[0].startswith("error:")
    assert path.name in lines[0]
    assert "not a readable JSON record" in lines[0]


def test_a_job_recorded_elsewhere_meanwhile_is_not_run_again(book, tmp_path):
    out = _copy(book, tmp_path)
    paths = {v: next(p for p in _records(out) if f"/slam/{v}/" in p.as_posix()) for v in ("parts", "ba")}
    recs = {v: read_record(p) for v, p in paths.items()}
    for v, p in paths.items():
        p.unlink()
        r = recs[v]
        shutil.rmtree(out / "runs" / r.grid / r.variant / r.sequence / r.scheme / f"seed{r.seed}")
    def another_machine_finishes_ba(_o) -> None:  # while this book runs the first variant
        write_record(out / "records", recs["ba"])

    res = run_book(load_book(SMOKE), out, only=["slam"], records=out / "records",
                   on_done=another_machine_finishes_ba)
    assert [(o.job.scheme, o.status) for o in res.outcomes] == [("replay+ewc", "done"), ("replay+ewc", "skipped")]
    assert res.book_json is not None

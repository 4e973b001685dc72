"""``mslam report`` reports what it can: a damaged run is listed with its reason and skipped, the others are
reported, a value that is not a finite number is an empty cell with a note, and a bad ``--out`` is refused
before any work (issue 48, kind 4)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.report.tables import build_tables, collect, write_report
from mutualslam_cli.results.run_folder import run_dir, write_json
from mutualslam_cli.results.summary import Summary

runner = CliRunner()


def _run(root: Path, seq: str, scheme: str, values: dict[str, float]) -> Path:
    folder = run_dir(root, seq, scheme, 0)
    folder.mkdir(parents=True)
    s = Summary()
    for k, v in {"sequence.name": seq, "scheme": scheme, "seed": 0, **values}.items():
        s.set(k, v)
    write_json(folder / "summary.json", s.to_dict())
    return folder


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """Two good runs, one summary that is not JSON, one that is a list, one that is a string."""
    root = tmp_path / "results"
    _run(root, "room", "none", {"depth.pcd.lsq.adapted": 30.0, "timing.depth_ms": 12.0})
    _run(root, "room", "replay+ewc", {"depth.pcd.lsq.adapted": 40.0, "timing.depth_ms": 14.0})
    for seq, text in (("torn", '{"depth": {"pcd": '), ("listed", "[1, 2, 3]"), ("worded", '"complete"')):
        folder = run_dir(root, seq, "none", 0)
        folder.mkdir(parents=True)
        (folder / "summary.json").write_text(text)
    return root


def test_damaged_runs_are_skipped_with_their_reason_and_the_rest_reported(tree: Path):
    notes: list[str] = []
    runs = collect([tree], notes)
    assert sorted(runs["scheme"]) == ["none", "replay+ewc"]
    assert set(runs["sequence.name"]) == {"room"}
    assert sorted(notes) == sorted([
        f"skipped, damaged: {run_dir(tree, 'listed', 'none', 0) / 'summary.json'}: a JSON list, not an object of "
        "metrics (the summary of mslam run)",
        f"skipped, damaged: {run_dir(tree, 'torn', 'none', 0) / 'summary.json'}: not valid JSON (Expecting value: "
        "line 1 column 19 (char 18))",
        f"skipped, damaged: {run_dir(tree, 'worded', 'none', 0) / 'summary.json'}: a JSON str, not an object of "
        "metrics (the summary of mslam run)"])


def test_nothing_readable_is_the_only_error(tmp_path: Path, tree: Path):
    with pytest.raises(DatasetError, match=r"no complete run to report \(1 damaged, none readable \(.*a JSON list"):
        collect([run_dir(tree, "listed", "none", 0)])


def test_staging_folders_and_the_cache_are_never_reported(tmp_path: Path, tree: Path):
    stage = tree / "room" / "none" / ".seed0.staging-abc"  # a run killed between its summary and its rename
    stage.mkdir()
    (stage / "summary.json").write_text(json.dumps({"scheme": "none", "sequence": {"name": "room"}}))
    (tree / "_cache" / "x").mkdir(parents=True)
    (tree / "_cache" / "x" / "summary.json").write_text("{}")
    runs = collect([tree])
    assert len(runs) == 2
    assert not any(".staging" in f or "_cache" in f for f in runs["folder"])


def test_non_finite_values_are_empty_cells_with_the_reason_in_the_notes(tmp_path: Path, tree: Path):
    bad = run_dir(tree, "room", "none", 0) / "summary.json"
    s = json.loads(bad.read_text())
    s["timing"]["depth_ms"] = float("inf")  # json.dumps writes Infinity: what another tool may leave
    s["depth"]["pcd"]["lsq"]["adapted"] = float("nan")
    bad.write_text(json.dumps(s))
    notes: list[str] = []
    rep = build_tables(collect([tree], notes), notes)
    write_report(rep, tmp_path / "rep")
    runtime = (tmp_path / "rep" / "runtime.csv").read_text()
    assert "inf" not in runtime.lower()
    assert "nan" not in runtime.lower()
    table = pd.read_csv(tmp_path / "rep" / "runtime.csv")
    row = table[table["scheme"] == "none"].iloc[0]
    assert pd.isna(row["depth ms"])
    assert table[table["scheme"] == "replay+ewc"].iloc[0]["depth ms"] == 14.0
    depth = pd.read_csv(tmp_path / "rep" / "depth.csv")
    assert pd.isna(depth[depth["scheme"] == "none"].iloc[0]["PCD lsq adapt"])
    md = (tmp_path / "rep" / "report.md").read_text()
    for key, value in (("timing.depth_ms", "inf"), ("depth.pcd.lsq.adapted", "nan")):
        line = f"{bad}: {key} is {value}, not a finite number; its cells are left empty"
        assert line in notes
        assert f"- {line}" in md


def test_a_table_value_that_overflows_is_an_empty_cell_with_a_note(tmp_path: Path):
    root = tmp_path / "results"
    for seed in (0, 1):  # two finite values whose mean is not: 1e308 + 1e308 overflows
        folder = run_dir(root, "room", "none", seed)
        folder.mkdir(parents=True)
        write_json(folder / "summary.json", {"sequence": {"name": "room"}, "scheme": "none", "seed": seed,
                                              "timing": {"depth_ms": 1.7e308}})
    rep = build_tables(collect([root]))
    write_report(rep, tmp_path / "rep")
    assert "inf" not in (tmp_path / "rep" / "runtime.csv").read_text()
    assert "runtime.csv: column 'depth ms' had a value that is not a finite number; its cell is left empty" in rep.notes


def test_cli_reports_the_good_runs_lists_the_damaged_and_exits_0(tree: Path, tmp_path: Path):
    r = runner.invoke(app, ["report", str(tree), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output
    assert (tmp_path / "rep" / "depth.csv").is_file()
    skipped = [ln for ln in r.stderr.splitlines() if ln.startswith("note: skipped, damaged:")]
    assert len(skipped) == 3
    assert any("torn" in ln and "not valid JSON" in ln for ln in skipped)
    assert "40" in r.stdout
    assert "(3 notes in report.md)" in r.stdout


def test_cli_exits_1_when_nothing_could_be_reported(tmp_path: Path, tree: Path):
    r = runner.invoke(app, ["report", str(run_dir(tree, "torn", "none", 0)), "--out", str(tmp_path / "rep")])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 1
    assert len(lines) == 1
    assert lines[0].startswith("error:")
    assert "not valid JSON" in lines[0]
    assert not (tmp_path / "rep").exists()


def test_cli_refuses_an_out_that_is_a_file_before_any_work(tree: Path, tmp_path: Path):
    f = tmp_path / "report.txt"
    f.write_text("keep me\n")
    r = runner.invoke(app, ["report", str(tree), "--out", str(f)])
    assert r.exit_code == 1
    assert r.output.splitlines() == [
        f"error: {f}: is a file, not a folder for the report; choose another --out (a folder, created when missing)"]
    assert f.read_text() == "keep me\n"  # and no table was printed before the refusal


def test_a_summary_that_is_not_utf8_or_a_folder_is_skipped_too(tmp_path: Path, tree: Path):
    run_dir(tree, "torn", "none", 0).joinpath("summary.json").write_bytes(b'{"scheme": "caf\xe9"}')
    odd = run_dir(tree, "odd", "none", 0) / "summary.json"
    odd.mkdir(parents=True)  # a folder of that name
    notes: list[str] = []
    assert len(collect([tree], notes)) == 2
    assert any("torn" in n and "not UTF-8 text (byte 0xe9" in n for n in notes)
    assert any("odd" in n and "cannot be read" in n for n in notes)

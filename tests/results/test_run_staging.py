"""End to end: a run's folder changes only when the run completes — a failed ``--force`` keeps the old run byte
for byte, a failed first run leaves no run folder, a write error is one line naming the path (issue 48, kind 3)."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest
from test_staging import digest
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.errors import DatasetError, OutputError
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.results.run_folder import is_complete, run_dir


@pytest.fixture(scope="module")
def seq_and_run(tiny_run, tmp_path_factory):
    """A copy of the tiny sequence (its frames get damaged here) and one complete run of it."""
    tmp, seq = tiny_run
    own = tmp_path_factory.mktemp("staging") / "seq"
    shutil.copytree(seq, own)
    out = own.parent / "res"
    r = run_sequence(own, _cfg(tmp), out=out)
    return tmp, own, out, r.folder


def _cfg(tmp: Path, *extra: str):
    return load_config(CONFIG_DIR / "smoke.yaml", [f"net.weights={tmp / 'weights'}", *extra])


def _truncate_a_frame(seq: Path) -> tuple[Path, bytes]:
    frame = sorted((seq / "rgb").iterdir())[5]
    data = frame.read_bytes()
    frame.write_bytes(data[:100])
    return frame, data


def _siblings(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir())


def test_a_failed_force_leaves_the_old_run_byte_identical(seq_and_run):
    tmp, seq, out, folder = seq_and_run
    before = digest(folder)
    frame, data = _truncate_a_frame(seq)
    try:
        with pytest.raises(DatasetError, match="truncated PNG"):
            run_sequence(seq, _cfg(tmp, "adapt.steps_per_keyframe=3"), out=out, force=True)
    finally:
        frame.write_bytes(data)
    assert digest(folder) == before  # config.yaml included: it still matches the summary beside it
    assert _siblings(folder) == [".seed0.lock", "seed0"]  # the staging folder is gone


def test_a_write_error_mid_run_is_one_line_and_keeps_the_old_run(seq_and_run, monkeypatch):
    import mutualslam_cli.stages.run_record as run_record

    tmp, seq, out, folder = seq_and_run
    before = digest(folder)

    def full(path, obj):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(run_record, "write_json", full)
    with pytest.raises(OutputError) as e:
        run_sequence(seq, _cfg(tmp, "adapt.steps_per_keyframe=3"), out=out, force=True)
    assert str(e.value) == (f"{out}: cannot write: No space left on device; free space there (or choose another "
                            "--out) and run again; the previous run in it is as it was")
    assert digest(folder) == before
    assert _siblings(folder) == [".seed0.lock", "seed0"]


def test_a_failed_first_run_leaves_no_run_folder(seq_and_run):
    tmp, seq, out, _ = seq_and_run
    frame, data = _truncate_a_frame(seq)
    try:
        with pytest.raises(DatasetError):
            run_sequence(seq, _cfg(tmp, "seed=7"), out=out)
    finally:
        frame.write_bytes(data)
    folder = run_dir(out, seq.name, "replay+ewc", 7)
    assert not folder.exists()
    assert ".seed7.lock" in _siblings(folder)
    assert not [n for n in _siblings(folder) if n.startswith(".seed7.staging")]


def test_a_forced_run_that_completes_replaces_the_old_one(seq_and_run):
    tmp, seq, out, _folder = seq_and_run
    r = run_sequence(seq, _cfg(tmp, "seed=3"), out=out)
    before = digest(r.folder)
    again = run_sequence(seq, _cfg(tmp, "seed=3", "adapt.steps_per_keyframe=3"), out=out, force=True)
    assert again.folder == r.folder
    assert is_complete(r.folder)
    assert digest(r.folder) != before
    assert "steps_per_keyframe: 3" in (r.folder / "config.yaml").read_text()
    assert [n for n in _siblings(r.folder) if "seed3" in n] == [".seed3.lock", "seed3"]


def test_cli_out_that_is_a_file_is_one_line_before_any_work(seq_and_run, tmp_path: Path):
    tmp, seq, _, _ = seq_and_run
    f = tmp_path / "res"
    f.write_text("not a folder\n")
    r = CliRunner().invoke(app, ["run", str(seq), "--config", str(CONFIG_DIR / "smoke.yaml"), "--out", str(f),
                                 "--set", f"net.weights={tmp / 'weights'}"])
    lines = [ln for ln in r.output.splitlines()]
    assert r.exit_code == 1, r.output
    assert lines == [f"error: {f}: is a file, not a folder for the results; choose another "
                                          "--out (a folder, created when missing)"], r.output
    assert f.read_text() == "not a folder\n"


def test_a_failed_grid_job_leaves_no_run_folder_and_a_rerun_completes(seq_and_run, tmp_path: Path):
    from mutualslam_cli.ablate import expand, run_grid

    tmp, seq, _, _ = seq_and_run
    out = tmp_path / "grid"
    frame, data = _truncate_a_frame(seq)
    try:
        first = run_grid(_cfg(tmp), expand([str(seq)], ["none"], [0]), out)
    finally:
        frame.write_bytes(data)
    assert [o.status for o in first] == ["failed"]
    assert "truncated PNG" in first[0].error
    folder = run_dir(out, seq.name, "none", 0)
    assert not folder.exists()
    assert _siblings(folder) == [".seed0.lock"]
    second = run_grid(_cfg(tmp), expand([str(seq)], ["none"], [0]), out)
    assert [o.status for o in second] == ["done"]
    assert is_complete(folder)
    assert [o.status for o in run_grid(_cfg(tmp), expand([str(seq)], ["none"], [0]), out)] == ["skipped"]

"""The result-folder lock: a second holder stops with the first one's pid; a killed holder frees it at once."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.errors import MslamError, ResultsLocked
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.results.lock import LOCK_NAME, hold_lock, read_holder
from mutualslam_cli.results.run_folder import is_complete, run_dir, write_json

HOLDER = textwrap.dedent("""
    import sys
    from mutualslam_cli.results.lock import hold_lock
    with hold_lock(sys.argv[1], "test holder"):
        print("locked", flush=True)
        sys.stdin.read()  # holds the lock until the test closes our stdin or kills us
""")


@pytest.fixture
def holder(tmp_path):
    """Another process holding the lock of ``tmp_path / "run"``; killed with SIGKILL at the end."""
    folder = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "locked"
        yield folder, proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=600)
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                stream.close()


def test_second_holder_gets_one_line_with_the_pid(holder):
    folder, proc = holder
    with pytest.raises(ResultsLocked) as info, hold_lock(folder, "mslam run"):
        pytest.fail("the lock was taken twice")
    msg = str(info.value)
    assert isinstance(info.value, MslamError)
    assert "\n" not in msg
    for needle in (str(folder), f"pid {proc.pid}", "test holder", os.uname().nodename, "Wait for it to finish"):
        assert needle in msg, (needle, msg)
    assert read_holder(folder)["pid"] == proc.pid  # the failed attempt did not overwrite the holder's note


def test_lock_is_free_at_once_after_the_holder_is_killed(holder):
    folder, proc = holder
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=600)
    assert (folder / LOCK_NAME).is_file()  # the file stays behind ...
    with hold_lock(folder, "mslam run"):  # ... and does not block
        assert read_holder(folder)["pid"] == os.getpid()
        assert read_holder(folder)["what"] == "mslam run"


def test_leftover_lock_file_does_not_block(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / LOCK_NAME).write_text(json.dumps({"pid": 1, "host": "elsewhere", "since": "2000-01-01T00:00:00"}))
    with hold_lock(folder, "mslam run"):
        assert read_holder(folder)["pid"] == os.getpid()


def test_not_reentrant_and_released_on_error(tmp_path):
    folder = tmp_path / "a" / "b"  # created when missing
    with pytest.raises(RuntimeError, match="boom"), hold_lock(folder, "outer"):  # noqa: PT012
        with pytest.raises(ResultsLocked, match=f"pid {os.getpid()}"), hold_lock(folder, "inner"):
            pass
        raise RuntimeError("boom")
    with hold_lock(folder, "again"):  # released by the exception
        pass


def test_lock_file_does_not_make_a_folder_complete(tmp_path):
    folder = tmp_path / "run"
    with hold_lock(folder, "mslam run"):
        assert not is_complete(folder)
    assert (folder / LOCK_NAME).is_file()
    assert not is_complete(folder)
    write_json(folder / "summary.json", {"done": True})
    with hold_lock(folder, "mslam run"):
        assert is_complete(folder)


# ----------------------------------------------------------------------------- the run folder


@pytest.fixture
def locked_run(tmp_path):
    """A tiny sequence, its run folder under ``tmp_path / "res"`` and the smoke config; the folder is locked as a
    run locks it (the lock file beside the folder, which a completing run replaces whole)."""
    seq = make_tum_dir(tmp_path, scene="room", n=6, width=64, height=48)
    cfg = load_config(CONFIG_DIR / "smoke.yaml")
    folder = run_dir(tmp_path / "res", seq.name, cfg.adapt.scheme, cfg.seed)
    with hold_lock(folder, "another mslam run", beside=True):
        yield seq, cfg, folder


def test_run_sequence_on_a_locked_folder_touches_nothing(locked_run, tmp_path):
    seq, cfg, folder = locked_run
    with pytest.raises(ResultsLocked, match="another mslam run"):
        run_sequence(seq, cfg, out=tmp_path / "res")
    assert not folder.exists()  # the run folder itself is made only by a run that completes
    assert sorted(p.name for p in folder.parent.iterdir()) == [f".{folder.name}{LOCK_NAME}"]
    assert not (tmp_path / "res" / "_cache").exists()  # not even the front end ran


def test_cli_run_on_a_locked_folder_is_one_red_line(locked_run, tmp_path):
    seq, _, _folder = locked_run
    r = CliRunner().invoke(app, ["run", str(seq), "--config", str(CONFIG_DIR / "smoke.yaml"),
                                 "--out", str(tmp_path / "res")])
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output, r.output
    text = " ".join(r.output.split())
    assert text.startswith("error:"), r.output
    assert f"pid {os.getpid()}" in text, r.output
    assert "is locked by" in text, r.output

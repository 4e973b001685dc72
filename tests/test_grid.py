"""The grid's executors and its behaviour when stopped: resume, no orphans, one grid per folder."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from mutualslam_cli.ablate import expand, run_grid
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.errors import ConfigError, ResultsLocked
from mutualslam_cli.grid_plan import plan_grid
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.summary import flatten


@pytest.fixture(scope="module")
def setup(tiny_run):
    return tiny_run


def _sets(tmp: Path) -> list[str]:
    return [f"net.weights={tmp / 'weights'}"]


def _comparable(folder: Path) -> dict:
    """A run's summary without its timings, and without the notes on timings: which of two parallel jobs
    evaluates the pre-trained model and which reads it from the cache ("timing.depth_ms: not computed")
    depends on the order the workers get to it."""
    s = flatten(json.loads((folder / "summary.json").read_text()))
    out = {k: v for k, v in s.items() if not k.startswith("timing.")}
    if isinstance(out.get("notes"), dict):
        out["notes"] = {k: v for k, v in out["notes"].items() if not k.startswith("timing.")}
    return out


def test_plan_grid_reads_the_experiment_and_expands_variants(setup, tmp_path):
    _tmp, seq = setup
    cfg = load_config(CONFIG_DIR / "table5_map.yaml")
    parts = plan_grid(cfg, [str(seq)], None, None, tmp_path)
    assert [p.label for p in parts] == ["fts500", "fts500_no_culling", "fts120", "fts120_no_culling"]
    assert [p.out for p in parts] == [tmp_path / p.label for p in parts]
    assert [(p.cfg.vo.max_fts, p.cfg.ba.culling) for p in parts] == [(500, True), (500, False), (120, True),
                                                                     (120, False)]
    assert {(j.scheme, j.seed) for j in parts[0].jobs} == {("replay+ewc", k) for k in (0, 1, 2)}
    one = plan_grid(load_config(), [str(seq)], "none,replay", "3-4", tmp_path)
    assert len(one) == 1
    assert one[0].out == tmp_path
    assert {j.seed for j in one[0].jobs} == {3, 4}
    with pytest.raises(ConfigError, match=r"unknown scheme|not a scheme|valid"):
        plan_grid(load_config(), [str(seq)], "nope", None, tmp_path)
    with pytest.raises(ConfigError, match="--seeds"):
        plan_grid(load_config(), [str(seq)], None, "a-b", tmp_path)


@pytest.mark.parametrize(("schemes", "seeds", "message"), [
    (None, "3-1", r"^--seeds '3-1': the range is empty \(1 < 3\), so the grid would run nothing; expected e.g. 1-3$"),
    (",", None, r"^--schemes ',': names no scheme, so the grid would run nothing"),
    (" , ,", None, r"^--schemes ' , ,': names no scheme"),
    ("none,none", None, r"^--schemes 'none,none': none given twice"),
    (None, "0,0", r"^--seeds '0,0': a seed is given twice"),
    (None, "0,4294967296", r"^--seeds '0,4294967296': seed 4294967296 is outside 0..4294967295$"),
    (None, "0-99999999999", r"^--seeds '0-99999999999': 100000000000 seeds; a grid runs at most 10000$"),
])
def test_a_grid_that_would_run_nothing_or_twice_is_refused(setup, tmp_path, schemes, seeds, message):
    _tmp, seq = setup
    with pytest.raises(ConfigError, match=message):
        plan_grid(load_config(), [str(seq)], schemes, seeds, tmp_path)


def test_cli_refuses_an_empty_grid_with_exit_1_and_keeps_typers_usage_errors_at_2(setup, tmp_path):
    from typer.testing import CliRunner

    from mutualslam_cli.cli import app

    _tmp, seq = setup
    out = tmp_path / "grid"
    for args, needle in ((["--seeds", "3-1"], "--seeds '3-1': the range is empty"),
                         (["--schemes", ","], "--schemes ',': names no scheme")):
        r = CliRunner().invoke(app, ["ablate", str(seq), "--out", str(out), *args])
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert r.exit_code == 1, r.output
        assert len(lines) == 1, r.output
        assert lines[0].startswith("error:"), r.output
        assert needle in lines[0], r.output
        assert "0 jobs" not in r.output
        assert not out.exists()
    r = CliRunner().invoke(app, ["ablate", str(seq), "--out", str(out), "-j", "0"])
    assert r.exit_code == 2
    assert not out.exists()


def test_a_second_grid_on_the_same_folder_stops_at_once(setup, tmp_path):
    tmp, seq = setup
    cfg = load_config(CONFIG_DIR / "smoke.yaml", _sets(tmp))
    with hold_lock(tmp_path, "another grid"), pytest.raises(ResultsLocked, match=str(os.getpid())):
        run_grid(cfg, expand([str(seq)], ["none"], [0]), tmp_path)
    assert not list(tmp_path.rglob("summary.json"))


# slow (~45 s in CI: a local Dask cluster starts); the Dask jobs' resources are checked in CI by tests/test_device.py
@pytest.mark.slow
def test_dask_local_cluster_gives_the_summaries_of_the_local_pool(setup, tmp_path):
    pytest.importorskip("dask.distributed")
    tmp, seq = setup
    cfg = load_config(CONFIG_DIR / "smoke.yaml", _sets(tmp))
    jobs = expand([str(seq)], ["none", "replay"], [0])
    local = run_grid(cfg, jobs, tmp_path / "local", workers=2)
    dask = run_grid(cfg, jobs, tmp_path / "dask", workers=2, executor="dask")
    assert sorted(o.status for o in local) == sorted(o.status for o in dask) == ["done", "done"]
    for o in local:
        other = tmp_path / "dask" / o.folder.relative_to(tmp_path / "local")
        assert _comparable(o.folder) == _comparable(other)
        assert (o.folder / "per_frame.csv").read_bytes() == (other / "per_frame.csv").read_bytes()
    with pytest.raises(ConfigError, match="executor"):
        run_grid(cfg, jobs, tmp_path / "x", executor="slurm")


def _tree(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _alive(p: psutil.Process) -> bool:
    try:
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _digest(folder: Path) -> dict[str, str]:
    return {str(f.relative_to(folder)): hashlib.sha1(f.read_bytes()).hexdigest()
            for f in sorted(folder.rglob("*")) if f.is_file() and f.name != ".lock"}


GATE_DIR = Path(__file__).parent / "gate"


def _gated_env(gate: Path, passing: str = "") -> dict[str, str]:
    """Environment of a grid whose jobs stop at the gate of ``tests/gate/sitecustomize.py``."""
    gate.mkdir()
    path = os.pathsep.join(filter(None, [str(GATE_DIR), os.environ.get("PYTHONPATH", "")]))
    return {**os.environ, "PYTHONPATH": path, "MSLAM_TEST_GATE": str(gate), "MSLAM_TEST_GATE_PASS": passing,
            "COLUMNS": "300"}


def _wait_for(what: str, ready, proc: subprocess.Popen, limit_s: float = 600.0) -> None:
    """Wait until ``ready()``; fail if the grid exits first (the limit only ends a hung test)."""
    deadline = time.monotonic() + limit_s
    while not ready():
        assert proc.poll() is None, f"the grid exited (code {proc.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} after {limit_s:.0f} s"
        time.sleep(0.1)


def _blocked_pids(gate: Path) -> set[str]:
    return {f.name.rsplit("-", 1)[1] for f in gate.glob("started-*")}


def _gone(workers: list[psutil.Process], limit_s: float = 60.0) -> list[int]:
    """Pids among ``workers`` still alive after up to ``limit_s`` (the kernel reaps them at once)."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline and any(_alive(p) for p in workers):
        time.sleep(0.1)
    return [p.pid for p in workers if _alive(p)]


@pytest.mark.slow  # ~45 s: CI keeps the budget with test_ctrl_c_stops_the_workers... and test_ablate_grid_resumes
def test_sigkill_mid_grid_leaves_no_process_and_a_rerun_completes(setup, tmp_path):
    tmp, seq = setup
    out, gate = tmp_path / "out", tmp_path / "gate"
    cmd = [sys.executable, "-m", "mutualslam_cli.cli", "ablate", str(seq), "--schemes",
           "none,recent,replay,replay+ewc", "--seeds", "0", "-j", "2", "--out", str(out),
           "--config", str(CONFIG_DIR / "smoke.yaml"), "--set", _sets(tmp)[0]]
    # `none` runs through; every other job waits at the gate: one job complete, both workers mid-job
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env=_gated_env(gate, "none"))
    try:
        _wait_for("a complete job and two workers at the gate",
                  lambda: list(out.rglob("summary.json")) and len(_blocked_pids(gate)) >= 2, proc)
        workers = _tree(proc.pid)
        assert {str(p.pid) for p in workers} >= _blocked_pids(gate)
        finished = {f.parent: _digest(f.parent) for f in out.rglob("summary.json")}
        assert len(finished) == 1
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not _gone(workers), "pool processes outlived the killed grid"
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)  # no gate: the rerun completes
    assert r.returncode == 0, r.stderr[-2000:]
    assert len(list(out.rglob("summary.json"))) == 4
    for folder, digest in finished.items():  # finished jobs were skipped, byte for byte
        assert _digest(folder) == digest


def test_ctrl_c_stops_the_workers_and_says_how_to_resume(setup, tmp_path):
    tmp, seq = setup
    gate = tmp_path / "gate"
    cmd = [sys.executable, "-m", "mutualslam_cli.cli", "ablate", str(seq), "--schemes", "recent,replay,replay+ewc",
           "--seeds", "0", "-j", "2", "--out", str(tmp_path / "out"), "--config", str(CONFIG_DIR / "smoke.yaml"),
           "--set", _sets(tmp)[0]]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=_gated_env(gate))
    try:
        _wait_for("two workers in their jobs", lambda: len(_blocked_pids(gate)) >= 2, proc)
        workers = _tree(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "interrupted" in err
    assert "run the same command again" in err
    assert "Traceback" not in err
    assert not _gone(workers)

"""``make gpu-check`` (``mslam bench gpu-check``, mutualslam_cli/bench/gpu_check.py): a clean skip without CUDA,
through the function and the command, and its comparison logic and run path exercised on the CPU (the 'GPU side'
told device=cpu, the bench stubbed)."""

from __future__ import annotations

import pytest
import torch
from typer.testing import CliRunner

from mutualslam_cli.bench import gpu_check
from mutualslam_cli.cli import app
from mutualslam_cli.config import CONFIG_DIR


def test_without_cuda_it_says_why_and_passes(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_check.gpu_check() == 0
    out = capsys.readouterr().out
    assert out.startswith("gpu-check: skipped, no CUDA device:")
    assert torch.__version__ in out


def test_the_command_without_cuda_says_why_and_exits_0(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    r = CliRunner().invoke(app, ["bench", "gpu-check"])
    assert r.exit_code == 0, r.output
    assert r.output.startswith("gpu-check: skipped, no CUDA device:")
    assert torch.__version__ in r.output


def test_the_comparison_wants_the_same_keyframes_and_pcd_within_a_point():
    def run(pcd, kfs):
        return {"summary": {"depth.pcd.lsq.adapted": pcd}, "keyframes": kfs}

    assert all(ok for _, ok, _ in gpu_check.compare(run(40.0, ["1", "2"]), run(40.9, ["1", "2"])))
    checks = dict((what, ok) for what, ok, _ in gpu_check.compare(run(40.0, ["1", "2"]), run(41.2, ["1"])))
    assert checks == {"same keyframes": False, "PCD lsq within 1 point": False}
    assert not gpu_check.compare(run(None, []), run(None, []))[1][1]  # no PCD is no agreement


@pytest.mark.slow  # ~25 s in CI: two whole runs; compare()'s checks are tested above
def test_the_script_runs_a_window_on_both_sides_and_checks_them(tiny_run, monkeypatch, capsys):
    tmp, seq = tiny_run
    monkeypatch.setattr(gpu_check, "no_cuda_reason", lambda: None)
    monkeypatch.setattr(gpu_check, "bench_gpu", lambda device: {"step_ms": 1.0, "predict_ms": 1.0,
                                                                 "mixed_precision": False})
    rc = gpu_check.gpu_check(device="cpu", sequence=str(seq), config=CONFIG_DIR / "smoke.yaml",
                             sets=[f"net.weights={tmp / 'weights'}"], out=tmp / "gpu_check")
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "same keyframes: ok" in out
    assert "PCD lsq within 1 point: ok" in out
    assert "fine-tuning step: 1.0 ms" in out

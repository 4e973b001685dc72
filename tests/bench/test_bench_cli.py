"""``mslam bench``: every sub-command answers ``--help`` through typer, names its options, and imports no
benchmark (nor torch) to do so."""

from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from mutualslam_cli.cli import app

runner = CliRunner()

#: sub-command → options its --help must name (one per parameter of the library function)
COMMANDS = {
    "suite": ["--quick", "--memory", "--grid", "--only-grid", "--whole-run", "--threads", "--out"],
    "ba": ["--iterations", "--runs", "--levels", "--coarse-iterations"],
    "gpu-check": ["--sequence", "--out", "--skip-cpu", "--device", "--config", "--set"],
    "strength": ["--out", "--sequence", "--frames", "--seed"],
    "vo": ["names"],
    "finetune": ["--threads"],
}


def test_the_group_lists_every_command():
    r = runner.invoke(app, ["bench", "--help"])
    assert r.exit_code == 0, r.output
    for name in COMMANDS:
        assert name in r.output


@pytest.mark.parametrize("name", COMMANDS)
def test_help_of_each_command(name: str):
    r = runner.invoke(app, ["bench", name, "--help"], env={"COLUMNS": "200", "TERMINAL_WIDTH": "200"})
    assert r.exit_code == 0, r.output
    for option in COMMANDS[name]:
        assert option in r.output, f"mslam bench {name} --help lacks {option}"


def test_help_imports_no_benchmark():
    code = ("import sys\nfrom mutualslam_cli.cli import app\n"
            "try:\n    app(['bench', 'suite', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('LOADED', ','.join(sorted(m for m in sys.modules\n"
            "                              if m == 'torch' or m.startswith('mutualslam_cli.bench'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.rstrip().endswith("LOADED"), out.stdout.rsplit("LOADED", 1)[-1]

"""Library code never imports the CLI toolkits (typer, rich)."""

from __future__ import annotations

import subprocess
import sys


def test_library_does_not_import_typer_or_rich():
    code = (
        "import sys\n"
        "import mutualslam_cli.pipeline, mutualslam_cli.report, mutualslam_cli.evaluation\n"
        "import mutualslam_cli.metrics.trajectory, mutualslam_cli.metrics.depth\n"
        "bad = sorted(m for m in ('typer', 'rich') if m in sys.modules)\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"library imported {out.stdout.strip()}"

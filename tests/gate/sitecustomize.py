"""A handshake for tests that stop a grid mid-job (``tests/test_grid.py``), loaded by every Python
process whose ``PYTHONPATH`` starts with this folder — the grid's own process and each worker it
spawns.

With ``MSLAM_TEST_GATE=DIR`` set, every run whose scheme is not listed in
``MSLAM_TEST_GATE_PASS`` (comma-separated) writes ``DIR/started-<scheme>-<pid>`` and then waits for
``DIR/go`` before it starts. A test waits for those files instead of guessing with sleeps when the
workers have begun their jobs; listed schemes run through, so some jobs finish first.
"""

import os

_GATE = os.environ.get("MSLAM_TEST_GATE")

if _GATE:
    import time
    from pathlib import Path

    import mutualslam_cli.pipeline as _pipeline

    _real = _pipeline.run_sequence
    _pass = set(filter(None, os.environ.get("MSLAM_TEST_GATE_PASS", "").split(",")))

    def _gated(sequence, cfg, *args, **kwargs):
        if cfg.adapt.scheme not in _pass:
            Path(_GATE, f"started-{cfg.adapt.scheme}-{os.getpid()}").write_text("")
            while not Path(_GATE, "go").exists():
                time.sleep(0.05)
        return _real(sequence, cfg, *args, **kwargs)

    _pipeline.run_sequence = _gated

"""The calibration of the regulariser coefficients (bench/strength.py), with a model of the shrink."""

from __future__ import annotations

from pathlib import Path

import pytest

from mutualslam_cli.bench import strength


def test_coefficients_rescaled_until_each_shrinks_like_ewc(monkeypatch, tmp_path: Path):
    """Shrink ≈ k·λ while small: the procedure lands each λ within 10 % of EWC's shrink, in few runs,
    and rounds λ to two significant digits."""
    calls = []

    def fake_shrink(seq, out, scheme, sets):
        calls.append((scheme, sets))
        if scheme == "replay+ewc":
            return 0.05
        lam = float(sets[0].split("=")[1])
        k = {"replay+mas": 1e-3, "replay+si": 3e-4}[scheme]
        return k * lam / (1.0 + 2.0 * k * lam)  # sublinear, as 1 − 1/(1 + 2Pcw) is

    monkeypatch.setattr(strength, "shrink_of", fake_shrink)
    res = strength.calibrate(tmp_path / "seq", tmp_path / "out")
    assert res["target"] == 0.05
    for scheme, key in strength.CALIBRATED.items():
        r = res[scheme]
        assert r["key"] == key
        assert r["shrink"] == pytest.approx(0.05, rel=0.1)
        assert len(r["runs"]) <= 5
        assert float(f"{r['value']:.2g}") == r["value"]
    assert calls[0] == ("replay+ewc", [])  # the paper's EWC first, with its own constants

"""The README's headline adaptation figure, causal (data): ``mslam run icl_lr_kt2`` with the defaults —
``configs/paper.yaml``, replay+ewc, causal labels, our VO, seed 0, one thread. README "The paper's grid":
PCD (lsq) 22.55 → 48.05 final, 31.50 online (the model of each frame's time); bounded here within 1.5×."""

from __future__ import annotations

import pytest

from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.results.summary import flatten

pytestmark = pytest.mark.data


def test_the_default_run_adapts_causally_as_the_readme_says(shared_data, tmp_path):
    cfg = load_config(CONFIG_DIR / "paper.yaml", ["threads=1", "seed=0"])
    r = run_sequence(shared_data / "icl_lr_kt2", cfg, out=tmp_path, command=["test"])
    s = flatten(r.summary)
    assert s["adaptation.labels"] == "causal" and s["scheme"] == "replay+ewc"
    assert s["depth.pcd.lsq.pretrained"] == pytest.approx(22.55, abs=0.1)  # the same network, the same frames
    assert 48.05 / 1.5 <= s["depth.pcd.lsq.adapted"] <= 48.05 * 1.5
    assert 31.50 / 1.5 <= s["depth.pcd_online.lsq"] <= 31.50 * 1.5
    assert s["depth.pcd.lsq.adapted"] > s["depth.pcd_online.lsq"] > s["depth.pcd.lsq.pretrained"]

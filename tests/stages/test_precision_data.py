"""The fast path is accurate, not only fast (issue 46; data, slow, ~6 min on 2 cores): on a CPU with native bf16
(AMX or AVX512-BF16) the default run — encoder trained in fp32, the decoder under bf16 autocast
(``net.fast_train: decoder``) — matches the fp32 run (``net.fast=off``) within 1.5 PCD points on the final
model's PCD (lsq) and on each quarter of the sequence, on a shared window, our VO, seed 0, one thread, at
lr 1e-4 (configs/tuned.yaml's). Measured on AVX512-BF16: 44.3 vs 43.9, quarters within 0.5.

Not asserted: the paper's lr 1e-3, where the two do not match (README "Devices": the fast path ends 7.5 / 22.9
points above fp32 on fr1_xyz / ICL kt2 and 3.9 below on desk_loss, a precision effect not yet explained); and
scheme ``replay``, whose single run is chaotic (one part in 10⁵ on the lr moves its final PCD on this window by
6 points in bf16 and 12 in fp32). Skips where the CPU has no bf16 (there the default run is the fp32 run)."""

from __future__ import annotations

import pytest

from mutualslam_cli.adapt.depthnet import fast_path_supported
from mutualslam_cli.config import CONFIG_DIR, load_config  # figures measured with the paper's values
from mutualslam_cli.pipeline import run_sequence

pytestmark = [pytest.mark.data, pytest.mark.slow,
              pytest.mark.skipif(not fast_path_supported(), reason="this CPU has no native bf16 (AMX / AVX512-BF16)")]

KEYS = ["depth.pcd.lsq.adapted"] + [f"depth.quarter_pcd_lsq.adapted.q{q}" for q in (1, 2, 3, 4)]


SCHEME = "replay+ewc"


def test_the_default_bf16_path_learns_what_fp32_learns(shared_data, tmp_path):
    seq = shared_data / "tum_fr1_xyz"
    runs = {}
    for name, sets in (("default", []), ("fp32", ["net.fast=off"])):
        cfg = load_config(CONFIG_DIR / "paper.yaml",
                          ["threads=1", "seed=0", f"adapt.scheme={SCHEME}", "adapt.lr=1e-4", *sets])
        runs[name] = run_sequence(seq, cfg, out=tmp_path / name, command=["test"]).summary.flat()
    print({k: (round(runs["default"][k], 2), round(runs["fp32"][k], 2)) for k in KEYS})
    for k in KEYS:
        assert abs(runs["default"][k] - runs["fp32"][k]) <= 1.5, k
    # the two runs trained: both end above the pre-trained network
    assert runs["fp32"]["depth.pcd.lsq.adapted"] > runs["fp32"]["depth.pcd.lsq.pretrained"] + 3

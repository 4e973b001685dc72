"""Accuracy of the monocular front end on the real sequence windows (DESIGN §4 targets).

Marked ``data`` (needs ../shared/data); about 15 s for the whole file.
"""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.bench.vo import vo_accuracy
from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.vo.frontend import run_vo

pytestmark = pytest.mark.data

# sequence folder -> ATE bound in metres (brief: ≤ 2 cm, ≤ 3 cm, ≤ 5 cm)
TARGETS = {"tum_fr1_xyz": 0.02, "icl_lr_kt2": 0.03, "redkitchen_7scenes": 0.05}


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_accuracy_targets(shared_data, name):
    seq = load_sequence(shared_data / name)
    vo = run_vo(seq, VOConfig(), seed=0)
    acc = vo_accuracy(seq, vo)
    assert acc["tracked"] >= 0.95
    assert acc["ate_kf"] is not None
    assert acc["ate_kf"] <= TARGETS[name]
    assert acc["ate_all"] is not None
    assert acc["ate_all"] <= TARGETS[name]
    assert acc["points"] >= 300
    assert acc["esi"] < 0.3  # the paper's SVO map: ≈ 0.53


def test_fast_motion_stride_keeps_tracking(shared_data):
    """Every second frame of fr1_xyz (twice the motion per frame, stronger blur and rolling
    shutter) still tracks; a robustness check, looser than the 30 Hz target."""
    seq = load_sequence(shared_data / "tum_fr1_xyz")
    seq.frames = seq.frames[::2]
    vo = run_vo(seq, VOConfig(), seed=0)
    acc = vo_accuracy(seq, vo)
    assert acc["tracked"] >= 0.9
    assert acc["ate_all"] is not None
    assert acc["ate_all"] <= 0.05


def test_nine_frames_do_not_crash(shared_data):
    seq = load_sequence(shared_data / "tum_fr1_desk_9f")
    vo = run_vo(seq, VOConfig(), seed=0)
    assert vo.frame_segment.shape == (9,)
    assert len(vo.traj_all) == int(np.sum(vo.frame_segment >= 0))


def test_fast_rotation_window_tracks_in_one_segment(shared_data):
    """tum_fr1_desk_loss: 100 frames of a fast hand-held sweep and roll with motion blur, where the front end
    used to lose track (2 segments). Weak frames' poses are rescued (vo/rescue.py): the window is tracked whole in
    one segment, within 1.5× of the ATE measured (front end alone, one Sim(3): 1.88 cm at keyframes)."""
    seq = load_sequence(shared_data / "tum_fr1_desk_loss")
    vo = run_vo(seq, VOConfig(), seed=0)
    acc = vo_accuracy(seq, vo)
    assert len({k.segment for k in vo.keyframes}) == 1
    assert vo.meta["losses"] == []
    assert sum(vo.meta["frames_lost"].values()) == 0
    assert sum(vo.meta["rescued"].values()) > 0  # the rescue is what carried it
    assert acc["tracked"] == 1.0
    assert acc["ate_kf"] is not None
    assert acc["ate_kf"] <= 1.5 * 0.0188

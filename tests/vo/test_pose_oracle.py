"""The pose oracle (``--vo gt``): our VO's tracks with GT poses, map re-triangulated in metres."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import project, se3_inv, transform
from mutualslam_cli.map.result import MapPoints
from mutualslam_cli.vo.frontend import run_vo
from mutualslam_cli.vo.pose_oracle import REASONS, retriangulate, run_pose_oracle

W, H = 640, 480


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    seq = load_sequence(make_tum_dir(tmp_path_factory.mktemp("po_room"), scene="room", n=60, width=W, height=H))
    return seq, run_vo(seq, VOConfig(), seed=0), run_pose_oracle(seq, VOConfig(), seed=0)


def _labels(vo) -> np.ndarray:
    pw = vo.points_world()
    return np.array([len(vo.sparse_depth(k.id, pw)[1]) for k in vo.keyframes])


def test_gt_poses_metric_depth_and_svo_density(room):
    seq, svo, po = room
    assert po.meta["mode"] == "gt"
    assert po.meta["vo_meta"]["mode"] == "svo"
    assert len(po.keyframes) == len(svo.keyframes)
    for kf in po.keyframes:
        np.testing.assert_allclose(kf.pose, seq.frames[kf.frame_index].pose, atol=1e-12)
    # every point's depth in its host matches GT depth there (metric, no scale alignment)
    P = po.points
    rel = []
    for kf in po.keyframes:
        m = P.host == kf.id
        D = seq.load_depth(kf.frame_index)
        px = np.round(P.pixel[m]).astype(int)
        rel.append(np.abs(1.0 / P.inv_depth[m] / D[px[:, 1], px[:, 0]] - 1.0))
    rel = np.concatenate(rel)
    assert np.median(rel) < 0.02
    assert np.percentile(rel, 90) < 0.05
    # labels per keyframe: svo's points minus the rejected ones
    n_po, n_svo = _labels(po), _labels(svo)
    assert np.all(n_po <= n_svo)
    assert np.all(n_po >= 0.5 * n_svo)
    pts = po.meta["points"]
    assert pts["vo"] == len(svo.points)
    assert pts["triangulated"] == len(P)
    assert pts["triangulated"] + sum(pts["rejected"].values()) == pts["vo"]
    assert np.all(P.sigma > 0)
    assert np.all(np.isfinite(P.sigma))


def test_result_contract(room):
    seq, svo, po = room
    P = po.points
    assert [k.id for k in po.keyframes] == list(range(len(po.keyframes)))
    assert np.array_equal(P.ids, np.arange(len(P)))
    for i in range(len(P)):
        assert len(P.observations[i]) >= 2
        assert P.host[i] in P.observations[i]
        j = int(np.flatnonzero(P.observations[i] == P.host[i])[0])
        np.testing.assert_array_equal(P.obs_pixels[i][j], P.pixel[i])
    assert po.frame_segment.shape == (len(seq),)
    assert set(np.unique(po.frame_segment)) <= {-1, 0}
    assert len(po.traj_all) == int(np.sum(po.frame_segment >= 0)) == int(np.sum(svo.frame_segment >= 0))
    gt = np.stack([seq.frames[i].pose for i in np.flatnonzero(po.frame_segment >= 0)])
    np.testing.assert_allclose(po.traj_all.poses, gt)
    for a, nb in po.covisibility.items():
        for b, c in nb.items():
            assert po.covisibility[b][a] == c > 0


def test_reuses_a_given_vo_result(room):
    seq, svo, po = room
    again = run_pose_oracle(seq, VOConfig(), vo=svo)
    np.testing.assert_array_equal(again.points.inv_depth, po.points.inv_depth)


def test_keyframes_without_gt_are_dropped_and_renumbered(room):
    seq, svo, _ = room
    seq = copy.copy(seq)
    seq.frames = list(seq.frames)
    gone = svo.keyframes[1].frame_index
    seq.frames[gone] = dataclasses.replace(seq.frames[gone], pose=None)
    po = run_pose_oracle(seq, VOConfig(), vo=svo)
    assert len(po.keyframes) == len(svo.keyframes) - 1 == po.meta["keyframes"]["vo"] - 1
    assert [k.id for k in po.keyframes] == list(range(len(po.keyframes)))
    assert gone not in [k.frame_index for k in po.keyframes]
    assert po.frame_segment[gone] == -1
    assert po.meta["points"]["rehosted"] > 0  # points born in the dropped keyframe
    assert all(o.max() < len(po.keyframes) for o in po.points.observations)
    assert set(po.covisibility) == set(range(len(po.keyframes)))


def _scene(rng: np.random.Generator):
    """Four cameras 10 cm apart along x looking down +z at points 2–4 m away; exact tracks."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    poses = np.stack([np.eye(4)] * 4)
    poses[:, 0, 3] = 0.1 * np.arange(4)
    Xw = np.c_[rng.uniform(-0.5, 0.5, (20, 2)), rng.uniform(2.0, 4.0, 20)]
    obs, pix = [], []
    for X in Xw:
        obs.append(np.arange(4))
        pix.append(np.stack([project(transform(se3_inv(T), X[None]), K)[0][0] for T in poses]))
    return K, poses, Xw, obs, pix


def _points(obs, pix) -> MapPoints:
    n = len(obs)
    return MapPoints(np.arange(n), np.array([o[0] for o in obs]), np.array([p[0] for p in pix]),
                     np.ones(n), np.zeros(n), [np.asarray(o) for o in obs], [np.asarray(p) for p in pix])


def test_single_inconsistent_behind_and_low_parallax_points_are_rejected(rng):
    K, poses, Xw, obs, pix = _scene(rng)
    n_good = len(obs)
    obs.append(np.array([2]))  # seen once
    pix.append(pix[0][2:3])
    bad = pix[1].copy()
    bad[3] += [20.0, -15.0]  # one track jumps to another feature
    obs.append(np.arange(4))
    pix.append(bad)
    # rays that meet behind the cameras: the second track moves the wrong way
    x0 = np.array([320.0, 240.0])
    obs.append(np.array([0, 1]))
    pix.append(np.stack([x0, x0 + [25.0, 0.0]]))
    # 20 m away seen over a 10 cm baseline: 0.3° of parallax
    far = project(transform(se3_inv(poses[1]), np.array([[0.0, 0.0, 20.0]])), K)[0][0]
    obs.append(np.array([0, 1]))
    pix.append(np.stack([x0, far]))
    kept, stats = retriangulate(_points(obs, pix), poses, K)
    assert stats["rejected"] == dict(zip(REASONS, (1, 1, 1, 1)))
    assert stats["rms_gate_px"] == 2.0
    assert stats["rms_median_px"] < 1e-6
    assert len(kept) == n_good
    np.testing.assert_allclose(1.0 / kept.inv_depth, Xw[:, 2], rtol=1e-9)
    # a gate looser than the bad track's error keeps it
    loose, stats = retriangulate(_points(obs, pix), poses, K, max_rms_px=50.0)
    assert len(loose) == n_good + 1
    assert stats["rejected"]["reprojection"] == 0


def test_noisy_tracks_refined_by_gauss_newton(rng):
    K, poses, Xw, obs, pix = _scene(rng)
    noisy = [p + np.r_[[[0.0, 0.0]], rng.normal(0, 0.3, (3, 2))] for p in pix]  # host exact
    kept, stats = retriangulate(_points(obs, noisy), poses, K)
    assert len(kept) == len(obs)
    assert 0 < stats["rms_median_px"] < 1.0
    assert np.median(np.abs(1.0 / kept.inv_depth / Xw[:, 2] - 1)) < 0.02


@pytest.mark.data
def test_tum_density_between_svo_and_far_below_gt_depth(shared_data: Path):
    from mutualslam_cli.vo.depth_oracle import run_oracle

    seq = load_sequence(shared_data / "tum_fr1_xyz")
    cfg = VOConfig()
    svo = run_vo(seq, cfg, seed=0)
    po = run_pose_oracle(seq, cfg, seed=0, vo=svo)
    gd = run_oracle(seq, cfg, seed=0)
    m_svo, m_po, m_gd = (float(np.median(_labels(v))) for v in (svo, po, gd))
    assert 0.5 * m_svo <= m_po <= 1.2 * m_svo
    assert m_po < 0.5 * m_gd
    for kf in po.keyframes:
        np.testing.assert_allclose(kf.pose, seq.frames[kf.frame_index].pose)

"""Synthetic RGB-D sequences: determinism, exact depth and poses, TUM files, texture quality."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from synth import make_sequence, make_tum_dir

from mutualslam_cli.datasets.synthetic import sequences as synthetic
from mutualslam_cli.datasets.synthetic.scenes import build_scene, camera_pose
from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.geometry import quat_to_rot, se3_inv


def _warp_error(seq: synthetic.SyntheticSequence, i: int, j: int, T_j: np.ndarray) -> float:
    """Mean |I_i − I_j→i| (grey levels) over pixels of frame i visible in frame j.

    Frame i's pixels are back-projected with frame i's depth, moved by T_j⁻¹·T_i and projected
    into frame j (pose ``T_j``), where the image is sampled bilinearly.
    """
    K = seq.intrinsics.K()
    H, W = seq.depth.shape[1:]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = seq.depth[i].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)
    T = se3_inv(T_j) @ seq.poses[i]
    pj = pts @ T[:3, :3].T + T[:3, 3]
    uj = K[0, 0] * pj[:, 0] / pj[:, 2] + K[0, 2]
    vj = K[1, 1] * pj[:, 1] / pj[:, 2] + K[1, 2]
    mx, my = uj.reshape(H, W).astype(np.float32), vj.reshape(H, W).astype(np.float32)
    gi = cv2.cvtColor(seq.rgb[i], cv2.COLOR_RGB2GRAY).astype(np.float32)
    gj = cv2.cvtColor(seq.rgb[j], cv2.COLOR_RGB2GRAY).astype(np.float32)
    warped = cv2.remap(gj, mx, my, cv2.INTER_LINEAR, borderValue=-1.0)
    # Not occluded in frame j: its depth at the reprojection agrees with the moved point.
    dj = cv2.remap(seq.depth[j], mx, my, cv2.INTER_NEAREST, borderValue=0.0)
    valid = (warped >= 0) & (mx > 1) & (my > 1) & (mx < W - 2) & (my < H - 2)
    valid &= np.abs(dj - pj[:, 2].reshape(H, W)) < 0.02 * dj
    assert valid.mean() > 0.5, "too few co-visible pixels"
    return float(np.abs(gi - warped)[valid].mean())


def test_deterministic_per_seed_and_different_across_seeds():
    a = make_sequence("room", n=3, seed=3)
    synthetic._setup.cache_clear()  # textures are re-synthesised, not reused from the cache
    b = make_sequence("room", n=3, seed=3)
    c = make_sequence("room", n=3, seed=4)
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(a.depth, b.depth)
    assert np.array_equal(a.poses, b.poses)
    assert not np.array_equal(a.rgb, c.rgb)
    assert not np.allclose(a.poses, c.poses)


def test_iter_render_matches_render_sequence():
    seq = make_sequence("far", n=4, seed=1)
    for i, rgb, depth, pose in synthetic.iter_render("far", 4, 64, 48, 1, "target"):
        assert np.array_equal(rgb, seq.rgb[i])
        assert np.array_equal(depth, seq.depth[i])
        assert np.array_equal(pose, seq.poses[i])
    assert seq.rgb.shape == (4, 48, 64, 3)
    assert seq.rgb.dtype == np.uint8
    assert seq.depth.dtype == np.float32
    assert seq.poses.dtype == np.float64
    np.testing.assert_allclose(seq.timestamps, np.arange(4) / 30.0)


@pytest.mark.parametrize("scene", synthetic.SCENES)
@pytest.mark.parametrize("domain", ["target", "source"])
def test_depth_positive_and_points_lie_on_scene_surfaces(scene, domain):
    """Back-projected z-depth must land exactly on a box face (z-depth, not ray length)."""
    seq = make_sequence(scene, n=3, width=80, height=60, seed=2, domain=domain)
    assert np.all(seq.depth > 0)
    assert np.all(np.isfinite(seq.depth))
    boxes = build_scene(scene, 2, domain).boxes
    K = seq.intrinsics.K()
    v, u = np.mgrid[0:60, 0:80].astype(np.float64)
    for i in range(len(seq)):
        z = seq.depth[i].astype(np.float64)
        pc = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)
        pw = pc @ seq.poses[i][:3, :3].T + seq.poses[i][:3, 3]
        dist = np.full(len(pw), np.inf)
        for box in boxes:  # distance to the box surface (0 on a face)
            inside = np.all((pw >= box.lo - 1e-3) & (pw <= box.hi + 1e-3), axis=1)
            to_face = np.minimum(np.abs(pw - box.lo), np.abs(pw - box.hi)).min(axis=1)
            dist = np.where(inside, np.minimum(dist, to_face), dist)
        assert np.all(dist < 1e-3 * np.maximum(1.0, z.reshape(-1))), f"frame {i}: off-surface depth"


@pytest.mark.parametrize("scene", synthetic.SCENES)
def test_photometric_warp_consistent_with_depth_and_poses(scene):
    seq = make_sequence(scene, n=6, width=320, height=240, seed=0)
    good = _warp_error(seq, 0, 5, seq.poses[5])
    # Perturb the pose of frame 5 by 1 cm and 0.5°.
    d = np.eye(4)
    d[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(0.5), 0.0]))[0]
    d[:3, 3] = [0.01, 0.0, 0.0]
    bad = _warp_error(seq, 0, 5, seq.poses[5] @ d)
    assert good < 6.0, f"photometric error {good:.2f} grey levels with exact depth/poses"
    assert bad > 2.0 * good, f"perturbed pose error {bad:.2f} not clearly above exact {good:.2f}"
    # The camera really moved between the frames (otherwise the check above is vacuous).
    assert np.linalg.norm(seq.poses[5][:3, 3] - seq.poses[0][:3, 3]) > 0.01


@pytest.mark.parametrize("scene", synthetic.SCENES)
@pytest.mark.parametrize("domain", ["target", "source"])
def test_poses_are_rigid_and_motion_is_handheld_like(scene, domain):
    path = build_scene(scene, 5, domain).path
    T = np.stack([camera_pose(path, i / 30.0) for i in range(30 * 20)])  # 20 s
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0, 0, 0, 1.0], (len(T), 4)))
    speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) * 30.0
    assert 0.1 < speed.mean() < 0.6, (speed.mean(), speed.max())
    assert speed.max() < 1.0, (speed.mean(), speed.max())
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    ang = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)) * 30.0
    assert np.rad2deg(ang.max()) < 60.0  # deg/s: a calm handheld camera


def test_write_tum_files_parse_and_depth_roundtrips(tmp_path):
    seq = make_sequence("room", n=4, seed=1)
    root = synthetic.write_tum(seq, tmp_path / "seq")
    rows = {}
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = (root / name).read_text().splitlines()
        assert lines[0].startswith("#")
        rows[name] = [ln.split() for ln in lines if not ln.startswith("#")]
        assert len(rows[name]) == 4
    assert [r[0] for r in rows["rgb.txt"]] == [f"{i / 30:.6f}" for i in range(4)]
    fx, fy, cx, cy, w, h = (root / "intrinsics.txt").read_text().split()
    np.testing.assert_allclose([float(fx), float(fy), float(cx), float(cy)], seq.intrinsics.as_list(), atol=1e-6)
    assert (int(w), int(h)) == (64, 48)
    for i in range(4):
        rgb = cv2.imread(str(root / rows["rgb.txt"][i][1]), cv2.IMREAD_COLOR)
        assert np.array_equal(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB), seq.rgb[i])
        raw = cv2.imread(str(root / rows["depth.txt"][i][1]), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        assert raw.shape == (48, 64)
        assert np.all(np.abs(raw / 5000.0 - seq.depth[i]) <= 1 / 5000.0)
        vals = np.array([float(x) for x in rows["groundtruth.txt"][i]])
        assert vals[0] == pytest.approx(i / 30.0, abs=1e-6)
        np.testing.assert_allclose(vals[1:4], seq.poses[i][:3, 3], atol=1e-8)
        np.testing.assert_allclose(quat_to_rot(vals[4:]), seq.poses[i][:3, :3], atol=1e-7)


def test_write_tum_streams_iterator_and_zeroes_far_depth(tmp_path):
    frames = list(synthetic.iter_render("far", 2, 64, 48, 0, "source"))
    assert any((d > synthetic.MAX_PNG_DEPTH).any() for _, _, d, _ in frames), "source far scene reaches > 13.1 m"
    root = synthetic.write_tum(iter(frames), tmp_path / "far", scene="far", width=64, height=48, seed=0)
    for i, _, depth, _ in frames:
        raw = cv2.imread(str(root / "depth" / f"{i / 30:.6f}.png"), cv2.IMREAD_UNCHANGED)
        assert np.all(raw[depth > synthetic.MAX_PNG_DEPTH] == 0)
        assert np.all(raw[depth <= synthetic.MAX_PNG_DEPTH] > 0)
    assert (root / "intrinsics.txt").read_text().split()[4:] == ["64", "48"]


def test_write_tum_rejects_empty_and_misshaped_input(tmp_path):
    with pytest.raises(ConfigError, match="no frames"):
        synthetic.write_tum(iter([]), tmp_path / "empty")
    bad = [(0, np.zeros((48, 64, 3), np.uint8), np.ones((48, 60), np.float32), np.eye(4))]
    with pytest.raises(ShapeError, match="depth"):
        synthetic.write_tum(iter(bad), tmp_path / "bad")


def test_make_tum_dir_helper(tmp_path):
    root = make_tum_dir(tmp_path, scene="planar", n=3)
    assert sorted(p.name for p in root.iterdir()) == ["depth", "depth.txt", "groundtruth.txt", "intrinsics.txt",
                                                    "rgb", "rgb.txt"]
    assert len(list((root / "rgb").glob("*.png"))) == 3


@pytest.mark.parametrize("scene", synthetic.SCENES)
def test_textures_give_many_corners_at_640x480(scene):
    seq = synthetic.render_sequence(scene, 1, 640, 480, seed=0)
    grey = cv2.cvtColor(seq.rgb[0], cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(grey, maxCorners=2000, qualityLevel=0.01, minDistance=7)
    assert corners is not None, f"{scene}: {0 if corners is None else len(corners)} corners"
    assert len(corners) >= 200, f"{scene}: {0 if corners is None else len(corners)} corners"


def test_unknown_scene_and_domain_raise_config_error():
    with pytest.raises(ConfigError, match="room, planar, far"):
        synthetic.render_sequence("kitchen", 2, 64, 48)
    with pytest.raises(ConfigError, match="domain"):
        list(synthetic.iter_render("room", 2, 64, 48, 0, "other"))  # type: ignore[arg-type]


@pytest.mark.parametrize("scene", synthetic.SCENES)
def test_source_domain_differs_from_target(scene):
    far = {"target": [], "source": []}
    for seed in range(3):
        tgt = make_sequence(scene, n=2, width=64, height=48, seed=seed, domain="target")
        src = make_sequence(scene, n=2, width=64, height=48, seed=seed, domain="source")
        # Palette: the target is warm (red > blue), the source cool (blue > red).
        t_mean, s_mean = tgt.rgb.reshape(-1, 3).mean(0), src.rgb.reshape(-1, 3).mean(0)
        assert t_mean[0] > t_mean[2], (seed, t_mean, s_mean)
        assert s_mean[2] > s_mean[0], (seed, t_mean, s_mean)
        far["target"].append(np.percentile(tgt.depth, 90))
        far["source"].append(np.percentile(src.depth, 90))
    # Depth range: the far end of the depth distribution differs by more than 25 %.
    t, s = np.mean(far["target"]), np.mean(far["source"])
    assert max(t, s) > 1.25 * min(t, s), (t, s)


def test_bench_render_reports_speed():
    r = synthetic.bench_render(64, 48, n=3)
    assert r["fps"] > 0
    assert r["ms_per_frame"] == pytest.approx(1000.0 / r["fps"])

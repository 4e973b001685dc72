"""Loaders, registry, autodetection, checks and fy-sign decision on tiny folders in tmp_path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mutualslam_cli.datasets import (
    bench_loader,
    check_sequence,
    decide_fy_sign,
    detect_format,
    get_spec,
    list_datasets,
    load_sequence,
)
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.check import jpeg_problem, png_problem
from mutualslam_cli.datasets.icl_nuim import ray_to_z
from mutualslam_cli.datasets.registry import DEFAULT_REGISTRY, FORMATS, resolve_root
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import backproject
from mutualslam_cli.types import Intrinsics, Trajectory

W, H = 64, 48
F = 50.0


def _pose(t, yaw_deg=0.0, pitch_deg=0.0) -> np.ndarray:
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = ry @ rx
    T[:3, 3] = t
    return T


def render_plane(T_wc: np.ndarray, fy: float) -> tuple[np.ndarray, np.ndarray]:
    """Grey image and z-depth of a textured plane Z_w = 2 m seen by camera ``T_wc``."""
    K = Intrinsics(F, fy, (W - 1) / 2, (H - 1) / 2, W, H).K()
    v, u = np.mgrid[0:H, 0:W]
    rays_c = backproject(np.stack([u.ravel(), v.ravel()], 1).astype(float), np.ones(W * H), K)
    rays_w = rays_c @ T_wc[:3, :3].T
    s = (2.0 - T_wc[2, 3]) / rays_w[:, 2]  # rays_c has z = 1, so s is the z-depth
    X = T_wc[:3, 3] + s[:, None] * rays_w
    tex = 128 + 60 * np.sin(9 * X[:, 0]) * np.cos(5 * X[:, 1]) + 50 * np.sin(23 * X[:, 1] + 3 * X[:, 0])
    return np.clip(tex, 0, 255).reshape(H, W).astype(np.uint8), s.reshape(H, W)


POSES = [_pose([0.03 * k, 0.02 * k, 0.0], yaw_deg=2.0 * k, pitch_deg=1.5 * k) for k in range(8)]


def write_tum_dir(root: Path, n: int = 6, fy: float = F, depth_bits: int = 16, gt: bool = True,
                  times=None, gt_times=None, intrinsics_txt: bool = False) -> Path:
    """A TUM-layout folder: rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    times = np.arange(n) * 0.1 + 100.0 if times is None else np.asarray(times)
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for k, t in enumerate(times):
        g, z = render_plane(POSES[k % len(POSES)], fy)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), cv2.merge([g, g, g]))
        raw = (z * 5000).astype(np.uint16) if depth_bits == 16 else np.full((H, W), 200, np.uint8)
        cv2.imwrite(str(root / "depth" / f"{t + 0.005:.6f}.png"), raw)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt:
        gts = times if gt_times is None else np.asarray(gt_times)
        poses = np.stack([POSES[k % len(POSES)] for k in range(len(gts))])
        write_tum_trajectory(root / "groundtruth.txt", Trajectory(gts, poses))
    if intrinsics_txt:
        (root / "intrinsics.txt").write_text(f"{F} {fy} {(W - 1) / 2} {(H - 1) / 2} {W} {H}\n")
    return root


def write_icl_dir(root: Path, n: int = 6, first: int = 0, fy: float = -F, gt_from: int = 1) -> Path:
    """An ICL-NUIM *_frei_png folder with associations.txt and a .gt.freiburg (no GT for frame 0)."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = []
    for k in range(first, first + n):
        g, z = render_plane(POSES[k % len(POSES)], fy)
        cv2.imwrite(str(root / "rgb" / f"{k}.png"), cv2.merge([g, g, g]))
        cv2.imwrite(str(root / "depth" / f"{k}.png"), (z * 5000).astype(np.uint16))
        lines.append(f"{k} depth/{k}.png {k} rgb/{k}.png")
    (root / "associations.txt").write_text("\n".join(lines) + "\n")
    ks = np.arange(max(first, gt_from), first + n)
    poses = np.stack([POSES[k % len(POSES)] for k in ks])
    write_tum_trajectory(root / "scene.gt.freiburg", Trajectory(ks.astype(float), poses))
    return root


def spec_yaml(tmp_path: Path, entries: dict) -> Path:
    p = tmp_path / "datasets.yaml"
    p.write_text(yaml.safe_dump({"datasets": entries}))
    return p


# ----------------------------------------------------------------------------- TUM / lab
def test_tum_folder_loads_with_family_intrinsics_and_gt(tmp_path):
    root = write_tum_dir(tmp_path / "rgbd_dataset_freiburg1_test")
    seq = load_sequence(root)
    assert len(seq) == 6
    assert seq.meta["format"] == "tum"
    assert seq.intrinsics.fx == 517.3
    assert seq.intrinsics.dist[0] == 0.2624
    assert (seq.intrinsics.width, seq.intrinsics.height) == (W, H)
    assert seq.meta["association"]["pairs"] == 6
    np.testing.assert_allclose(seq.frames[3].pose, POSES[3], atol=1e-12)
    d = seq.load_depth(2)
    assert d.dtype == np.float32
    assert 1.5 < np.median(d) < 2.5


def test_intrinsics_txt_overrides_family_and_gives_synthetic(tmp_path):
    root = write_tum_dir(tmp_path / "synth_fr1", intrinsics_txt=True)
    assert detect_format(root) == "synthetic"
    seq = load_sequence(root)
    assert seq.intrinsics.fx == F
    assert seq.meta["intrinsics_source"] == "intrinsics.txt"


def test_all_frames_keeps_the_rgb_frames_without_depth(tmp_path):
    # a colour sequence with depth for its first frames only (RedKitchen whole: depth for 300 of 1000 frames)
    root = write_tum_dir(tmp_path / "partial", n=8, intrinsics_txt=True)
    lines = (root / "depth.txt").read_text().splitlines()
    (root / "depth.txt").write_text("\n".join(lines[:4]) + "\n")  # header + 3 depth frames
    entry = {"root": str(root), "format": "lab", "intrinsics": [F, F, 31.5, 23.5], "gt": "groundtruth.txt"}
    paired = load_sequence("p", registry_path=spec_yaml(tmp_path, {"p": entry}))
    assert len(paired) == 3
    every = load_sequence("p", registry_path=spec_yaml(tmp_path, {"p": {**entry, "all_frames": True}}))
    assert len(every) == 8
    assert every.has_gt_poses
    assert [f.depth_path is not None for f in every.frames] == [True] * 3 + [False] * 5
    assert every.frames[1].depth_path == paired.frames[1].depth_path
    with pytest.raises(DatasetError, match="all_frames = 'yes': expected true or false"):
        load_sequence("p", registry_path=spec_yaml(tmp_path, {"p": {**entry, "all_frames": "yes"}}))


def test_lab_folder_without_gt_has_no_poses(tmp_path):
    root = write_tum_dir(tmp_path / "mylab", gt=False, intrinsics_txt=True)
    (root / "intrinsics.txt").unlink()
    reg = spec_yaml(tmp_path, {"lab1": {"root": str(root), "format": "lab", "intrinsics": [F, F, 31.5, 23.5]}})
    seq = load_sequence("lab1", registry_path=reg)
    assert len(seq) == 6
    assert not seq.has_gt_poses
    assert seq.gt is None
    rep = check_sequence(seq)
    assert rep.frames_with_gt == 0
    assert any("no GT poses" in w for w in rep.warnings)


def test_lab_without_intrinsics_raises(tmp_path):
    root = write_tum_dir(tmp_path / "mylab")
    with pytest.raises(DatasetError, match="no intrinsics"):
        load_sequence(root)


# ----------------------------------------------------------------------------- bad input
def test_missing_rgb_txt(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    (root / "rgb.txt").unlink()
    reg = spec_yaml(tmp_path, {"s": {"root": str(root), "format": "tum"}})
    with pytest.raises(DatasetError, match=r"rgb\.txt: not found"):
        load_sequence("s", registry_path=reg)


def test_missing_depth_txt_for_tum(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    (root / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt: not found"):
        load_sequence(root)


def test_gt_file_named_in_spec_missing(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    reg = spec_yaml(tmp_path, {"s": {"root": str(root), "format": "tum", "gt": "nope.txt"}})
    with pytest.raises(DatasetError, match=r"nope\.txt: GT file named in the registry entry 's' not found"):
        load_sequence("s", registry_path=reg)


def test_malformed_list_line_names_file_and_line(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    lines = (root / "depth.txt").read_text().splitlines()
    lines[3] = "12x depth/bad.png"
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"depth\.txt:4: expected 'timestamp path'"):
        load_sequence(root)


def test_8bit_depth_png_raises_in_check(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1", depth_bits=8)
    seq = load_sequence(root)
    with pytest.raises(DatasetError, match=r"\.png: depth image is uint8 .*expected a 16-bit"):
        check_sequence(seq)


def test_no_gt_overlap_message(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1", gt_times=np.arange(6) * 0.1 + 500.0)
    msg = r"no GT overlap: images span 100\.0+–100\.50+ s, GT spans 500\.0+–500\.50+ s"
    with pytest.raises(DatasetError, match=msg):
        load_sequence(root)


def test_empty_sequence(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    (root / "rgb.txt").write_text("# color images\n# nothing\n")
    with pytest.raises(DatasetError, match="empty sequence"):
        load_sequence(root)


def test_missing_image_referenced_by_list(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    victim = sorted((root / "rgb").iterdir())[2]
    victim.unlink()
    with pytest.raises(DatasetError, match=rf"rgb\.txt:4: image file rgb/{victim.name} not found"):
        load_sequence(root)


def test_wrong_depth_scale_warns(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    reg = spec_yaml(tmp_path, {"s": {"root": str(root), "format": "tum", "depth_scale": 50}})
    rep = check_sequence("s", registry_path=reg)
    assert rep.median_depth_m > 100
    assert any("depth_scale 50" in w for w in rep.warnings)
    ok = check_sequence(root)
    assert ok.warnings == []
    assert ok.gt_coverage_pct == 100.0
    assert ok.frames_with_depth == 6


# ----------------------------------------------------------------------------- every image decoded
def _victim(root: Path, kind: str, k: int = 3) -> Path:
    return sorted((root / kind).iterdir())[k]


def test_check_decodes_every_image_and_reports_each(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    calls = []
    rep = check_sequence(load_sequence(root), progress=lambda stage, info: calls.append((stage, dict(info))))
    assert rep.ok
    assert rep.images_decoded == 12
    assert rep.frames_decoded == 6
    every = {str(p) for kind in ("rgb", "depth") for p in (root / kind).iterdir()}
    assert {c[1]["file"] for c in calls} == every
    assert len(calls) == 12
    assert [c[1]["done"] for c in calls] == list(range(1, 13))
    assert {c[1]["total"] for c in calls} == {12}
    assert {c[0] for c in calls} == {"decode"}


@pytest.mark.parametrize("kind", ["rgb", "depth"])
@pytest.mark.parametrize("cut", [12, 300], ids=["no-IEND", "mid-IDAT"])
def test_truncated_png_fails_naming_it(tmp_path, kind, cut):
    root = write_tum_dir(tmp_path / "seq_fr1")
    victim = _victim(root, kind)
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) - cut])
    label = {"rgb": "RGB", "depth": "depth"}[kind]
    msg = rf"{kind}/{victim.name}: truncated PNG: .*expected a complete {label} image"
    with pytest.raises(DatasetError, match=msg):
        check_sequence(load_sequence(root))


@pytest.mark.parametrize("kind", ["rgb", "depth"])
def test_corrupted_png_fails_naming_it(tmp_path, kind):
    root = write_tum_dir(tmp_path / "seq_fr1")
    victim = _victim(root, kind, 5)
    data = bytearray(victim.read_bytes())
    data[60] ^= 0xFF  # a flipped byte inside the image data: the chunk's CRC no longer matches
    victim.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=rf"{victim.name}: corrupted PNG: CRC mismatch"):
        check_sequence(load_sequence(root))


def test_image_of_another_size_fails_naming_it_and_the_expected_size(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    victim = _victim(root, "rgb", 4)
    cv2.imwrite(str(victim), np.zeros((H // 2, W // 2, 3), np.uint8))
    first = _victim(root, "rgb", 0)
    msg = rf"{victim.name}: RGB image is {W // 2}×{H // 2}×3 uint8, expected {W}×{H}×3 uint8 like .* {first.name}"
    with pytest.raises(DatasetError, match=msg):
        check_sequence(load_sequence(root))
    cv2.imwrite(str(victim), np.zeros((H, W), np.uint8))  # one grey image among colour ones
    with pytest.raises(DatasetError, match=rf"{victim.name}: RGB image is {W}×{H} uint8, expected {W}×{H}×3 uint8"):
        check_sequence(load_sequence(root))


def test_sampled_check_decodes_only_the_sampled_frames(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    victim = _victim(root, "rgb", 3)  # frames 0 and 5 are sampled, 3 is not
    victim.write_bytes(victim.read_bytes()[:-100])
    files = []
    rep = check_sequence(load_sequence(root), sample=2, progress=lambda stage, info: files.append(info["file"]))
    assert rep.images_decoded == 4
    assert rep.frames_decoded == 2
    assert len(files) == 4
    assert str(victim) not in files
    with pytest.raises(DatasetError, match=victim.name):
        check_sequence(load_sequence(root), sample=0)


def test_png_and_jpeg_structure():
    img = np.arange(48 * 64 * 3, dtype=np.uint8).reshape(48, 64, 3)
    png = cv2.imencode(".png", img)[1].tobytes()
    assert png_problem(png) is None
    assert png_problem(png + b"trailing bytes") is None
    assert "no IEND" in png_problem(png[:-12])
    assert "needs" in png_problem(png[:-13])
    assert "not a PNG" in png_problem(b"GIF89a" + png[6:])
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    assert jpeg_problem(jpg) is None
    assert jpeg_problem(jpg + b"\x00" * 8) is None
    assert "truncated JPEG" in jpeg_problem(jpg[:-10])
    assert "not a JPEG" in jpeg_problem(png)


# ----------------------------------------------------------------------------- ICL-NUIM
@pytest.mark.parametrize("true_sign", [-1, 1])
def test_fy_sign_decided_from_data(tmp_path, true_sign):
    root = write_icl_dir(tmp_path / f"icl{true_sign}", fy=true_sign * F)
    reg = spec_yaml(tmp_path, {"i": {"root": str(root), "format": "icl", "intrinsics": [F, F, 31.5, 23.5]}})
    seq = load_sequence("i", registry_path=reg)
    assert seq.meta["fy_sign"] == true_sign
    assert seq.intrinsics.fy == true_sign * F
    err = seq.meta["fy_sign_errors"]
    right, wrong = ("-", "+") if true_sign < 0 else ("+", "-")
    assert err[right] < 0.5 * err[wrong]
    assert decide_fy_sign(seq)[0] == true_sign


def test_icl_first_frame_has_no_gt_and_exact_frame_match(tmp_path):
    root = write_icl_dir(tmp_path / "living_room_traj0_frei_png", gt_from=1)
    seq = load_sequence(root)
    assert seq.meta["format"] == "icl"
    assert [f.timestamp for f in seq.frames] == [0, 1, 2, 3, 4, 5]
    assert seq.frames[0].pose is None
    np.testing.assert_allclose(seq.frames[4].pose, POSES[4], atol=1e-12)
    assert seq.intrinsics.fx == 481.2
    assert abs(seq.intrinsics.fy) == 480.0


def test_icl_without_gt_falls_back_to_spec_sign(tmp_path):
    root = write_icl_dir(tmp_path / "nogt_frei_png", fy=F)
    (root / "scene.gt.freiburg").unlink()
    for sign in (1, -1):
        reg = spec_yaml(tmp_path, {"i": {"root": str(root), "format": "icl", "intrinsics": [F, sign * F, 31.5, 23.5]}})
        seq = load_sequence("i", registry_path=reg)
        assert not seq.has_gt_poses
        assert seq.meta["fy_sign"] == sign
        assert seq.meta["fy_sign_errors"] is None
        assert seq.meta["fy_sign_source"].startswith("fallback")
    assert load_sequence(root).meta["fy_sign"] == -1  # no spec: ICL default -480


def test_icl_missing_associations(tmp_path):
    root = write_icl_dir(tmp_path / "x_frei_png")
    reg = spec_yaml(tmp_path, {"i": {"root": str(root), "format": "icl"}})
    (root / "associations.txt").unlink()
    with pytest.raises(DatasetError, match=r"associations\.txt: not found \(expected lines 'idx depth/idx\.png"):
        load_sequence("i", registry_path=reg)


def _povray_txt(T: np.ndarray) -> str:
    r, u, d = T[:3, 0], T[:3, 1], T[:3, 2]
    fmt = lambda v: "[" + ", ".join(f"{x:.9g}" for x in v) + "]'"  # noqa: E731
    return (f"cam_pos      = {fmt(T[:3, 3])};\ncam_dir      = {fmt(d)};\ncam_up       = {fmt(u)};\n"
            f"cam_lookat   = [0, 0, 1]';\ncam_sky      = [0, 1, 0]';\ncam_right    = {fmt(1.333 * r)};\n"
            "cam_fpoint   = [0, 0, 10]';\ncam_angle    = 90;\n")


def test_icl_native_loop_ray_depth_and_povray_cameras(tmp_path):
    root = tmp_path / "living_room_traj0_loop"
    root.mkdir()
    # the native camera has x right, y UP, z forward, so its images pair with a negative fy
    for k in range(6):
        T_up = POSES[k] @ np.diag([1.0, -1.0, 1.0, 1.0])  # same optical axis, y up ...
        T_up[:3, 0] *= -1  # ... keep it a rotation: right = up × dir
        g, z = render_plane(T_up, -F)
        K = Intrinsics(F, -F, 31.5, 23.5, W, H)
        v, u = np.mgrid[0:H, 0:W]
        ray = z * np.sqrt(((u - K.cx) / K.fx) ** 2 + ((v - K.cy) / K.fy) ** 2 + 1)
        cv2.imwrite(str(root / f"scene_00_{k:04d}.png"), cv2.merge([g, g, g]))
        (root / f"scene_00_{k:04d}.depth").write_text(" ".join(f"{x:.6f}" for x in ray.ravel()))
        (root / f"scene_00_{k:04d}.txt").write_text(_povray_txt(T_up))
    assert detect_format(root) == "icl_loop"
    reg = spec_yaml(tmp_path, {"n": {"root": str(root), "format": "icl_loop", "intrinsics": [F, -F, 31.5, 23.5]}})
    seq = load_sequence("n", registry_path=reg)
    assert len(seq) == 6
    assert seq.meta["fy_sign"] == -1
    T_up = POSES[3] @ np.diag([1.0, -1.0, 1.0, 1.0])
    T_up[:3, 0] *= -1
    np.testing.assert_allclose(seq.frames[3].pose, T_up, atol=1e-6)
    _, z3 = render_plane(T_up, -F)
    np.testing.assert_allclose(seq.load_depth(3), z3, rtol=1e-5, atol=1e-5)
    assert check_sequence(seq).images_decoded == 12
    cut = root / "scene_00_0004.depth"
    cut.write_text(cut.read_text()[: len(cut.read_text()) // 2])  # a truncated native depth file
    with pytest.raises(DatasetError, match=rf"scene_00_0004\.depth: expected {W}×{H} = {W * H} numbers"):
        check_sequence(seq)


def test_ray_to_z_centre_and_corner():
    K = Intrinsics(100.0, -100.0, 1.0, 1.0, 3, 3)
    z = ray_to_z(np.full((3, 3), 2.0), K)
    assert z[1, 1] == pytest.approx(2.0)
    assert z[0, 0] == pytest.approx(2.0 / np.sqrt(1 + 2e-4))


# ----------------------------------------------------------------------------- registry
def test_autodetect_unknown_folder_lists_what_was_looked_for(tmp_path):
    (tmp_path / "junk").mkdir()
    msg = r"looked for associations\.txt \+ \*\.gt\.freiburg .*rgb\.txt .*scene_00_NNNN\.png"
    with pytest.raises(DatasetError, match=msg):
        load_sequence(tmp_path / "junk")


def test_unknown_name_lists_valid_names():
    with pytest.raises(DatasetError, match=r"unknown dataset 'nope'; valid names: tum_fr1_xyz, .*icl_lr_kt2"):
        load_sequence("nope")


def test_relative_roots(tmp_path, monkeypatch):
    reg = tmp_path / "repo" / "datasets.yaml"
    reg.parent.mkdir()
    assert resolve_root("../data/a", reg) == (tmp_path / "data" / "a").resolve()
    monkeypatch.delenv("MSLAM_DATA", raising=False)
    assert resolve_root("TUM/x", reg) == (tmp_path / "repo" / "TUM" / "x").resolve()
    monkeypatch.setenv("MSLAM_DATA", str(tmp_path / "env"))
    assert resolve_root("TUM/x", reg) == (tmp_path / "env" / "TUM" / "x").resolve()
    assert resolve_root("TUM/x", reg, data_root=tmp_path / "arg") == (tmp_path / "arg" / "TUM" / "x").resolve()
    assert resolve_root("../data/a", reg, data_root=tmp_path / "arg") == (tmp_path / "data" / "a").resolve()


def test_stride_and_max_frames_reindex(tmp_path):
    root = write_tum_dir(tmp_path / "seq_fr1")
    seq = load_sequence(root, stride=2, max_frames=2)
    assert [f.index for f in seq.frames] == [0, 1]
    assert [round(f.timestamp, 3) for f in seq.frames] == [100.0, 100.2]
    np.testing.assert_allclose(seq.frames[1].pose, POSES[2], atol=1e-12)


def test_bench_loader_counts_frames(tmp_path):
    seq = load_sequence(write_tum_dir(tmp_path / "seq_fr1"))
    out = bench_loader(seq, n=4)
    assert out["frames"] == 4
    assert out["fps"] > 0
    assert out["seconds"] > 0


# ----------------------------------------------------------------------------- datasets.yaml
ENTRIES = yaml.safe_load(DEFAULT_REGISTRY.read_text())["datasets"]


@pytest.mark.parametrize("name", list(ENTRIES))
def test_registry_entry_well_formed(name):
    spec = get_spec(name)
    entry = ENTRIES[name]
    assert spec.format in FORMATS
    assert spec.intrinsics is not None
    assert len(entry["intrinsics"]) == 4
    assert spec.intrinsics.fx > 100
    assert 100 < abs(spec.intrinsics.fy) < 1000
    assert 0 < spec.intrinsics.cx < 700
    assert 0 < spec.intrinsics.cy < 500
    assert spec.depth_scale in (1000.0, 5000.0)
    assert spec.gt_file
    assert (spec.gt_file == "groundtruth.txt" or spec.gt_file.endswith(".gt.freiburg"))
    if spec.format == "icl":
        assert spec.extra.get("fy_sign") == "auto"
        assert spec.intrinsics.fx == 481.2
    if "fr1" in name:
        assert spec.intrinsics.dist == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    if name.startswith("fr3_"):
        assert spec.intrinsics.as_list() == [535.4, 539.2, 320.1, 247.6]
        assert spec.root.name == "rgbd_dataset_freiburg3_" + name[4:]


def test_registry_has_the_papers_sequences():
    names = {s.name for s in list_datasets()}
    need = {f"office{k}" for k in range(3)} | {f"living{k}" for k in range(3)}
    need |= {"fr3_long_office_household", "fr3_nostructure_texture_near_withloop", "fr3_structure_texture_far"}
    need |= {"tum_fr1_xyz", "tum_fr1_desk_9f", "icl_lr_kt2", "redkitchen_7scenes"}
    assert need <= names

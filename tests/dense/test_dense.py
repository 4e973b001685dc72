"""Dense reconstruction (issue 13): TSDF fusion, surface scores against closed forms, the run's stage,
``mslam fuse`` and the report's table."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from synth import make_sequence
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.dense import tsdf
from mutualslam_cli.dense.picture import fit_view, look_from_cameras
from mutualslam_cli.errors import ConfigError, GeometryError
from mutualslam_cli.pipeline import fuse_run
from mutualslam_cli.stages.dense import DENSE_KEYS

VOXEL = 0.02


def _volume(block_count: int = 40000) -> tsdf.TSDFVolume:
    return tsdf.TSDFVolume(VOXEL, 4.0, 0.1, 4.0, 8, block_count)


# ----------------------------------------------------------------------------- scores in closed form


def test_score_points_closed_form():
    # Reference: a 100 × 20 grid on z = 0 with 1.5 cm spacing; prediction: its first 10 columns.
    # Every predicted point lies on the reference: P = 1, accuracy 0. Reference column j ≥ 10 is
    # (j − 9)·1.5 cm from the prediction's last column: within 5 cm for j − 9 ≤ 3 → R = 13 / 100.
    s = 0.015
    jj, ii = np.meshgrid(np.arange(100), np.arange(20), indexing="ij")
    ref = np.stack([jj.ravel() * s, ii.ravel() * s, np.zeros(jj.size)], axis=1)
    pred = ref[jj.ravel() < 10]
    r = tsdf.score_points(pred, ref)
    p_exp, r_exp = 1.0, 13 / 100
    assert r.precision == p_exp
    assert r.recall == pytest.approx(r_exp, abs=1e-12)
    assert r.fscore == pytest.approx(2 * p_exp * r_exp / (p_exp + r_exp), abs=1e-12)  # harmonic, not arithmetic
    assert r.accuracy_m == 0.0
    d = np.maximum(np.arange(100) - 9, 0) * s  # per column, the same for every row
    assert r.completeness_m == pytest.approx(d.mean(), abs=1e-12)  # a plain mean, no cap
    assert r.completeness_median_m == pytest.approx(np.median(np.repeat(d, 20)), abs=1e-12)
    with pytest.raises(GeometryError):
        tsdf.score_points(np.zeros((0, 3)), ref)
    assert tsdf.score_points(ref + [0, 0, 1.0], ref).fscore == 0.0  # P = R = 0 → F = 0, not NaN


# ----------------------------------------------------------------------------- fusion


def _fuse_gt(seq, vol: tsdf.TSDFVolume) -> tsdf.Mesh:
    K = seq.intrinsics.K()
    for i in range(len(seq)):
        vol.integrate(seq.depth[i], K, seq.poses[i], seq.rgb[i])
    return vol.mesh(1.0)


def test_gt_depth_fused_with_gt_poses_scores_perfectly_against_itself():
    seq = make_sequence("room", n=6, width=128, height=96)
    mesh = _fuse_gt(seq, _volume())
    assert len(mesh.triangles) > 1000
    assert mesh.colours.max() <= 1.0
    assert mesh.colours.std() > 0
    s = tsdf.score_surfaces(mesh, mesh, VOXEL)
    assert s.fscore == 1.0
    assert s.precision == 1.0
    assert s.recall == 1.0
    assert s.accuracy_m == 0.0
    assert s.completeness_m == 0.0
    # the same inputs give the same mesh, to the bit
    again = _fuse_gt(seq, _volume())
    assert np.array_equal(again.vertices, mesh.vertices)
    assert np.array_equal(again.triangles, mesh.triangles)


# Floor + wall seen by one camera (x right, y down, z forward): floor y = H_FLOOR, wall z = D_WALL.
H_FLOOR, D_WALL, W, H, F = 0.30, 0.80, 160, 120, 60.0
#: the camera sits off the voxel lattice, so no plane coincides with voxel centres
CAM = np.array([0.0071, 0.0043, 0.0029])


def _floor_wall_depth(fy_sign: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact depth of the floor + wall scene at pixel centres, its K and camera pose."""
    K = np.array([[F, 0, (W - 1) / 2], [0, fy_sign * F, (H - 1) / 2], [0, 0, 1]])
    v, _ = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    yn = (v - K[1, 2]) / K[1, 1]
    with np.errstate(divide="ignore"):
        z_floor = np.where(yn > 0, H_FLOOR / yn, np.inf)
    T = np.eye(4)
    T[:3, 3] = CAM
    return np.minimum(z_floor, D_WALL).astype(np.float32), K, T


def _fuse_one(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> tsdf.Mesh:
    vol = _volume()
    vol.integrate(depth, K, T)
    return vol.mesh(1.0)


def test_depth_scaled_by_1_1_lowers_the_fscore_by_the_computed_amount():
    depth, K, T = _floor_wall_depth()
    ref, pred = _fuse_one(depth, K, T), _fuse_one(depth * 1.1, K, T)
    assert tsdf.score_surfaces(ref, ref, VOXEL).fscore == 1.0
    s = tsdf.score_surfaces(pred, ref, VOXEL)
    # Expected, from the geometry alone. Depth × 1.1 moves every point along its ray to 1.1·p: the floor
    # to y = 1.1 h (3 cm below it: within 5 cm), the wall to z = 1.1 D (8 cm behind it: outside).
    # The image spans x/z ∈ ±W/(2F), y/z ∈ ±H/(2F): the floor is seen from z0 = h·2F/H to D, the wall
    # from y = −D·H/(2F) down to h. Scores weigh area (downsampled to one point per voxel):
    wn, tau, h, d, z0 = W / F, tsdf.FSCORE_THRESHOLD_M, H_FLOOR, D_WALL, H_FLOOR * 2 * F / H
    floor = wn * (d**2 - z0**2) / 2  # ∫ width(z) dz, width(z) = wn·z
    wall = wn * d * (h + d * H / (2 * F))
    # precision: the moved floor is right up to z' = D + √(τ² − (0.1h)²), where its nearest reference
    # point becomes the floor-wall edge; beyond it and the whole moved wall are wrong
    z_ok = d + np.sqrt(tau**2 - (0.1 * h) ** 2)
    p_exp = wn * (z_ok**2 - (1.1 * z0) ** 2) / 2 / (1.21 * (floor + wall))
    # recall: the whole floor (3 cm from the moved one), and the wall's bottom strip within τ of the
    # moved floor (y > 1.1h − τ)
    r_exp = (floor + wn * d * (h - (1.1 * h - tau))) / (floor + wall)
    f_exp = 2 * p_exp * r_exp / (p_exp + r_exp)  # P 0.2135, R 0.2519, F 0.2311
    # Tolerance 0.02: the fused surfaces end within about a voxel of the true borders (at the frustum's
    # edges a voxel behind the surface must still project into the image), and the strips above are
    # 2–4 cm (1–2 voxels) wide; a border of length L moves a share by ~L·2 cm / area, 0.014 for the
    # 2.1 m floor–wall edge (measured: P −0.010, R −0.014, F −0.012). Mutations it catches: no depth
    # scaling (F = 1), a 10 cm threshold (P, R ≈ 0.9), distances to the wrong surface (P or R ≈ 0).
    assert s.precision == pytest.approx(p_exp, abs=0.02)
    assert s.recall == pytest.approx(r_exp, abs=0.02)
    assert s.fscore == pytest.approx(f_exp, abs=0.02)
    assert 1.0 - s.fscore == pytest.approx(1.0 - f_exp, abs=0.02)  # the drop from the perfect 1.0
    # The mean distances against the same geometry without the TSDF: every pixel back-projected (at 4×
    # the resolution, so the grazing floor is sampled densely), both clouds downsampled alike.
    exact, moved = _floor_wall_points(4), _floor_wall_points(4, 1.1)
    geo = tsdf.score_points(tsdf.voxel_downsample(moved, VOXEL), tsdf.voxel_downsample(exact, VOXEL))
    assert s.accuracy_m == pytest.approx(geo.accuracy_m, abs=0.003)  # 0.072 m
    assert s.completeness_m == pytest.approx(geo.completeness_m, abs=0.003)  # 0.067 m
    assert s.accuracy_median_m == pytest.approx(0.1 * d, abs=0.005)  # most predicted area is the moved wall


def _floor_wall_points(upsample: int, scale: float = 1.0) -> np.ndarray:
    """``(N, 3)`` world points of every pixel of the floor + wall scene at ``upsample``× the resolution."""
    w, h, f = W * upsample, H * upsample, F * upsample
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    xn, yn = (u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f
    with np.errstate(divide="ignore"):
        z = np.minimum(np.where(yn > 0, H_FLOOR / yn, np.inf), D_WALL) * scale
    return np.stack([xn * z, yn * z, z], axis=-1).reshape(-1, 3) + CAM


def test_negative_fy_fuses_the_same_surfaces():
    # ICL-NUIM's fy < 0: pixel rows run the other way; the fused surfaces must still be the floor and the wall.
    depth, K, T = _floor_wall_depth(fy_sign=-1.0)
    mesh = _fuse_one(depth, K, T)
    local = mesh.vertices - CAM
    on_floor = np.abs(local[:, 1] - H_FLOOR) < VOXEL
    on_wall = np.abs(local[:, 2] - D_WALL) < VOXEL
    assert len(local) > 1000
    assert np.mean(on_floor | on_wall) > 0.99
    assert on_floor.mean() > 0.1
    pos = _fuse_one(*_floor_wall_depth(fy_sign=1.0))
    assert tsdf.score_surfaces(mesh, pos, VOXEL).fscore == 1.0


def test_block_cap_bounds_the_grid():
    seq = make_sequence("room", n=6, width=128, height=96)
    probe = _volume()
    probe.integrate(seq.depth[0], seq.intrinsics.K(), seq.poses[0], seq.rgb[0])
    cap = probe.blocks + 20  # room for the first frame, not for all six
    vol = _volume(block_count=cap)
    kinds = [vol.integrate(seq.depth[i], seq.intrinsics.K(), seq.poses[i], seq.rgb[i]) for i in range(len(seq))]
    assert vol.blocks <= cap
    assert vol.grid.hashmap().capacity() == cap
    assert kinds[0] == "full"
    assert set(kinds[1:]) <= {"full", "existing_only", "skipped"}
    assert vol.frames["existing_only"] + vol.frames["skipped"] > 0
    assert len(vol.mesh().triangles) > 0
    assert tsdf.block_memory_bytes(8, 40000) == 40000 * 512 * 20


def test_mesh_ply_round_trip(tmp_path: Path):
    depth, K, T = _floor_wall_depth()
    mesh = _fuse_one(depth, K, T)
    tsdf.write_mesh(tmp_path / "m.ply", mesh)
    back = tsdf.read_mesh(tmp_path / "m.ply")
    assert len(back.triangles) == len(mesh.triangles) > 0
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    tsdf.write_mesh(tmp_path / "empty.ply", tsdf.Mesh.empty())
    assert len(tsdf.read_mesh(tmp_path / "empty.ply").vertices) == 0


def test_render_mesh_draws_the_surface():
    depth, K, T = _floor_wall_depth()
    mesh = _fuse_one(depth, K, T)
    eye, target, up = look_from_cameras(T[None], np.median(mesh.vertices, axis=0))
    eye, target = fit_view(mesh.vertices, eye, target, up, 70.0, 72 / 96)
    img = tsdf.render_mesh(mesh, eye, target, up, 96, 72, threads=1)
    assert img.shape == (72, 96, 3)
    assert img.dtype == np.uint8
    surface = np.any(img != 255, axis=-1)
    assert 0.5 < surface.mean() < 1.0
    assert len(np.unique(img[surface].sum(-1))) > 5
    # upright: seen from the camera itself, the floor alone (y = +H_FLOOR, below it) is drawn in the lower half
    on_floor = np.abs(mesh.vertices[:, 1] - CAM[1] - H_FLOOR) < VOXEL
    floor = tsdf.Mesh(mesh.vertices, mesh.triangles[on_floor[mesh.triangles].all(axis=1)], mesh.colours)
    seen = np.any(tsdf.render_mesh(floor, CAM, CAM + [0, 0, 1], np.array([0, -1.0, 0]), 96, 72) != 255, axis=-1)
    rows = np.nonzero(seen)[0]
    assert len(rows) > 100
    assert rows.min() > 36
    blank = tsdf.render_mesh(tsdf.Mesh.empty(), eye, target, up, 96, 72)
    assert (blank == 255).all()


def test_dense_config_is_validated():
    assert load_config(overrides=["dense.enabled=true"]).dense.enabled
    with pytest.raises(ConfigError, match=r"dense.voxel_size"):
        load_config(overrides=["dense.voxel_size=0"])
    with pytest.raises(ConfigError, match=r"dense.depth_min"):
        load_config(overrides=["dense.depth_min=5"])


# ----------------------------------------------------------------------------- the run's stage, end to end


def _cfg(tmp: Path, *extra: str):
    return load_config(CONFIG_DIR / "smoke.yaml", [f"net.weights={tmp / 'weights'}", "dense.enabled=true",
                                                   "eval.save_weights=true", *extra])


@pytest.fixture(scope="module")
def dense_run(tiny_run):
    from mutualslam_cli.pipeline import run_sequence

    tmp, seq = tiny_run
    return tmp, seq, run_sequence(seq, _cfg(tmp), out=tmp / "dense", command=["test"])


def test_run_with_dense_stage_writes_meshes_picture_and_scores(dense_run):
    import open3d as o3d

    _, _, r = dense_run
    flat = r.summary.flat()
    for key in DENSE_KEYS:
        assert isinstance(flat[key], float), (key, r.summary.notes.get(key))
    assert 0 <= flat["dense.fscore_5cm.adapted"] <= 1
    assert flat["dense.accuracy_m.pretrained"] > 0
    # the oracle front end (gt-depth) has GT poses and a metric map: the Sim(3) is the identity
    assert flat["dense.sim3_scale"] == pytest.approx(1.0, abs=1e-6)
    assert flat["dense.frames"] == flat["vo.keyframes"] == flat["dense.frames_reference"]
    for name in ("pretrained", "adapted", "gt"):
        mesh = o3d.io.read_triangle_mesh(str(r.folder / f"mesh_{name}.ply"))
        assert len(mesh.triangles) > 0, name
        assert mesh.has_vertex_colors(), name
    assert (r.folder / "dense.png").stat().st_size > 10_000
    stages = r.summary.nested()["timing"]["stage_s"]
    assert stages["dense"] > 0
    assert sum(stages.values()) == pytest.approx(flat["timing.total_s"])
    assert not list(r.folder.glob(".dense-*"))  # the prediction files are gone


def test_fuse_on_the_finished_run_gives_the_same_scores(dense_run, tmp_path):
    _tmp, _, r = dense_run
    root = tmp_path / "copy"
    shutil.copytree(r.folder.parents[2], root)
    folder = root / r.folder.relative_to(r.folder.parents[2])
    out = fuse_run(folder, command=["test"]).flat()
    flat = r.summary.flat()
    for key in DENSE_KEYS + ("dense.scale.pretrained", "dense.scale.adapted", "dense.frames"):
        assert out[key] == flat[key], key
    written = json.loads((folder / "summary.json").read_text())
    assert written["dense"]["fscore_5cm"] == r.summary.nested()["dense"]["fscore_5cm"]
    assert "fuse" in json.loads((folder / "manifest.json").read_text())
    # the CLI prints the table
    cli = CliRunner().invoke(app, ["fuse", str(folder)])
    assert cli.exit_code == 0, cli.output
    assert "F-score @5cm" in cli.output
    assert f"{flat['dense.fscore_5cm.adapted']:.4f}" in cli.output


def test_fuse_every_frame(dense_run, tmp_path):
    # dense.every=1: every tracked frame, aligned by the all-frames trajectory (a window with < 3 keyframes fuses so)
    _, _, r = dense_run
    root = tmp_path / "every"
    shutil.copytree(r.folder.parents[2], root)
    s = fuse_run(root / r.folder.relative_to(r.folder.parents[2]), ["dense.every=1"]).flat()
    assert s["dense.frames"] == 12
    assert s["dense.source"].startswith("every k-th frame (k = 1)")
    assert all(isinstance(s[k], float) for k in DENSE_KEYS)
    assert s["dense.sim3_scale"] == pytest.approx(1.0, abs=1e-6)


def test_sequence_without_gt_depth_gives_null_scores_with_the_reason(dense_run, tmp_path):
    from mutualslam_cli.datasets.registry import load_sequence

    _tmp, seq_dir, r = dense_run
    root = tmp_path / "nodepth"
    shutil.copytree(r.folder.parents[2], root)
    folder = root / r.folder.relative_to(r.folder.parents[2])
    seq = load_sequence(seq_dir)
    seq.frames = [dataclasses.replace(f, depth_path=None, pose=f.pose) for f in seq.frames]
    s = fuse_run(folder, seq=seq)
    flat = s.flat()
    for key in DENSE_KEYS:
        assert flat[key] is None, key
        assert "no GT depth" in s.notes[key], key
    # the predictions are still fused (metric by the Sim(3) to the GT poses); there is no reference mesh
    assert (folder / "mesh_adapted.ply").is_file()
    assert not (folder / "mesh_gt.ply").exists()
    assert flat["dense.frames_reference"] == 0
    assert (folder / "dense.png").is_file()


def test_fuse_without_weights_is_one_line(dense_run, tmp_path):
    _, _, r = dense_run
    folder = tmp_path / "run"
    shutil.copytree(r.folder, folder, ignore=shutil.ignore_patterns("weights"))
    out = CliRunner().invoke(app, ["fuse", str(folder)])
    assert out.exit_code == 1
    assert "Traceback" not in out.output
    text = " ".join(out.output.split())
    assert text.startswith("error:")
    assert str(folder) in text
    assert "eval.save_weights=true" in text


def test_report_shows_the_dense_table(dense_run, tmp_path):
    from mutualslam_cli.report.tables import build_tables, collect, write_report

    tmp, _, r = dense_run
    rep = build_tables(collect([tmp / "dense"]))
    t = rep.tables["dense"]
    # one row per scaling, the headline (one VO scale per sequence) first
    assert list(t["scaling"]) == ["sequence (VO)", "per frame (VO)", "per frame to GT (oracle)"]
    assert t.iloc[0]["F@5cm adapt"] == pytest.approx(r.summary.get("dense.fscore_5cm.adapted"))
    assert t.iloc[0]["acc pre m"] == pytest.approx(r.summary.get("dense.accuracy_m.pretrained"))
    for row, p in ((1, "frame_scale"), (2, "gt_scale")):
        assert t.iloc[row]["F@5cm pre"] == pytest.approx(r.summary.nested()["dense"][p]["fscore_5cm"]["pretrained"])
        assert t.iloc[row]["fallback frames"] == r.summary.nested()["dense"][p]["fallback_frames"]["adapted"]
    assert "oracle" in rep.titles["dense"]
    assert "one scale per model and sequence" in rep.titles["dense"]
    files = write_report(rep, tmp_path / "rep")
    assert any(p.parent.name == "dense" and p.suffix == ".png" for p in files)
    assert "dense/dense_" in (tmp_path / "rep" / "report.md").read_text()
    # runs without the stage: no table
    assert "dense" not in build_tables(collect([tmp / "dense"]).drop(columns=["dense.time_s"])).tables


# ----------------------------------------------------------------------------- the three depth scalings


def _gt_predictors(monkeypatch, seq_dir: Path, cfg_factors: dict[str, np.ndarray]) -> None:
    """Make the dense stage's networks predict GT depth (nearest pixel at network resolution, 96 × 64)
    times a per-frame factor: ``cfg_factors[model][frame]`` (models in the stage's order)."""
    import cv2

    from mutualslam_cli.datasets.registry import load_sequence
    from mutualslam_cli.stages import evaluation
    from mutualslam_cli.vo.camera import Undistorter

    seq = load_sequence(seq_dir)
    und = Undistorter(seq.intrinsics)
    frame_of = {und.image(seq.load_rgb(i)).tobytes(): i for i in range(len(seq))}
    depth = [cv2.resize(und.depth(seq.load_depth(i)), (96, 64), interpolation=cv2.INTER_NEAREST)
             for i in range(len(seq))]
    models = iter(cfg_factors)

    def make_predictor(net, cfg, fast, calibration=None):
        c = cfg_factors[next(models)]

        def predict(frames):
            idx = [frame_of[f.tobytes()] for f in frames]
            return np.stack([depth[i] * c[i] for i in idx]).astype(np.float32)
        return predict

    monkeypatch.setattr(evaluation, "make_predictor", make_predictor)  # predictors_for builds them


def test_per_frame_scalings_tell_scale_jitter_from_shape(dense_run, tmp_path, monkeypatch):
    # Both "models" predict exact GT depth up to scale: the pre-trained one with a random factor per frame
    # (±40 %: scale jitter), the adapted one with one factor for the whole sequence. One scale per sequence
    # fixes the adapted one only; each frame's own scale from the oracle front end's exact sparse points
    # (gt-depth), and each frame scaled to GT, fix both: what is left is the network-resolution shape.
    _tmp, seq_dir, r = dense_run
    jitter = np.exp(np.random.default_rng(3).uniform(-0.4, 0.4, 12))
    _gt_predictors(monkeypatch, seq_dir, {"pretrained": jitter, "adapted": np.full(12, 1.7)})
    root = tmp_path / "scalings"
    shutil.copytree(r.folder.parents[2], root)
    folder = root / r.folder.relative_to(r.folder.parents[2])
    s = fuse_run(folder).flat()
    F = {p: {m: s[f"dense.{p}fscore_5cm.{m}"] for m in ("pretrained", "adapted")}
         for p in ("", "frame_scale.", "gt_scale.")}
    assert F[""]["adapted"] > 0.9
    assert F[""]["pretrained"] < 0.5
    for p in ("frame_scale.", "gt_scale."):
        assert F[p]["pretrained"] > 0.9, p
        assert F[p]["adapted"] > 0.9, p
        assert F[p]["pretrained"] == pytest.approx(F[p]["adapted"], abs=0.02), p  # the same shape
        assert s[f"dense.{p}fallback_frames.pretrained"] == 0
    # the per-frame factors found are the inverse of the ones planted (up to the shape at 96 × 64)
    from mutualslam_cli.datasets.associate import read_tum_trajectory
    from mutualslam_cli.datasets.registry import load_sequence

    index = {f.timestamp: i for i, f in enumerate(load_sequence(seq_dir).frames)}
    kf = [index[float(t)] for t in read_tum_trajectory(folder / "traj_kf.txt").timestamps]
    assert len(kf) == s["dense.frames"] == 6
    truth = float(np.std(np.log(1 / jitter[kf])))
    for p in ("frame_scale.", "gt_scale."):
        assert s[f"dense.{p}metric_scale_log_std.pretrained"] == pytest.approx(truth, rel=0.05), p
        assert s[f"dense.{p}metric_scale_log_std.adapted"] < 0.02, p
        assert s[f"dense.{p}metric_scale_median.adapted"] == pytest.approx(1 / 1.7, rel=0.02), p
    assert s["dense.metric_scale.adapted"] == pytest.approx(1 / 1.7, rel=0.02)
    # every frame, without the GT scaling: only keyframes observe map points, the others take the sequence
    # factor (counted); the GT scaling's keys are null with the reason, and the sequence keys are unchanged
    _gt_predictors(monkeypatch, seq_dir, {"pretrained": jitter, "adapted": np.full(12, 1.7)})
    e = fuse_run(folder, ["dense.every=1", "dense.scalings=[sequence, frame]"])
    f = e.flat()
    assert f["dense.frames"] == 12
    assert f["dense.frame_scale.fallback_frames.pretrained"] == 12 - 6
    assert f["dense.frame_scale.fscore_5cm.pretrained"] > f["dense.fscore_5cm.pretrained"]
    for key in ("dense.gt_scale.fscore_5cm.adapted", "dense.gt_scale.fallback_frames.pretrained"):
        assert f[key] is None
        assert "dense.scalings leaves out 'gt'" in e.notes[key]


def test_fuse_prints_every_scaling_it_scored(dense_run, tmp_path):
    _, _, r = dense_run
    root = tmp_path / "cli"
    shutil.copytree(r.folder.parents[2], root)
    out = CliRunner().invoke(app, ["fuse", str(root / r.folder.relative_to(r.folder.parents[2]))],
                             env={"COLUMNS": "200"})
    assert out.exit_code == 0, out.output
    for scale in ("sequence (VO)", "per frame (VO)", "per frame (GT, oracle)"):
        assert scale in out.output

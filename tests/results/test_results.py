"""Result files: atomic writes, summary nulls with reasons, manifest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mutualslam_cli import atomic
from mutualslam_cli.results.map_ply import read_ply, write_ply
from mutualslam_cli.results.run_folder import is_complete, manifest, run_dir, write_json
from mutualslam_cli.results.summary import SUMMARY_KEYS, Summary, flatten


def test_summary_absent_values_are_null_with_reason():
    s = Summary()
    s.set("depth.pcd.lsq.adapted", 71.5)
    s.set("map.esi.vo", float("nan"), "no map point has GT depth")
    d = s.to_dict()
    assert d["depth"]["pcd"]["lsq"]["adapted"] == 71.5
    assert d["map"]["esi"]["vo"] is None
    assert d["notes"]["map.esi.vo"] == "no map point has GT depth"
    # Every required key exists; the unset ones are null with a reason, never 0.
    flat = flatten(d)
    for k in SUMMARY_KEYS:
        assert k in flat
        if k not in ("depth.pcd.lsq.adapted",):
            assert flat[k] is None
            assert k in d["notes"]


def test_atomic_write_keeps_old_file_on_failure(tmp_path: Path, monkeypatch):
    p = tmp_path / "summary.json"
    write_json(p, {"a": 1})

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_json(p, {"a": 2})
    assert json.loads(p.read_text()) == {"a": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["summary.json"]  # no temp file left behind


def test_json_is_plain(tmp_path: Path):
    p = tmp_path / "x.json"
    write_json(p, {"n": np.int64(3), "v": np.float32(0.5), "arr": np.arange(3), "bad": np.nan, "p": tmp_path})
    d = json.loads(p.read_text())
    assert d == {"n": 3, "v": 0.5, "arr": [0, 1, 2], "bad": None, "p": str(tmp_path)}


def test_manifest_records_versions_and_seed():
    m = manifest(["mslam", "run", "x"], 7, {"total_s": 1.0})
    assert m["seed"] == 7
    assert m["command"][1] == "run"
    assert "torch" in m["versions"]
    assert "numpy" in m["versions"]


def test_run_dir_layout(tmp_path: Path):
    d = run_dir(tmp_path, "tum_fr1_xyz", "replay+ewc", 2)
    assert d == tmp_path / "tum_fr1_xyz" / "replay+ewc" / "seed2"
    assert not is_complete(d)


def test_atomic_writes_have_the_usual_permissions(tmp_path):
    """Result files are readable like any other output (mkstemp alone would leave them 0600)."""
    import stat

    from mutualslam_cli import atomic

    path = tmp_path / "x.txt"
    atomic.atomic_write_text(path, "hello")
    assert path.read_text() == "hello"
    plain = tmp_path / "plain.txt"
    with open(plain, "w") as f:  # what open() gives under this process's umask
        f.write("x")
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o666 & ~atomic._UMASK
    assert not list(tmp_path.glob(".x.txt.*"))  # no temporary file left behind


# ----------------------------------------------------------------------------- map PLYs


def _fake_map():
    """Two keyframes at the origin, four points: host pixel, inverse depth (map units); GT depth
    2 m everywhere except a hole (0) at the last point's pixel."""
    from types import SimpleNamespace

    from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
    from mutualslam_cli.types import Intrinsics, Trajectory

    intr = Intrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)
    depth = np.full((24, 32), 2.0)
    depth[20, 30] = 0.0  # no GT here
    seq = SimpleNamespace(intrinsics=intr, load_depth=lambda i: depth)
    kfs = [Keyframe(k, k, float(k), np.eye(4)) for k in range(2)]
    # depths 2·e^{+0.6}, 2·e^{-0.6}, 2 (d = 0.6, -0.6, 0) and one point over the hole
    z = np.array([2 * np.exp(0.6), 2 * np.exp(-0.6), 2.0, 3.0])
    pts = MapPoints(np.arange(4), np.array([0, 0, 1, 1]), np.array([[5.0, 5], [10, 12], [20, 3], [30, 20]]),
                    1 / z, np.zeros(4), [np.array([0])] * 4, [np.zeros((1, 2))] * 4)
    vo = VOResult(kfs, pts, intr, Trajectory(np.zeros(0), np.zeros((0, 4, 4))), np.zeros(0, int))
    return seq, vo


def test_map_log_depth_errors_and_esi_are_one_computation():
    from mutualslam_cli.metrics.depth import esi
    from mutualslam_cli.metrics.slam import map_esi, map_log_depth_errors

    seq, vo = _fake_map()
    d = map_log_depth_errors(seq, vo)
    np.testing.assert_allclose(d[:3], [0.6, -0.6, 0.0], atol=1e-12)
    assert np.isnan(d[3])
    e, n = map_esi(seq, vo)
    assert n == 3
    assert e == pytest.approx(esi(1 / vo.points.inv_depth[:3], np.full(3, 2.0)))
    keep = np.array([True, False, True, True])
    np.testing.assert_array_equal(map_log_depth_errors(seq, vo, keep), d[keep])


def test_map_ply_round_trip_through_open3d(tmp_path: Path):
    import open3d as o3d

    from mutualslam_cli.metrics.slam import map_log_depth_errors
    from mutualslam_cli.results import map_ply

    seq, vo = _fake_map()
    d = map_log_depth_errors(seq, vo)  # mean over GT points is 0: colours show d itself
    pts = vo.points_world()
    write_ply(tmp_path / "map_vo.ply", pts, d)
    assert not list(tmp_path.glob(".map_vo.ply.*"))  # no temporary file left behind
    pc = o3d.io.read_point_cloud(str(tmp_path / "map_vo.ply"))  # the plain legacy reader
    np.testing.assert_allclose(np.asarray(pc.points), pts, rtol=0, atol=1e-12)
    want = np.array([map_ply.ERROR_FAR, map_ply.ERROR_NEAR, map_ply.ERROR_ZERO, map_ply.NO_GT])
    np.testing.assert_allclose(np.asarray(pc.colors), want, atol=0.6 / 255)
    p2, c2, e2 = read_ply(tmp_path / "map_vo.ply")
    np.testing.assert_allclose(p2, pts, atol=1e-12)
    np.testing.assert_allclose(c2, want, atol=0.6 / 255)
    np.testing.assert_allclose(e2, d, atol=1e-6)  # NaN where there is no GT
    # half the saturation error is half way to red; an offset shared by every point (scale) is removed
    half = map_ply.error_colours(np.array([0.25, -0.25, np.nan]) + 3.0)
    np.testing.assert_allclose(half[0], (np.array(map_ply.ERROR_ZERO) + map_ply.ERROR_FAR) / 2)
    np.testing.assert_allclose(half[2], map_ply.NO_GT)


def test_map_ply_empty_and_old_and_bad(tmp_path: Path):
    from mutualslam_cli.errors import DatasetError

    write_ply(tmp_path / "empty.ply", np.zeros((0, 3)), np.zeros(0))
    p, c, e = read_ply(tmp_path / "empty.ply")
    assert p.shape == (0, 3)
    old = tmp_path / "old.ply"  # the xyz-only ASCII maps of earlier runs
    old.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                   "property float z\nend_header\n1 2 3\n4 5 6\n")
    p, c, e = read_ply(old)
    np.testing.assert_allclose(p, [[1, 2, 3], [4, 5, 6]])
    assert c is None
    assert e is None
    write_ply(tmp_path / "grey.ply", p)  # without errors: every point "no GT"
    assert read_ply(tmp_path / "grey.ply")[2] is None
    (tmp_path / "bad.ply").write_text("not a ply\n")
    with pytest.raises(DatasetError, match=r"bad.ply"):
        read_ply(tmp_path / "bad.ply")
    with pytest.raises(DatasetError, match=r"missing.ply"):
        read_ply(tmp_path / "missing.ply")


def test_atomic_write_with_a_failing_writer_keeps_the_old_file(tmp_path: Path):
    from mutualslam_cli.atomic import atomic_write_with

    target = tmp_path / "mesh.ply"
    target.write_text("old")
    with pytest.raises(OSError, match=r"mesh.ply: could not write the mesh"):
        atomic_write_with(target, lambda name: False, "mesh")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply"]
    atomic_write_with(target, lambda name: Path(name).write_text("new") > 0 and name.endswith(".ply"), "mesh")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply"]

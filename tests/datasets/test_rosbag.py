"""ROS bags → TUM-layout folders (:mod:`mutualslam_cli.datasets.recordings.rosbag`), on bags written from rendered
sequences."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from bagtools import CAMERA_INFO, RGB_RAW, encode_jpeg, write_bag_from_tum
from synth import make_tum_dir

from mutualslam_cli.datasets.associate import read_list_file, read_tum_trajectory
from mutualslam_cli.datasets.recordings.recording import RecordingOptions, open_recording
from mutualslam_cli.datasets.recordings.rosbag import decode_depth, quantise_metres, select_topics
from mutualslam_cli.datasets.registry import load_spec
from mutualslam_cli.datasets.tum import read_intrinsics_txt
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics

DIST = (0.12, -0.25, 0.001, -0.002, 0.07)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("tum"), scene="room", n=8, width=64, height=48)


def _bag_name(tmp: Path, ros: int, stem: str = "seq") -> Path:
    return tmp / (f"{stem}.bag" if ros == 1 else stem)


def _convert(info: dict, tmp: Path, **kw):
    opts = RecordingOptions(depth_topic=info["depth"], pose_topic=info["pose"], cache=tmp / "cache", **kw)
    spec = open_recording(info["bag"], opts)
    return spec, load_spec(spec)


def _folder_rgb(folder: Path, i: int) -> np.ndarray:
    path = folder / read_list_file(folder / "rgb.txt").paths[i]
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _folder_depth_raw(folder: Path, i: int) -> np.ndarray:
    return cv2.imread(str(folder / read_list_file(folder / "depth.txt").paths[i]), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize(("ros", "depth", "pose", "auto_rgb"), [
    (1, "16UC1", "pose", True), (1, "32FC1", "transform", False),
    (2, "16UC1", "odometry", False), (2, "32FC1", "pose", True)])
def test_raw_bag_round_trip(folder, tmp_path, ros, depth, pose, auto_rgb):
    info = write_bag_from_tum(folder, _bag_name(tmp_path, ros), ros_version=ros, depth=depth, dist=DIST,
                              pose_topic=pose)
    spec, seq = _convert(info, tmp_path, rgb_topic=None if auto_rgb else info["rgb"])
    rgb_l = read_list_file(folder / "rgb.txt")
    assert len(seq) == len(rgb_l) == 8
    # header stamps, not the record times (which lag by 12.3 ms)
    np.testing.assert_allclose([f.timestamp for f in seq.frames], rgb_l.timestamps, rtol=0, atol=1e-6)
    for i in range(len(seq)):
        np.testing.assert_array_equal(seq.load_rgb(i), _folder_rgb(folder, i))
        raw = _folder_depth_raw(folder, i)
        if depth == "32FC1":  # metres back to the folder's 5000/m units, bit for bit
            conv = cv2.imread(str(seq.frames[i].depth_path), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(conv, raw)
        else:  # millimetres: 0.5 mm rounding of the 0.2 mm units
            np.testing.assert_allclose(seq.load_depth(i), raw / 5000.0, rtol=0, atol=0.5e-3 + 1e-7)
    assert seq.depth_scale == (5000.0 if depth == "32FC1" else 1000.0)
    k = read_intrinsics_txt(folder / "intrinsics.txt")
    assert seq.intrinsics == Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height, DIST)
    gt = read_tum_trajectory(folder / "groundtruth.txt")
    assert seq.gt is not None
    assert len(seq.gt) == len(gt)
    np.testing.assert_allclose(seq.gt.timestamps, gt.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(seq.gt.poses, gt.poses, rtol=0, atol=1e-6)
    meta = json.loads((spec.root / "source.json").read_text())
    assert meta["messages"][info["rgb"]] == 8
    assert meta["messages"][info["depth"]] == 8
    assert meta["encodings"][info["depth"]] == [depth]
    assert meta["intrinsics_source"] == f"CameraInfo {CAMERA_INFO}"
    assert any("0.2 mm" in n for n in meta["notes"]) == (depth == "32FC1")


@pytest.mark.parametrize(("ros", "rgb", "storage"),
                         [(1, "jpeg", "sqlite3"), (2, "png", "mcap"), (2, "jpeg", "sqlite3")])
def test_compressed_colour_stored_as_is(folder, tmp_path, ros, rgb, storage):
    info = write_bag_from_tum(folder, _bag_name(tmp_path, ros), ros_version=ros, rgb=rgb, depth="compressedDepth",
                              pose_topic=False, storage=storage)
    _spec, seq = _convert(info, tmp_path, rgb_topic=info["rgb"])
    assert len(seq) == 8
    assert seq.depth_scale == 1000.0
    assert seq.gt is None
    paths = read_list_file(folder / "rgb.txt").paths
    for i, f in enumerate(seq.frames):
        src = folder / paths[i]
        assert f.rgb_path.suffix == (".jpg" if rgb == "jpeg" else ".png")
        assert f.rgb_path.read_bytes() == (encode_jpeg(src) if rgb == "jpeg" else src.read_bytes())
        if rgb == "png":
            np.testing.assert_array_equal(seq.load_rgb(i), _folder_rgb(folder, i))
        mm = np.round(_folder_depth_raw(folder, i) / 5.0).astype(np.uint16)
        np.testing.assert_array_equal(cv2.imread(str(f.depth_path), cv2.IMREAD_UNCHANGED), mm)


@pytest.mark.parametrize(("encoding", "pad", "bigendian"), [("bgr8", 5, True), ("bgra8", 0, False), ("mono8", 3, True),
                                                      ("rgba8", 8, False)])
def test_row_padding_and_encodings(folder, tmp_path, encoding, pad, bigendian):
    info = write_bag_from_tum(folder, tmp_path / "pad.bag", rgb_encoding=encoding, pad=pad, bigendian=bigendian,
                              pose_topic=False)
    _, seq = _convert(info, tmp_path, rgb_topic=RGB_RAW)
    for i in range(len(seq)):
        rgb = _folder_rgb(folder, i)
        if encoding == "mono8":
            np.testing.assert_array_equal(seq.load_gray(i), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        else:
            np.testing.assert_array_equal(seq.load_rgb(i), rgb)
        mm = np.round(_folder_depth_raw(folder, i) / 5.0).astype(np.uint16)
        np.testing.assert_array_equal(cv2.imread(str(seq.frames[i].depth_path), cv2.IMREAD_UNCHANGED), mm)


def test_missing_topic_lists_the_bags_topics(folder, tmp_path):
    info = write_bag_from_tum(folder, tmp_path / "a.bag", depth=None, pose_topic=False)
    with pytest.raises(DatasetError) as err:
        _convert(info, tmp_path, rgb_topic="/camera/color/image_raw")
    msg = str(err.value)
    assert "\n" not in msg
    assert "/camera/color/image_raw" in msg
    assert f"{RGB_RAW} (sensor_msgs/msg/Image)" in msg
    assert f"{CAMERA_INFO} (sensor_msgs/msg/CameraInfo)" in msg
    assert not any((tmp_path / "cache").iterdir())  # nothing half-converted left behind


def test_unsupported_encoding_is_one_line(folder, tmp_path):
    info = write_bag_from_tum(folder, tmp_path / "b.bag", rgb_encoding="bayer_rggb8", depth=None, pose_topic=False)
    with pytest.raises(DatasetError, match="bayer_rggb8") as err:
        _convert(info, tmp_path)
    assert "\n" not in str(err.value)
    assert RGB_RAW in str(err.value)


def test_no_camera_info_asks_for_a_camera_file(folder, tmp_path):
    info = write_bag_from_tum(folder, tmp_path / "c", ros_version=2, camera_info=False, depth=None)
    with pytest.raises(DatasetError, match=r"no intrinsics.*--camera") as err:
        _convert(info, tmp_path)
    assert "\n" not in str(err.value)


def test_topic_choice():
    img, comp, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
    topics = {"/cam/rgb/image_raw": img, "/cam/rgb/image_raw/compressed": comp, "/cam/depth/image_raw": img,
              "/cam/rgb/camera_info": info, "/cam/depth/camera_info": info, "/tf": "tf2_msgs/msg/TFMessage"}
    with pytest.raises(DatasetError, match="--rgb-topic") as err:
        select_topics(Path("x.bag"), topics, RecordingOptions())
    assert "/cam/rgb/image_raw, /cam/rgb/image_raw/compressed" in str(err.value)
    sel = select_topics(Path("x.bag"), topics, RecordingOptions(rgb_topic="/cam/rgb/image_raw/compressed",
                                                                depth_topic="cam/depth/image_raw"))
    assert sel == {"rgb": "/cam/rgb/image_raw/compressed", "depth": "/cam/depth/image_raw",
                   "camera_info": "/cam/rgb/camera_info"}
    with pytest.raises(DatasetError, match=r"'/tf' .* is tf2_msgs/msg/TFMessage; expected geometry_msgs"):
        select_topics(Path("x.bag"), topics, RecordingOptions(rgb_topic="/cam/rgb/image_raw", pose_topic="/tf"))


def test_depth_conversions():
    d = np.array([[np.nan, np.inf, -1.0, 0.0], [1.0002, 13.107, 13.2, 0.00009]])
    out, far = quantise_metres(d)
    np.testing.assert_array_equal(out, [[0, 0, 0, 0], [5001, 65535, 0, 0]])
    assert out.dtype == np.uint16
    assert far == 1
    # compressed_depth_image_transport's 32FC1: inverse depth v = A / d + B in a PNG after {int32, float A, float B}
    a, b = 100.0, 1.0 - 100.0 / 10.0
    metres = np.array([[0.5, 1.0, 2.0], [4.0, 0.0, 3.3]], np.float32)
    with np.errstate(divide="ignore"):
        inv = np.where(metres > 0, np.round(a / metres + b), 0).astype(np.uint16)
    header = np.array([0], "<i4").tobytes() + np.array([a, b], "<f4").tobytes()
    msg = SimpleNamespace(format="32FC1; compressedDepth png", data=header + cv2.imencode(".png", inv)[1].tobytes())
    raw, scale, enc, _ = decode_depth(msg, "sensor_msgs/msg/CompressedImage", "/d")
    assert scale == 5000.0
    assert enc.startswith("32FC1")
    with np.errstate(divide="ignore"):
        expected = np.where(inv > 0, a / (inv - np.float32(b)), 0.0)  # 3.3 m comes back as 100 / 30 m
    np.testing.assert_allclose(raw / 5000.0, expected, rtol=0, atol=1e-4)
    np.testing.assert_allclose(raw / 5000.0, metres, rtol=0, atol=0.5 * 3.3**2 / a)
    assert raw[1, 1] == 0
    with pytest.raises(DatasetError, match=r"^/d: .*'8UC1'"):
        decode_depth(SimpleNamespace(encoding="8UC1"), "sensor_msgs/msg/Image", "/d")


@pytest.mark.data
def test_real_fr1_window(shared_data, tmp_path):
    """Five frames of TUM fr1/xyz (640×480, fr1 distortion) through a ROS 1 bag with 32FC1 depth."""
    src = shared_data / "tum_fr1_xyz"
    fr1 = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
    dist = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    info = write_bag_from_tum(src, tmp_path / "fr1.bag", depth="32FC1", dist=dist, intrinsics=fr1, max_frames=5)
    _, seq = _convert(info, tmp_path, rgb_topic=info["rgb"])
    assert len(seq) >= 4
    assert seq.intrinsics == Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, dist)
    rgb_l, dep_l = read_list_file(src / "rgb.txt"), read_list_file(src / "depth.txt")
    for i, f in enumerate(seq.frames):
        k = int(np.argmin(np.abs(rgb_l.timestamps - f.timestamp)))
        assert abs(rgb_l.timestamps[k] - f.timestamp) < 1e-6
        np.testing.assert_array_equal(seq.load_rgb(i), _folder_rgb(src, k))
        j = int(np.argmin(np.abs(dep_l.timestamps - float(f.depth_path.stem))))
        np.testing.assert_array_equal(cv2.imread(str(f.depth_path), cv2.IMREAD_UNCHANGED), _folder_depth_raw(src, j))
    gt = read_tum_trajectory(src / "groundtruth.txt")
    assert seq.gt is not None
    idx = np.searchsorted(gt.timestamps, seq.gt.timestamps)
    np.testing.assert_allclose(gt.timestamps[idx], seq.gt.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(gt.poses[idx], seq.gt.poses, rtol=0, atol=1e-6)

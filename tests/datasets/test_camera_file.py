"""Camera files: OpenCV YAML/XML (written by cv2.FileStorage), ROS and Kalibr YAML, plain text."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mutualslam_cli.datasets.recordings.camera_file import read_camera_file
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics

K = np.array([[525.5, 0.0, 319.75], [0.0, 524.25, 239.5], [0.0, 0.0, 1.0]])
D5 = (0.25, -0.75, 0.002, -0.001, 0.5)
WANT = Intrinsics(525.5, 524.25, 319.75, 239.5, 640, 480, D5)


def _filestorage(path: Path, entries: dict) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in entries.items():
        fs.write(k, v)
    fs.release()
    return path


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_opencv_filestorage(tmp_path: Path, suffix: str) -> None:
    p = _filestorage(tmp_path / f"calib{suffix}", {"image_width": 640, "image_height": 480, "camera_matrix": K,
                                                   "distortion_coefficients": np.array([D5])})
    assert p.read_text().startswith("%YAML" if suffix == ".yaml" else "<?xml")  # OpenCV 5: '%YAML 1.2'
    assert read_camera_file(p) == WANT


def test_opencv4_yaml_header(tmp_path: Path) -> None:
    """The '%YAML:1.0' files of OpenCV 4's calibration sample (pyyaml cannot read them)."""
    p = tmp_path / "out_camera_data.yml"
    p.write_text("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
                 "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                 "   data: [ 525.5, 0., 319.75, 0., 524.25, 239.5, 0., 0., 1. ]\n"
                 "distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
                 "   data: [ 0.25, -0.75, 0.002, -0.001, 0.5 ]\navg_reprojection_error: 0.31\n")
    assert read_camera_file(p) == WANT


@pytest.mark.parametrize(("dist", "want"), [
    (np.array([[0.25], [-0.75], [0.002], [-0.001]]), (0.25, -0.75, 0.002, -0.001, 0.0)),  # 4×1: k3 = 0
    (np.array([[0.25, -0.75, 0.002, -0.001, 0.5, 0.1, 0.2, 0.3]]), D5),                   # 1×8: first 5
    (np.zeros((1, 5)), None),                                                              # all zero
])
def test_opencv_other_keys_and_distortion_shapes(tmp_path: Path, dist: np.ndarray, want) -> None:
    p = _filestorage(tmp_path / "c.yml", {"cameraMatrix": K, "distCoeffs": dist})
    assert read_camera_file(p) == Intrinsics(525.5, 524.25, 319.75, 239.5, 0, 0, want)
    p = _filestorage(tmp_path / "k.yml", {"K": K, "D": dist})
    assert read_camera_file(p).dist == want


def test_ros_camera_calibration_yaml(tmp_path: Path) -> None:
    p = tmp_path / "ost.yaml"
    p.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: narrow_stereo\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [525.5, 0, 319.75, 0, 524.25, 239.5, 0, 0, 1]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.25, -0.75, 0.002, -0.001, 0.5]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [525, 0, 320, 0, 0, 524, 240, 0, 0, 0, 1, 0]\n")
    assert read_camera_file(p) == WANT


def test_kalibr_camchain(tmp_path: Path) -> None:
    p = tmp_path / "camchain.yaml"
    p.write_text("cam0:\n  camera_model: pinhole\n  intrinsics: [525.5, 524.25, 319.75, 239.5]\n"
                 "  distortion_model: radtan\n  distortion_coeffs: [0.25, -0.75, 0.002, -0.001]\n"
                 "  resolution: [640, 480]\n")
    assert read_camera_file(p) == Intrinsics(525.5, 524.25, 319.75, 239.5, 640, 480, (0.25, -0.75, 0.002, -0.001, 0))


@pytest.mark.parametrize(("text", "want"), [
    ("525.5 524.25 319.75 239.5\n", Intrinsics(525.5, 524.25, 319.75, 239.5, 0, 0, None)),
    ("# fx fy cx cy k1 k2 p1 p2 k3\n525.5 524.25 319.75 239.5 0.25 -0.75 0.002 -0.001 0.5  # phone\n",
     Intrinsics(525.5, 524.25, 319.75, 239.5, 0, 0, D5)),
    ("525.5 524.25 319.75 239.5 0.25 -0.75 0.002 -0.001\n",
     Intrinsics(525.5, 524.25, 319.75, 239.5, 0, 0, (0.25, -0.75, 0.002, -0.001, 0.0))),
    ("525.5 0 319.75\n0 524.25 239.5\n0 0 1\n", Intrinsics(525.5, 524.25, 319.75, 239.5, 0, 0, None)),
])
def test_plain_text(tmp_path: Path, text: str, want: Intrinsics) -> None:
    p = tmp_path / "camera.txt"
    p.write_text(text)
    assert read_camera_file(p) == want


def _bad_opencv_2x3(p: Path) -> None:
    _filestorage(p, {"camera_matrix": K[:2]})


@pytest.mark.parametrize(("name", "content", "fault"), [
    ("k23.yaml", _bad_opencv_2x3, "camera_matrix is 2×3; expected 3×3"),
    ("ros23.yaml", "camera_matrix: {rows: 2, cols: 3, data: [1, 0, 2, 0, 1, 2]}\n", "camera_matrix is 2×3"),
    ("three.txt", "525 524 319\n", "3 numbers; expected 4"),
    ("negfx.txt", "-525 524 319 239\n", "fx is -525; fx and fy must be > 0"),
    ("negfx.yaml", "camera_matrix: {rows: 3, cols: 3, data: [-5, 0, 3, 0, 5, 2, 0, 0, 1]}\n", "fx is -5"),
    ("garbage.txt", "hello world, this is not a camera\n", "not numbers"),
    ("binary.yaml", bytes(range(256)), "not a text file"),
    ("empty.txt", "", "empty file"),
    ("nok.yaml", "image_width: 640\nimage_height: 480\n", "without camera_matrix"),
    ("fisheye.yaml", "camera_matrix: {rows: 3, cols: 3, data: [5, 0, 3, 0, 5, 2, 0, 0, 1]}\n"
                     "distortion_model: equidistant\n", "distortion_model 'equidistant' is not supported"),
    ("d3.yaml", "K: [5, 0, 3, 0, 5, 2, 0, 0, 1]\nD: [0.1, 0.2, 0.3]\n", "D has 3 coefficients"),
    ("brokenxml.xml", "<?xml version=\"1.0\"?>\n<opencv_storage><camera_matrix>\n", "OpenCV cannot"),
])
def test_bad_files_one_line(tmp_path: Path, name: str, content, fault: str) -> None:
    p = tmp_path / name
    if callable(content):
        content(p)
    elif isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    with pytest.raises(DatasetError) as e:
        read_camera_file(p)
    msg = str(e.value)
    assert "\n" not in msg, msg
    assert str(p) in msg, msg
    assert fault in msg, msg
    assert "expected an OpenCV calibration YAML/XML" in msg


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="camera file not found"):
        read_camera_file(tmp_path / "nope.yaml")

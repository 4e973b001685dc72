"""Recordings are checked before a run: every frame decodes, all frames share one size, the camera file's size
is the frames'; the first bad frame is named in one line. And a sequence folder whose frames differ in size
fails in one line when the front end reads the odd one, not in an OpenCV assertion.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import CONFIG_DIR
from mutualslam_cli.datasets.recordings import video as video_mod
from mutualslam_cli.datasets.recordings.conversion import TumWriter
from mutualslam_cli.datasets.recordings.recording import RecordingOptions, open_recording
from mutualslam_cli.datasets.tum import read_intrinsics_txt
from mutualslam_cli.errors import DatasetError

W, H, N = 128, 96, 8
runner = CliRunner()


@pytest.fixture(scope="module")
def tum(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("rec"), scene="room", n=N, width=W, height=H)


def _frames(tum: Path) -> list[Path]:
    return sorted((tum / "rgb").glob("*.png"))


def _folder(tmp_path: Path, tum: Path) -> Path:
    folder = tmp_path / "shots"
    folder.mkdir()
    for k, f in enumerate(_frames(tum)):
        shutil.copy(f, folder / f"frame_{k:03d}.png")
    return folder


def _camera(tmp_path: Path, tum: Path, size: tuple[int, int] | None = None) -> Path:
    K = read_intrinsics_txt(tum / "intrinsics.txt")
    cam = tmp_path / ("camera.yaml" if size else "camera.txt")
    if size:
        fs = cv2.FileStorage(str(cam), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", size[0])
        fs.write("image_height", size[1])
        fs.write("camera_matrix", np.array([[K.fx, 0, K.cx], [0, K.fy, K.cy], [0, 0, 1]]))
        fs.release()
    else:
        cam.write_text(f"{K.fx!r} {K.fy!r} {K.cx!r} {K.cy!r}\n")
    return cam


def _one_line_error(result, *needles: str) -> str:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output, result.output
    assert "cv2.error" not in result.output, result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, result.output
    assert lines[-1] == errors[0], result.output
    for n in needles:
        assert n in errors[0], (n, result.output)
    return errors[0]


def _run(seq: Path, out: Path, *extra: str):
    return runner.invoke(app, ["run", str(seq), "--config", str(CONFIG_DIR / "smoke.yaml"), "--set", "vo.mode=svo",
                               "--out", str(out), *extra])


# ----------------------------------------------------------------------------- image folders


@pytest.mark.parametrize("bad", ["smaller", "truncated", "not_an_image"])
def test_image_folder_bad_frame_named_before_the_run(tmp_path, tum, bad):
    folder = _folder(tmp_path, tum)
    victim = folder / "frame_005.png"
    if bad == "smaller":
        cv2.imwrite(str(victim), np.zeros((H // 2, W // 2, 3), np.uint8))
        needles = (f"{victim}: the frame is {W // 2}×{H // 2}, expected {W}×{H}", "frame_000.png")
    elif bad == "truncated":
        victim.write_bytes(victim.read_bytes()[:-300])
        needles = (f"{victim}: truncated PNG", "expected a complete .png colour image")
    else:
        victim.write_bytes(b"not an image at all")
        needles = (f"{victim}: not a PNG file",)
    opts = RecordingOptions(camera=_camera(tmp_path, tum), cache=tmp_path / "cache")
    with pytest.raises(DatasetError) as e:
        open_recording(folder, opts)
    assert "\n" not in str(e.value), str(e.value)
    assert all(n in str(e.value) for n in needles), str(e.value)
    assert not list((tmp_path / "cache").glob("*/source.json"))
    assert not list((tmp_path / "cache").glob(".*"))


def test_image_folder_mixed_sizes_from_the_command_line(tmp_path, tum):
    folder = _folder(tmp_path, tum)
    victim = folder / "frame_002.png"
    cv2.imwrite(str(victim), np.zeros((H + 8, W, 3), np.uint8))
    r = _run(folder, tmp_path / "res", "--camera", str(_camera(tmp_path, tum)))
    _one_line_error(r, str(victim), f"is {W}×{H + 8}, expected {W}×{H}", "one size")
    assert not list((tmp_path / "res").rglob("summary.json"))
    assert not list((tmp_path / "res").rglob("source.json"))  # no half conversion to reuse


def test_camera_size_checked_at_the_first_frame(tmp_path, tum, monkeypatch):
    folder = _folder(tmp_path, tum)
    cam = _camera(tmp_path, tum, size=(640, 480))
    seen: list[int] = []
    with pytest.raises(DatasetError) as e:
        open_recording(folder, RecordingOptions(camera=cam, cache=tmp_path / "cache"), progress=seen.append)
    msg = str(e.value)
    assert msg.startswith(f"{cam}: the camera is for 640×480 but the frames are {W}×{H} (first frame: ")
    assert seen == []  # stopped at the first frame, not after converting them all


# ----------------------------------------------------------------------------- bags and videos (the writer)


def test_writer_checks_every_encoded_frame(tmp_path, tum):
    frames = [f.read_bytes() for f in _frames(tum)]
    w = TumWriter(tmp_path / "conv", source="walk.bag")
    w.add_rgb(0.0, frames[0], ".png")
    w.add_rgb(0.1, frames[1], ".png")
    with pytest.raises(DatasetError, match=r"walk.bag: frame 2 at 0.200000 s: truncated PNG"):
        w.add_rgb(0.2, frames[2][:-200], ".png")
    small = cv2.imencode(".jpg", np.zeros((H // 2, W // 2, 3), np.uint8))[1].tobytes()
    first = r"\(walk.bag: frame 0 at 0.000000 s\)"
    with pytest.raises(DatasetError, match=rf"walk.bag: frame 2 at 0.300000 s: the frame is {W // 2}×{H // 2}, "
                                           rf"expected {W}×{H} like the first frame {first}"):
        w.add_rgb(0.3, small, ".jpg")
    with pytest.raises(DatasetError, match=r"frame 2 at 0.400000 s: the frame is 64×48"):
        w.add_rgb(0.4, np.zeros((48, 64, 3), np.uint8))
    w.abort()


class _GrowingCap:
    """A video whose frames change size at frame 3 (a stream switching resolution)."""

    def __init__(self):
        self.i = -1

    def read(self):
        self.i += 1
        size = (H, W) if self.i < 3 else (H * 2, W * 2)
        return self.i < 5, np.full((*size, 3), self.i, np.uint8)

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_POS_MSEC: 40.0 * max(self.i, 0), cv2.CAP_PROP_FPS: 25.0,
                cv2.CAP_PROP_FRAME_COUNT: 5}.get(prop, 0.0)


def test_video_changing_size_named(tmp_path):
    w = TumWriter(tmp_path / "conv", source="clip.mp4")
    with pytest.raises(DatasetError, match=rf"clip.mp4: frame 3 at 0.120000 s: the frame is {2 * W}×{2 * H}, "
                                           rf"expected {W}×{H}"):
        video_mod._decode(Path("clip.mp4"), _GrowingCap(), RecordingOptions(), w)  # type: ignore[arg-type]
    w.abort()


# ----------------------------------------------------------------------------- sequence folders given to run


@pytest.mark.parametrize("bad", ["smaller", "truncated"])
def test_sequence_folder_with_an_odd_frame_fails_in_one_line(tmp_path, tum, bad):
    root = tmp_path / "seq"
    shutil.copytree(tum, root)
    victim = _frames(root)[3]
    if bad == "smaller":  # today's front end: a 140-line trace ending in OpenCV's lkpyramid.cpp assertion
        cv2.imwrite(str(victim), np.zeros((H // 2, W // 2, 3), np.uint8))
        needles = (f"is {W // 2}×{H // 2}, expected {W}×{H}", "datasets check")
    else:  # libpng's "Read Error" on stderr, or a partly decoded frame
        victim.write_bytes(victim.read_bytes()[:-300])
        needles = ("truncated PNG", "datasets check")
    r = _run(root, tmp_path / "res")
    _one_line_error(r, str(victim), *needles)
    assert not list((tmp_path / "res").rglob("summary.json"))

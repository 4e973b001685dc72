"""Videos and plain image folders as recordings: conversion, times, frames, caching, errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.datasets.recordings import video as video_mod
from mutualslam_cli.datasets.recordings.recording import RecordingOptions, open_recording
from mutualslam_cli.datasets.recordings.video import natural_key
from mutualslam_cli.datasets.registry import load_spec
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.datasets.tum import read_intrinsics_txt
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics

W, H, N, FPS = 128, 96, 12, 30.0
# Mean absolute difference (grey levels, per channel) between a decoded frame and its original.
# Measured on these 128×96 renderings: mp4v 5.99–6.43, MJPG 5.66–5.82 (OpenCV 5.0, FFmpeg 62). The
# floor is 4:2:0 chroma subsampling alone (an I420 round trip without quantisation: 4.83 — the
# textures are fine, neighbouring pixels differ by 7.3 on average); quantisation adds 1–1.6.
# Consecutive originals differ by 8.5–12, hence the second check: each frame is nearest its own.
MAX_MEAN_DIFF = 8.0


@pytest.fixture(scope="module")
def tum(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("video"), scene="room", n=N, width=W, height=H)


@pytest.fixture(scope="module")
def originals(tum: Path) -> list[np.ndarray]:
    names = [ln.split()[1] for ln in (tum / "rgb.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    return [cv2.cvtColor(cv2.imread(str(tum / n)), cv2.COLOR_BGR2RGB) for n in names]


def _camera(tmp: Path, tum: Path, name: str = "camera.txt") -> tuple[Path, Intrinsics]:
    K = read_intrinsics_txt(tum / "intrinsics.txt")
    p = tmp / name
    p.write_text(f"# fx fy cx cy\n{K.fx!r} {K.fy!r} {K.cx!r} {K.cy!r}\n")
    return p, K


def _write_video(path: Path, fourcc: str, frames: list[np.ndarray]) -> Path:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (W, H))
    if not w.isOpened():
        pytest.skip(f"cv2.VideoWriter cannot write {fourcc} {path.suffix} here")
    for f in frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    return path


def _open(path: Path, tmp: Path, **kw) -> Sequence:
    """The converted recording, loaded; ``seq.meta["recording"]`` is the conversion's source.json."""
    spec = open_recording(path, RecordingOptions(cache=tmp / "cache", **kw))
    seq = load_spec(spec)
    seq.meta["recording"] = spec.extra["recording"]
    return seq


@pytest.mark.parametrize(("fourcc", "suffix", "codec"), [("mp4v", ".mp4", "FMP4"), ("MJPG", ".avi", "MJPG")])
def test_video_round_trip_and_cache(tmp_path: Path, tum: Path, originals: list[np.ndarray], monkeypatch,
                                    fourcc: str, suffix: str, codec: str) -> None:
    vid = _write_video(tmp_path / f"walk{suffix}", fourcc, originals)
    cam, K = _camera(tmp_path, tum)
    seq = _open(vid, tmp_path, camera=cam)
    assert len(seq) == N
    np.testing.assert_allclose([f.timestamp for f in seq.frames], np.arange(N) / FPS, atol=1e-3)
    assert seq.intrinsics == Intrinsics(K.fx, K.fy, K.cx, K.cy, W, H, None)
    assert not seq.has_depth
    assert not seq.has_gt_poses
    assert seq.gt is None
    diffs = np.array([[np.abs(seq.load_rgb(i).astype(float) - o).mean() for o in originals] for i in range(N)])
    assert diffs.diagonal().max() < MAX_MEAN_DIFF, diffs.diagonal()
    assert (diffs.argmin(axis=1) == np.arange(N)).all()  # right order, RGB not BGR
    meta = seq.meta["recording"]
    assert meta["video_frames"] == N
    assert meta["codec"] == codec
    assert meta["fps"] == FPS
    assert meta["times"].startswith("container")
    assert meta["fps_used"] is None
    assert meta["notes"] == []

    # cached: a second open neither decodes nor rewrites
    source = open_recording(vid, RecordingOptions(camera=cam, cache=tmp_path / "cache")).root / "source.json"
    stamp = source.stat().st_mtime_ns

    def no_decode(*a, **k):
        raise AssertionError("decoded again")

    monkeypatch.setattr(video_mod, "convert_video", no_decode)
    assert len(_open(vid, tmp_path, camera=cam)) == N
    assert source.stat().st_mtime_ns == stamp
    monkeypatch.undo()

    # an edited camera file converts anew
    cam.write_text(f"{K.fx * 2!r} {K.fy * 2!r} {K.cx!r} {K.cy!r}\n")
    seq2 = _open(vid, tmp_path, camera=cam)
    assert seq2.root != seq.root
    assert seq2.intrinsics.fx == K.fx * 2
    assert len(seq2) == N


def test_video_fps_option_overrides_container(tmp_path: Path, tum: Path, originals: list[np.ndarray]) -> None:
    vid = _write_video(tmp_path / "slow.avi", "MJPG", originals[:4])
    cam, _ = _camera(tmp_path, tum)
    seq = _open(vid, tmp_path, camera=cam, fps=10.0)
    np.testing.assert_allclose([f.timestamp for f in seq.frames], [0, 0.1, 0.2, 0.3], atol=1e-6)
    assert seq.meta["recording"]["fps_used"] == 10.0


def test_video_without_camera_file(tmp_path: Path, originals: list[np.ndarray]) -> None:
    vid = _write_video(tmp_path / "nocam.avi", "MJPG", originals[:2])
    with pytest.raises(DatasetError, match="no intrinsics") as e:
        _open(vid, tmp_path)
    assert "\n" not in str(e.value)
    assert str(vid) in str(e.value)


@pytest.mark.parametrize("make", ["random", "empty_writer"])
def test_unreadable_video(tmp_path: Path, tum: Path, make: str) -> None:
    vid = tmp_path / "broken.mp4"
    if make == "random":
        vid.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    else:  # a writer closed before any frame: no stream, or no frame
        cv2.VideoWriter(str(vid), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (W, H)).release()
        if not vid.exists():
            vid.write_bytes(b"")
    cam, _ = _camera(tmp_path, tum)
    with pytest.raises(DatasetError) as e:
        _open(vid, tmp_path, camera=cam)
    msg = str(e.value)
    assert "\n" not in msg, msg
    assert str(vid) in msg, msg
    assert ("cannot open" in msg or "no frame" in msg), msg
    assert not list((tmp_path / "cache").glob("*/source.json"))  # nothing half-converted is left to read


class _FakeCap:
    """A capture whose container gives the listed times (ms) — to exercise the fallbacks."""

    def __init__(self, times_ms: list[float], fps: float = 25.0):
        self.times, self.fps, self.i = times_ms, fps, -1

    def read(self):
        self.i += 1
        return (self.i < len(self.times)), np.full((2, 3, 3), self.i, np.uint8)

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_POS_MSEC: self.times[max(self.i, 0)] if self.i < len(self.times) else 0.0,
                cv2.CAP_PROP_FPS: self.fps, cv2.CAP_PROP_FRAME_COUNT: len(self.times)}.get(prop, 0.0)


class _FakeWriter:
    def __init__(self):
        self.rgb: list[tuple[float, np.ndarray]] = []

    def add_rgb(self, t: float, image: np.ndarray, ext: str = ".png") -> None:
        self.rgb.append((t, image))


@pytest.mark.parametrize(("times_ms", "want", "how"), [
    ([0, 0, 0, 0], [0, 0.04, 0.08, 0.12], "frame index / 25 fps"),           # no container times
    ([0, 40, 40, 120], [0, 0.04, 0.08, 0.12], "container"),                   # one repaired
    ([0, 50, 90, 200], [0, 0.05, 0.09, 0.2], "container"),                    # variable rate kept
    ([500], [0.5], "container presentation time (one frame)"),
])
def test_container_time_fallbacks(times_ms: list[float], want: list[float], how: str) -> None:
    w = _FakeWriter()
    meta = video_mod._decode(Path("fake.mp4"), _FakeCap(times_ms), RecordingOptions(), w)  # type: ignore[arg-type]
    np.testing.assert_allclose([t for t, _ in w.rgb], want, atol=1e-9)
    assert [int(img[0, 0, 0]) for _, img in w.rgb] == list(range(len(times_ms)))  # in order, none dropped
    assert meta["times"].startswith(how)
    assert meta["video_frames"] == len(times_ms)
    assert meta["times_repaired"] == (1 if times_ms == [0, 40, 40, 120] else 0)


def test_image_folder_with_tum_stamps(tmp_path: Path, tum: Path, originals: list[np.ndarray]) -> None:
    cam, _ = _camera(tmp_path, tum)
    seq = _open(tum / "rgb", tmp_path, camera=cam)
    stamps = sorted(float(p.stem) for p in (tum / "rgb").glob("*.png"))
    assert len(seq) == N
    assert [f.timestamp for f in seq.frames] == pytest.approx(stamps, abs=1e-6)
    assert seq.meta["recording"]["times"] == "file names (seconds)"
    assert (seq.intrinsics.width, seq.intrinsics.height) == (W, H)
    assert not seq.has_depth
    assert all(Path(f.rgb_path).parent == (tum / "rgb").resolve() for f in seq.frames)  # images stay
    assert all((seq.load_rgb(i) == originals[i]).all() for i in (0, N - 1))


@pytest.mark.parametrize("fps", [None, 10.0])
def test_image_folder_natural_order(tmp_path: Path, tum: Path, originals: list[np.ndarray], fps) -> None:
    folder = tmp_path / "shots"
    folder.mkdir()
    for i, img in enumerate(originals):  # frame_1 … frame_12: frame_2 before frame_10
        cv2.imwrite(str(folder / f"frame_{i + 1}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    (folder / "notes.txt").write_text("not an image")
    cam, _ = _camera(tmp_path, tum)
    seq = _open(folder, tmp_path, camera=cam, fps=fps)
    rate = fps or 30.0
    assert [Path(f.rgb_path).name for f in seq.frames] == [f"frame_{i + 1}.png" for i in range(N)]
    np.testing.assert_allclose([f.timestamp for f in seq.frames], np.arange(N) / rate, atol=1e-6)
    assert seq.meta["recording"]["fps_used"] == rate
    assert all((seq.load_rgb(i) == originals[i]).all() for i in range(N))


def test_image_folder_frame_numbers_and_duplicates(tmp_path: Path, tum: Path) -> None:
    cam, _ = _camera(tmp_path, tum)
    folder = tmp_path / "numbered"
    folder.mkdir()
    src = sorted((tum / "rgb").glob("*.png"))
    for k in (0, 1, 2, 4):  # 0000.png … 0004.png, frame 3 dropped: times keep the gap
        shutil.copy(src[k], folder / f"{k:04d}.png")
    seq = _open(folder, tmp_path, camera=cam, fps=10.0)
    np.testing.assert_allclose([f.timestamp for f in seq.frames], [0, 0.1, 0.2, 0.4], atol=1e-6)
    shutil.copy(src[3], folder / "4.png")  # the same frame number twice
    with pytest.raises(DatasetError, match="same time as"):
        _open(folder, tmp_path, camera=cam)


def test_natural_key() -> None:
    names = ["frame_10.png", "frame_2.png", "Frame_1.png", "frame_1b.png", "a9.png"]
    assert sorted(names, key=natural_key) == ["a9.png", "Frame_1.png", "frame_1b.png", "frame_2.png", "frame_10.png"]

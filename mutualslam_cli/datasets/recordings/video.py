"""Videos and plain image folders → frames of a TUM-layout conversion (:mod:`.recording`).

A video is decoded with OpenCV's FFmpeg backend, one frame at a time (memory stays flat), and every
frame is written as a PNG. Frame times come from the container: ``CAP_PROP_POS_MSEC`` read right
after each ``read()`` is the presentation time of the frame just decoded (0 for the first frame of
the files ``cv2.VideoWriter`` writes, then ``i / fps``), so variable-rate phone videos keep their
real timing. A container without usable times (the first two frames not increasing, as raw
streams give) falls back to ``index / fps``; a later time that does not increase is replaced by
the previous one plus ``1 / fps`` and counted in the metadata. ``RecordingOptions.fps``, when
given, overrides both: times become ``index / fps``.

An image folder keeps its images where they are. Times come from the file names when every stem
is a number: with a decimal point, seconds (TUM ``1305031102.175304.png``); an integer of 16 or
more digits, nanoseconds (EuRoC, ROS); a shorter integer, a frame number (``0042.png``: ``42 / fps``).
Otherwise the images are sorted in natural order (``frame_2`` before ``frame_10``) and timed
``index / fps``, with ``fps`` = ``RecordingOptions.fps`` or 30.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import JSON, JSONObject

if TYPE_CHECKING:
    from mutualslam_cli.datasets.recordings.conversion import RecordingOptions, TumWriter

#: Frame rate of an image folder whose names are not times, when ``RecordingOptions.fps`` is not given.
DEFAULT_FPS = 30.0
_DECIMAL_STEM = re.compile(r"[+-]?(\d+\.\d*|\.\d+)([eE][+-]?\d+)?")
_INTEGER_STEM = re.compile(r"\d+")
_NS_DIGITS = 16  # an integer stem this long is nanoseconds (1e15 ns ≈ 11.6 days)


def _fourcc(cap: cv2.VideoCapture) -> str:
    code = int(cap.get(cv2.CAP_PROP_FOURCC))
    text = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return text if text.isprintable() and text.strip() else f"0x{code:08x}"


def _rate(value: float) -> float | None:
    """A usable frame rate (frames/s) or ``None`` (0, NaN, or the 1000 some containers report)."""
    return float(value) if math.isfinite(value) and 0 < value < 1000 else None


def convert_video(path: Path, opts: RecordingOptions, writer: TumWriter) -> JSONObject:
    """Decode a video frame by frame into ``writer`` (``(H, W, 3)`` uint8 RGB frames, times in s).

    Args:
        path: the video file (whatever OpenCV's FFmpeg backend decodes).
        opts: ``opts.fps`` (frames/s), when given, times frames ``index / fps`` instead of the container.
        writer: receives each frame with :meth:`~mutualslam_cli.datasets.recordings.conversion.TumWriter.add_rgb`.

    Returns:
        Metadata for ``source.json``: ``video_frames``, ``fps`` (the container's), ``fps_used``
        (when times are ``index / fps``), ``times`` (how they were obtained), ``codec`` (FourCC),
        ``duration_s``, ``notes``.

    Raises:
        DatasetError: OpenCV cannot open the file, or it decodes to no frame — one line naming it.
    """
    path = Path(path)
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            raise DatasetError(f"{path}: OpenCV (FFmpeg) cannot open this video; expected a readable video file "
                               "(mp4, avi, mkv, mov …) — is it complete and a supported codec?")
        return _decode(path, cap, opts, writer)
    finally:
        cap.release()


class _Frames:
    """Writes frames to the writer and keeps their count, first and last time (s)."""

    def __init__(self, writer: TumWriter):
        self.writer, self.n, self.first, self.last = writer, 0, 0.0, -math.inf
        self.size = (0, 0)  # (width, height) of the first decoded frame, pixels

    def add(self, rgb: np.ndarray, t: float) -> None:
        self.writer.add_rgb(float(t), rgb)
        if self.n == 0:
            self.first, self.size = float(t), (int(rgb.shape[1]), int(rgb.shape[0]))
        self.last, self.n = float(t), self.n + 1


def _decode(path: Path, cap: cv2.VideoCapture, opts: RecordingOptions, writer: TumWriter) -> JSONObject:
    container_fps = _rate(cap.get(cv2.CAP_PROP_FPS))
    reported = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    fps = float(opts.fps) if opts.fps else (container_fps or DEFAULT_FPS)
    notes: list[JSON] = []  # lines, appended to until the end
    meta: JSONObject = {"codec": _fourcc(cap), "fps": container_fps, "notes": notes}
    rotation = cap.get(cv2.CAP_PROP_ORIENTATION_META)
    if math.isfinite(rotation) and rotation % 360:
        notes.append(f"the container asks for a {rotation:g}° rotation, which OpenCV applied: "
                     "the camera file must describe the rotated frames")
    mode = "index" if opts.fps else "undecided"  # undecided: the first two frames decide
    if opts.fps:
        meta["times"] = f"frame index / {fps:g} fps (--fps given; container times ignored)"
    out = _Frames(writer)
    held: tuple[np.ndarray, float] | None = None  # the first frame, while undecided
    repaired = 0
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        pos = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0  # the time of the frame just decoded
        rgb = cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB if bgr.ndim == 2 else cv2.COLOR_BGR2RGB)
        if mode == "undecided":
            if held is None:
                held = (rgb, pos)
                continue
            (first, first_pos), held = held, None
            good = math.isfinite(first_pos) and math.isfinite(pos) and 0 <= first_pos < pos
            mode = "container" if good else "index"
            if good:
                meta["times"] = "container presentation times (CAP_PROP_POS_MSEC)"
            else:
                meta["times"] = f"frame index / {fps:g} fps (the container gives no increasing times)"
                notes.append(f"container times unusable (first two frames at {first_pos:g} s and {pos:g} s); "
                             f"frames timed index / {fps:g} fps" + ("" if container_fps else " (default rate)"))
            out.add(first, first_pos if good else 0.0)
        t = out.n / fps if mode == "index" else pos
        if mode == "container" and not (math.isfinite(t) and t > out.last):
            t, repaired = out.last + 1.0 / fps, repaired + 1
        out.add(rgb, t)
    if held is not None:  # a one-frame video
        rgb, pos = held
        usable = math.isfinite(pos) and pos >= 0
        meta["times"] = "container presentation time (one frame)" if usable else "0 s (one frame)"
        out.add(rgb, pos if usable else 0.0)
    if out.n == 0:
        raise DatasetError(f"{path}: the video decodes to no frame; expected at least one frame "
                           f"(codec {meta['codec']}, {reported:g} frames reported by the container)")
    meta["fps_used"] = fps if mode == "index" else None
    if repaired:
        notes.append(f"{repaired} container times did not increase; each set to the previous + 1/{fps:g} s")
    if reported > 0 and abs(reported - out.n) > max(1.0, 0.01 * out.n):
        notes.append(f"the container reports {reported:g} frames but {out.n} decoded (truncated, or an estimate)")
    meta.update(video_frames=out.n, width=out.size[0], height=out.size[1],
                duration_s=round(out.last - out.first, 6), times_repaired=repaired)
    return meta


# --- image folders ------------------------------------------------------------------------------------------------

def natural_key(name: str) -> tuple[list[int | str], str]:
    """Sort key that orders digit runs by value, ignoring case: ``frame_2`` before ``frame_10``."""
    parts = re.split(r"(\d+)", name)  # text, digits, text, …: every odd part is a digit run
    return [int(p) if i % 2 else p.lower() for i, p in enumerate(parts)], name


def _stem_times(files: list[Path]) -> tuple[list[float], str] | None:
    """Times (s) from the file stems when all are numbers, with how they were read; else ``None``."""
    stems = [f.stem for f in files]
    if all(_DECIMAL_STEM.fullmatch(s) for s in stems):
        return [float(s) for s in stems], "file names (seconds)"
    if all(_INTEGER_STEM.fullmatch(s) for s in stems):
        if all(len(s.lstrip("0")) >= _NS_DIGITS for s in stems):
            return [int(s) * 1e-9 for s in stems], "file names (nanoseconds)"
        return [float(int(s)) for s in stems], "frame numbers in the file names"
    return None


def convert_image_folder(path: Path, opts: RecordingOptions, writer: TumWriter) -> JSONObject:
    """List a folder of images (``conversion.IMAGE_SUFFIXES``) as the colour frames of ``writer``.

    The images stay where they are (listed by absolute path); each is decoded once here, so that a
    truncated or undecodable image, or one whose size differs from the first's, stops the conversion
    in one line naming it (``writer.size``: ``(width, height)`` pixels of the first).

    Args:
        path: the folder (no ``rgb.txt``; subfolders such as ``depth/`` are not read).
        opts: ``opts.fps`` (frames/s; default 30) times frames whose names are not times.
        writer: receives each image with :meth:`~mutualslam_cli.datasets.recordings.conversion.TumWriter.add_rgb_path`.

    Returns:
        Metadata for ``source.json``: ``images``, ``times`` (from the names or ``index / fps``),
        ``fps_used``, ``first``/``last`` file names, ``notes``.

    Raises:
        DatasetError: no image, two images with the same time, or the first image that is truncated, does not
            decode, or differs in size from the first.
    """
    from mutualslam_cli.datasets.recordings.conversion import IMAGE_SUFFIXES

    path = Path(path)
    files = [q for q in path.iterdir() if q.is_file() and not q.name.startswith(".")
             and q.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise DatasetError(f"{path}: no image found; expected files ending in {', '.join(IMAGE_SUFFIXES)}")
    fps = float(opts.fps) if opts.fps else DEFAULT_FPS
    stamped = _stem_times(files)
    notes: list[JSON] = []
    meta: JSONObject = {"images": len(files), "notes": notes}
    if stamped is not None and stamped[1] == "frame numbers in the file names":
        order = sorted(range(len(files)), key=lambda i: stamped[0][i])
        times = [stamped[0][i] / fps for i in order]
        meta.update(times=f"frame numbers in the file names / {fps:g} fps", fps_used=fps)
    elif stamped is not None:
        order = sorted(range(len(files)), key=lambda i: stamped[0][i])
        times = [stamped[0][i] for i in order]
        meta.update(times=stamped[1], fps_used=None)
        if opts.fps:
            notes.append(f"--fps {fps:g} ignored: the file names are times")
    else:
        order = sorted(range(len(files)), key=lambda i: natural_key(files[i].name))
        times = [i / fps for i in range(len(files))]
        meta.update(times=f"image index in natural name order / {fps:g} fps", fps_used=fps)
    files = [files[i] for i in order]
    for a in range(1, len(files)):
        if times[a] <= times[a - 1]:
            raise DatasetError(f"{files[a]}: same time as {files[a - 1].name} ({times[a]:.6f} s); "
                               "expected file names with distinct times")
    for t, f in zip(times, files):
        writer.add_rgb_path(t, f)  # decodes and checks every image: structure, decoding, one size
    assert writer.size is not None
    meta.update(first=files[0].name, last=files[-1].name, width=writer.size[0], height=writer.size[1],
                duration_s=round(times[-1] - times[0], 6))
    return meta

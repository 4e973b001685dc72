"""What a recording is converted into (:mod:`~mutualslam_cli.datasets.recordings.recording`): the options that say how
to read it (:class:`RecordingOptions`) and the TUM-layout folder its frames are written to (:class:`TumWriter`).
The converters (:mod:`.rosbag`, :mod:`.video`) write through these; :mod:`.recording` dispatches to them.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.image_files import decode_frame
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics, JSONObject, Trajectory

#: File suffixes read as videos (whatever OpenCV's FFmpeg backend decodes).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")
#: File suffixes read as bags: ROS 1 ``.bag``; ROS 2 storage files (their folder holds ``metadata.yaml``).
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
#: Image suffixes of a plain image folder.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")
#: Version of the converted layout; a change converts every recording anew.
CONVERSION_VERSION = 1


@dataclass(frozen=True)
class RecordingOptions:
    """How to read a recording; every field is optional.

    Attributes:
        rgb_topic: bag topic of the colour images (``sensor_msgs/Image`` or ``CompressedImage``);
            ``None``: the only image topic that is not depth.
        depth_topic: bag topic of depth images (``16UC1`` millimetres or ``32FC1`` metres); ``None``: no depth.
        camera_info_topic: bag topic of ``sensor_msgs/CameraInfo``; ``None``: the one beside the RGB topic.
        pose_topic: bag topic of GT poses (``PoseStamped``, ``TransformStamped``, ``Odometry``),
            camera-to-world.
        gt: a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, camera-to-world) of GT poses.
        camera: a camera file; it wins over a bag's ``CameraInfo``.
        fps: frames per second: an image folder whose file names are not timestamps (default 30), or a
            video whose container times are to be replaced by ``index / fps``.
        cache: folder of converted recordings (default ``<recording's folder>/.mslam/``).
    """

    rgb_topic: str | None = None
    depth_topic: str | None = None
    camera_info_topic: str | None = None
    pose_topic: str | None = None
    gt: Path | None = None
    camera: Path | None = None
    fps: float | None = None
    cache: Path | None = None

    def key_fields(self) -> JSONObject:
        """The fields that change a conversion's result (not where it is cached): strings, numbers or ``None``."""
        d = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items() if k != "cache"}
        for k in ("gt", "camera"):  # an edited GT or camera file converts anew
            if getattr(self, k) is not None:
                d[k] = file_stamp(Path(getattr(self, k)))
        return d


def file_stamp(path: Path) -> str:
    """``path:size:mtime_ns`` of an existing file (a conversion's cache key part)."""
    if not path.exists():
        raise DatasetError(f"{path}: not found")
    st = path.stat()
    return f"{path.resolve()}:{st.st_size}:{st.st_mtime_ns}"



class TumWriter:
    """Builds a TUM-layout folder in a temporary sibling; :meth:`finish` renames it into place.

    RGB frames go to ``rgb/<t>.<ext>`` (encoded bytes written as they are: no re-encoding) or stay
    where they are (:meth:`add_rgb_path`); depth to ``depth/<t>.png`` as 16-bit raw units.

    Every colour frame is checked as it arrives, so a bad one stops the conversion before any run, in
    one line naming it: its file structure (a truncated PNG or JPEG), that it decodes, and that its
    size (``(width, height)`` pixels) is the first frame's — and ``expect_size``'s, the camera file's,
    when it gives one.
    """

    def __init__(self, folder: Path, progress: Callable[[int], None] | None = None, source: str | None = None,
                 expect_size: tuple[int, int] | None = None, camera: str | None = None):
        self.folder = Path(folder)
        self.progress = progress  # called with the number of colour frames so far
        self.source = source or str(self.folder)  # the recording, for messages
        self.expect_size, self.camera = expect_size, camera  # the camera file's size and name, if it gives one
        self.tmp = self.folder.with_name(f".{self.folder.name}.converting-{os.getpid()}")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        (self.tmp / "rgb").mkdir(parents=True)
        (self.tmp / "depth").mkdir()
        self.rgb: list[tuple[float, str]] = []
        self.depth: list[tuple[float, str]] = []
        self.gt: Trajectory | None = None
        self.size: tuple[int, int] | None = None  # (width, height) of the first RGB frame
        self._first = ""  # how the first frame is named in messages

    def _name(self, t: float, ext: str, taken: list[tuple[float, str]], sub: str) -> str:
        name = f"{sub}/{t:.6f}{ext}"
        if (self.tmp / name).exists():  # frames within a microsecond: keep them all
            name = f"{sub}/{t:.6f}_{len(taken)}{ext}"
        return name

    def _check_size(self, img: np.ndarray, what: str) -> None:
        """``img`` must have the first frame's size (and the camera file's); ``what`` names the frame."""
        size = (int(img.shape[1]), int(img.shape[0]))
        if self.size is None:
            self.size, self._first = size, what
            if self.expect_size and self.expect_size != size:
                raise DatasetError(f"{self.camera}: the camera is for {self.expect_size[0]}×{self.expect_size[1]} "
                                   f"but the frames are {size[0]}×{size[1]} (first frame: {what})")
        elif size != self.size:
            raise DatasetError(f"{what}: the frame is {size[0]}×{size[1]}, expected {self.size[0]}×{self.size[1]} "
                               f"like the first frame ({self._first}); every frame of a recording must have one size")

    def add_rgb(self, t: float, image: bytes | np.ndarray, ext: str = ".png") -> None:
        """One colour frame at time ``t`` (s): encoded file bytes (``ext`` names the format), or a
        ``(H, W, 3)`` uint8 RGB / ``(H, W)`` uint8 grey array, written as PNG.

        Raises:
            DatasetError: the frame does not decode, or its size differs from the first frame's.
        """
        what = f"{self.source}: frame {len(self.rgb)} at {t:.6f} s"
        if isinstance(image, np.ndarray):
            self._check_size(image, what)
            arr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
            ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise DatasetError(f"{what}: cannot encode the frame as PNG")
            image, ext = buf.tobytes(), ".png"
        else:
            img, problem = decode_frame(image, ext)
            if img is None:
                raise DatasetError(f"{what}: {problem}; expected a complete {ext} colour image")
            self._check_size(img, what)
        name = self._name(t, ext, self.rgb, "rgb")
        (self.tmp / name).write_bytes(image)
        self.rgb.append((t, name))
        if self.progress is not None:
            self.progress(len(self.rgb))

    def add_rgb_path(self, t: float, path: Path) -> None:
        """One colour frame that stays where it is (an image folder): checked (decoded), listed by its absolute path.

        Raises:
            DatasetError: the file cannot be read or decoded, or its size differs from the first frame's.
        """
        path = Path(path)
        try:
            data = path.read_bytes()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read the image ({e.strerror})") from None
        img, problem = decode_frame(data, path.suffix.lower())
        if img is None:
            raise DatasetError(f"{path}: {problem}; expected a complete {path.suffix} colour image (frame "
                               f"{len(self.rgb)} of {self.source})")
        self._check_size(img, str(path))
        self.rgb.append((t, str(path.resolve())))
        if self.progress is not None:
            self.progress(len(self.rgb))

    def add_depth(self, t: float, depth: np.ndarray) -> None:
        """One ``(H, W)`` uint16 depth image at time ``t`` (s), in the raw units of ``depth_scale``."""
        if depth.dtype != np.uint16 or depth.ndim != 2:
            raise DatasetError(f"{self.folder}: depth at {t:.6f} s is {depth.dtype} {depth.shape}; expected 2-D uint16")
        name = self._name(t, ".png", self.depth, "depth")
        if not cv2.imwrite(str(self.tmp / name), depth, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise DatasetError(f"{self.tmp / name}: cannot write the depth image")
        self.depth.append((t, name))

    def set_gt(self, traj: Trajectory) -> None:
        """GT poses (camera-to-world), written as ``groundtruth.txt``."""
        self.gt = traj

    def finish(self, intrinsics: Intrinsics, depth_scale: float, meta: JSONObject) -> Path:
        """Write the lists, ``intrinsics.txt`` and ``source.json`` (``meta``: how the recording was read, with
        ``source``, ``kind`` and ``options``; the counts and the scale are added), then rename into place."""
        if not self.rgb:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise DatasetError(f"{meta.get('source', self.folder)}: no colour frame found "
                               f"({meta.get('what', 'expected at least one image')})")
        head = "# timestamp filename (written by mslam from {})\n".format(meta.get("source", "a recording"))
        atomic_write_text(self.tmp / "rgb.txt", head + "".join(f"{t:.6f} {n}\n" for t, n in self.rgb))
        if self.depth:
            atomic_write_text(self.tmp / "depth.txt", head + "".join(f"{t:.6f} {n}\n" for t, n in self.depth))
        if self.gt is not None:
            write_tum_trajectory(self.tmp / "groundtruth.txt", self.gt)
        w, h = self.size if self.size is not None else (intrinsics.width, intrinsics.height)
        line = f"{intrinsics.fx!r} {intrinsics.fy!r} {intrinsics.cx!r} {intrinsics.cy!r} {w} {h}"
        if intrinsics.dist:
            line += " " + " ".join(repr(float(d)) for d in intrinsics.dist)
        atomic_write_text(self.tmp / "intrinsics.txt",
                          "# fx fy cx cy width height [k1 k2 p1 p2 k3] (pixels; OpenCV distortion)\n" + line + "\n")
        meta = {**meta, "depth_scale": depth_scale, "frames": len(self.rgb), "depth_frames": len(self.depth),
                "gt_poses": 0 if self.gt is None else len(self.gt), "conversion_version": CONVERSION_VERSION}
        atomic_write_text(self.tmp / "source.json", json.dumps(meta, indent=1, default=str) + "\n")
        if self.folder.exists():
            shutil.rmtree(self.folder)
        os.replace(self.tmp, self.folder)
        return self.folder

    def abort(self) -> None:
        """Remove the temporary folder (after an error)."""
        shutil.rmtree(self.tmp, ignore_errors=True)

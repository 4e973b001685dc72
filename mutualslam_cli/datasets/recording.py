"""Recordings that are not sequence folders: ROS bags, videos, plain image folders (DESIGN §3).

A recording is converted once into a TUM-layout folder (``rgb.txt``, ``depth.txt``,
``groundtruth.txt``, ``intrinsics.txt``) under a conversion cache, and from then on runs like any
``lab`` folder: frames stream from disk, and every stage reads them alike. The folder is built
in a temporary sibling and renamed into place, so a killed conversion leaves nothing a run
would read; the cache key holds the recording's size, mtime and the options that change the
result, so an edited recording or other topics convert anew.

- ROS 1 ``.bag`` and ROS 2 bag folders / ``.db3`` / ``.mcap``: :mod:`~mutualslam_cli.datasets.rosbag`.
- Videos (``.mp4``, ``.avi``, ``.mkv``, ``.mov`` …) and image folders with a camera file:
  :mod:`~mutualslam_cli.datasets.video`.
- Camera files (OpenCV calibration YAML, ROS ``camera_calibration`` YAML, plain
  ``fx fy cx cy [k1 k2 p1 p2 k3]``): :mod:`~mutualslam_cli.datasets.camera_file`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.associate import read_tum_trajectory, write_tum_trajectory
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics, SequenceSpec, Trajectory

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

    def key_fields(self) -> dict[str, Any]:
        """The fields that change a conversion's result (not where it is cached)."""
        d = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items() if k != "cache"}
        for k in ("gt", "camera"):  # an edited GT or camera file converts anew
            if getattr(self, k) is not None:
                d[k] = _file_stamp(Path(getattr(self, k)))
        return d


def _file_stamp(path: Path) -> str:
    if not path.exists():
        raise DatasetError(f"{path}: not found")
    st = path.stat()
    return f"{path.resolve()}:{st.st_size}:{st.st_mtime_ns}"


def recording_kind(path: str | os.PathLike, opts: RecordingOptions | None = None) -> str | None:
    """``"bag"``, ``"video"``, ``"images"`` or ``None`` (a sequence folder or a registry name).

    An image folder counts only with a camera file (``opts.camera``) and no ``rgb.txt``/``associations.txt``.
    """
    p = Path(path)
    if p.is_file():
        suf = p.suffix.lower()
        if suf in BAG_SUFFIXES:
            return "bag"
        if suf in VIDEO_SUFFIXES:
            return "video"
        raise DatasetError(f"{p}: unknown recording type '{suf}'; expected a ROS bag ({', '.join(BAG_SUFFIXES)}), "
                           f"a video ({', '.join(VIDEO_SUFFIXES)}) or a sequence folder")
    if p.is_dir():
        if (p / "metadata.yaml").is_file() and any(q.suffix in (".db3", ".mcap") for q in p.iterdir()):
            return "bag"
        if not (p / "rgb.txt").is_file() and not (p / "associations.txt").is_file():
            if any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()) and opts is not None and opts.camera:
                return "images"
    return None


def _stamp_of_recording(path: Path) -> str:
    if path.is_dir():  # a ROS 2 bag folder or an image folder: every file's size and mtime
        parts = sorted(f"{q.name}:{q.stat().st_size}:{q.stat().st_mtime_ns}" for q in path.iterdir() if q.is_file())
        return f"{path.resolve()}|" + "|".join(parts)
    return _file_stamp(path)


def conversion_folder(path: Path, opts: RecordingOptions) -> Path:
    """Where the conversion of ``path`` with ``opts`` lives: ``<cache>/<stem>-<key>``."""
    key = json.dumps({"v": CONVERSION_VERSION, "rec": _stamp_of_recording(path), "opts": opts.key_fields()},
                     sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    cache = Path(opts.cache) if opts.cache is not None else path.resolve().parent / ".mslam"
    stem = path.name if path.is_dir() else path.stem
    return cache / f"{stem}-{digest}"


class TumWriter:
    """Builds a TUM-layout folder in a temporary sibling; :meth:`finish` renames it into place.

    RGB frames go to ``rgb/<t>.<ext>`` (encoded bytes written as they are: no re-encoding) or stay
    where they are (:meth:`add_rgb_path`); depth to ``depth/<t>.png`` as 16-bit raw units.
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.tmp = self.folder.with_name(f".{self.folder.name}.converting-{os.getpid()}")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        (self.tmp / "rgb").mkdir(parents=True)
        (self.tmp / "depth").mkdir()
        self.rgb: list[tuple[float, str]] = []
        self.depth: list[tuple[float, str]] = []
        self.gt: Trajectory | None = None
        self.size: tuple[int, int] | None = None  # (width, height) of the first RGB frame

    def _name(self, t: float, ext: str, taken: list[tuple[float, str]], sub: str) -> str:
        name = f"{sub}/{t:.6f}{ext}"
        if (self.tmp / name).exists():  # frames within a microsecond: keep them all
            name = f"{sub}/{t:.6f}_{len(taken)}{ext}"
        return name

    def add_rgb(self, t: float, image: bytes | np.ndarray, ext: str = ".png") -> None:
        """One colour frame at time ``t`` (s): encoded file bytes (``ext`` names the format), or a
        ``(H, W, 3)`` uint8 RGB / ``(H, W)`` uint8 grey array, written as PNG."""
        if isinstance(image, np.ndarray):
            arr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
            ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise DatasetError(f"{self.folder}: cannot encode frame at {t:.6f} s as PNG")
            image, ext = buf.tobytes(), ".png"
            if self.size is None:
                self.size = (int(arr.shape[1]), int(arr.shape[0]))
        name = self._name(t, ext, self.rgb, "rgb")
        (self.tmp / name).write_bytes(image)
        if self.size is None:
            img = cv2.imread(str(self.tmp / name), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DatasetError(f"{self.folder}: frame at {t:.6f} s cannot be decoded (expected {ext} bytes)")
            self.size = (int(img.shape[1]), int(img.shape[0]))
        self.rgb.append((t, name))

    def add_rgb_path(self, t: float, path: Path) -> None:
        """One colour frame that stays where it is (an image folder): listed by its absolute path."""
        self.rgb.append((t, str(Path(path).resolve())))

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

    def finish(self, intrinsics: Intrinsics, depth_scale: float, meta: dict[str, Any]) -> Path:
        """Write the lists, ``intrinsics.txt`` and ``source.json``, then rename into place."""
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


def open_recording(path: str | os.PathLike, opts: RecordingOptions) -> SequenceSpec:
    """Convert a recording once (cached) and return the spec of its TUM-layout folder.

    Raises:
        DatasetError: an unreadable recording, no colour frames, no intrinsics (no ``CameraInfo``
            and no camera file), a bad camera or GT file — one line naming the file.
    """
    from mutualslam_cli.datasets.camera_file import read_camera_file

    path = Path(path).expanduser()
    kind = recording_kind(path, opts)
    if kind is None:
        raise DatasetError(f"{path}: not a recording (a ROS bag, a video, or an image folder with --camera)")
    folder = conversion_folder(path, opts)
    if not (folder / "source.json").is_file():
        camera = read_camera_file(Path(opts.camera)) if opts.camera is not None else None
        writer = TumWriter(folder)
        try:
            if kind == "bag":
                from mutualslam_cli.datasets.rosbag import convert_bag

                intr, depth_scale, meta = convert_bag(path, opts, writer)
            else:
                from mutualslam_cli.datasets.video import convert_image_folder, convert_video

                convert = convert_video if kind == "video" else convert_image_folder
                intr, depth_scale, meta = None, 5000.0, convert(path, opts, writer)
            intr = camera if camera is not None else intr
            if intr is None:
                raise DatasetError(f"{path}: no intrinsics: the recording has no CameraInfo; give a camera file "
                                   "with --camera (OpenCV YAML, or a text line 'fx fy cx cy [k1 k2 p1 p2 k3]')")
            if writer.size is not None and intr.width and intr.height and (intr.width, intr.height) != writer.size:
                raise DatasetError(f"{opts.camera or path}: the camera is for {intr.width}×{intr.height} but the "
                                   f"frames are {writer.size[0]}×{writer.size[1]}")
            if opts.gt is not None:
                writer.set_gt(read_tum_trajectory(Path(opts.gt)))
            meta = {**meta, "source": str(path.resolve()), "kind": kind, "options": opts.key_fields(),
                    "intrinsics_source": "camera file" if camera is not None else meta.get("intrinsics_source")}
            writer.finish(intr, depth_scale, meta)
        except BaseException:
            writer.abort()
            raise
    return spec_of_conversion(folder, path)


def spec_of_conversion(folder: Path, source: Path | None = None) -> SequenceSpec:
    """The spec of a converted folder (format ``lab``: GT and depth optional)."""
    from mutualslam_cli.datasets.tum import read_intrinsics_txt

    meta = json.loads((folder / "source.json").read_text(encoding="utf-8"))
    intr = read_intrinsics_txt(folder / "intrinsics.txt")
    name = (source.name if source is not None and source.is_dir() else Path(meta["source"]).stem)
    name = "".join(c if c.isalnum() or c in "_.-" else "_" for c in name) or "recording"
    gt = "groundtruth.txt" if (folder / "groundtruth.txt").is_file() else None
    return SequenceSpec(name, folder, "lab", replace(intr), float(meta["depth_scale"]), gt,
                        {"recording": meta})

"""Recordings that are not sequence folders: ROS bags, videos, plain image folders (DESIGN §3).

A recording is converted once into a TUM-layout folder (``rgb.txt``, ``depth.txt``,
``groundtruth.txt``, ``intrinsics.txt``) under a conversion cache, and from then on runs like any
``lab`` folder: frames stream from disk, and every stage reads them alike. The folder is built
in a temporary sibling and renamed into place, so a killed conversion leaves nothing a run
would read; the cache key holds the recording's size, mtime and the options that change the
result, so an edited recording or other topics convert anew.

- ROS 1 ``.bag`` and ROS 2 bag folders / ``.db3`` / ``.mcap``: :mod:`~mutualslam_cli.datasets.recordings.rosbag`.
- Videos (``.mp4``, ``.avi``, ``.mkv``, ``.mov`` …) and image folders with a camera file:
  :mod:`~mutualslam_cli.datasets.recordings.video`.
- Camera files (OpenCV calibration YAML, ROS ``camera_calibration`` YAML, plain
  ``fx fy cx cy [k1 k2 p1 p2 k3]``): :mod:`~mutualslam_cli.datasets.recordings.camera_file`.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from mutualslam_cli.datasets.associate import read_tum_trajectory
from mutualslam_cli.datasets.recordings.conversion import (
    BAG_SUFFIXES,
    CONVERSION_VERSION,
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    RecordingOptions,
    TumWriter,
    file_stamp,
)
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import SequenceSpec

__all__ = [
    "IMAGE_SUFFIXES",
    "RecordingOptions",
    "TumWriter",
    "conversion_folder",
    "open_recording",
    "recording_kind",
    "spec_of_conversion",
]

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
        if (not (p / "rgb.txt").is_file() and not (p / "associations.txt").is_file()
                and any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()) and opts is not None and opts.camera):
            return "images"
    return None


def _stamp_of_recording(path: Path) -> str:
    if path.is_dir():  # a ROS 2 bag folder or an image folder: every file's size and mtime
        parts = sorted(f"{q.name}:{q.stat().st_size}:{q.stat().st_mtime_ns}" for q in path.iterdir() if q.is_file())
        return f"{path.resolve()}|" + "|".join(parts)
    return file_stamp(path)


def conversion_folder(path: Path, opts: RecordingOptions) -> Path:
    """Where the conversion of ``path`` with ``opts`` lives: ``<cache>/<stem>-<key>``."""
    key = json.dumps({"v": CONVERSION_VERSION, "rec": _stamp_of_recording(path), "opts": opts.key_fields()},
                     sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    cache = Path(opts.cache) if opts.cache is not None else path.resolve().parent / ".mslam"
    stem = path.name if path.is_dir() else path.stem
    return cache / f"{stem}-{digest}"


def open_recording(path: str | os.PathLike, opts: RecordingOptions,
                   progress: Callable[[int], None] | None = None) -> SequenceSpec:
    """Convert a recording once (cached) and return the spec of its TUM-layout folder; ``progress`` is
    called with the number of colour frames converted so far.

    Raises:
        DatasetError: an unreadable recording, no colour frames, no intrinsics (no ``CameraInfo``
            and no camera file), a bad camera or GT file — one line naming the file.
    """
    from mutualslam_cli.datasets.recordings.camera_file import read_camera_file

    path = Path(path).expanduser()
    kind = recording_kind(path, opts)
    if kind is None:
        raise DatasetError(f"{path}: not a recording (a ROS bag, a video, or an image folder with --camera)")
    folder = conversion_folder(path, opts)
    if not (folder / "source.json").is_file():
        camera = read_camera_file(Path(opts.camera)) if opts.camera is not None else None
        size = (camera.width, camera.height) if camera is not None and camera.width and camera.height else None
        writer = TumWriter(folder, progress, source=str(path), expect_size=size, camera=str(opts.camera))
        try:
            if kind == "bag":
                from mutualslam_cli.datasets.recordings.rosbag import convert_bag

                intr, depth_scale, meta = convert_bag(path, opts, writer)
            else:
                from mutualslam_cli.datasets.recordings.video import convert_image_folder, convert_video

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

"""``datasets.yaml`` → :class:`SequenceSpec`, folder autodetection, and :func:`load_sequence`.

See the comment header of the repository's ``datasets.yaml`` for the fields and how
relative roots are resolved.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from mutualslam_cli.config.yaml_file import read_yaml_mapping
from mutualslam_cli.datasets.associate import read_list_file
from mutualslam_cli.datasets.icl_nuim import NATIVE_RE, load_icl, load_icl_loop
from mutualslam_cli.datasets.recordings.conversion import BAG_SUFFIXES, VIDEO_SUFFIXES
from mutualslam_cli.datasets.recordings.recording import RecordingOptions, open_recording, recording_kind
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.datasets.tum import load_tum, tum_family
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics, JSONObject, SequenceSpec

log = logging.getLogger(__name__)

DEFAULT_REGISTRY = Path(__file__).resolve().parents[2] / "datasets.yaml"
FORMATS = ("tum", "icl", "icl_loop", "lab", "synthetic")
LOADERS: dict[str, Callable[[SequenceSpec], Sequence]] = {
    "tum": load_tum, "lab": load_tum, "synthetic": load_tum, "icl": load_icl, "icl_loop": load_icl_loop,
}
_KNOWN_KEYS = {"root", "format", "intrinsics", "dist", "size", "depth_scale", "gt"}


def _registry_path(registry_path: str | os.PathLike | None) -> Path:
    path = Path(registry_path) if registry_path is not None else DEFAULT_REGISTRY
    if not path.is_file():
        raise DatasetError(f"{path}: dataset registry not found (expected a datasets.yaml file)")
    return path


def _read_registry(path: Path) -> dict[str, dict[str, Any]]:
    """The ``datasets:`` mapping of a registry file, read strictly (:mod:`~mutualslam_cli.config.yaml_file`: no
    key given twice, few aliases, UTF-8)."""
    data = read_yaml_mapping(path, DatasetError, "dataset registry (datasets.yaml)")
    entries = data.get("datasets")
    if not isinstance(entries, dict):
        raise DatasetError(f"{path}: expected a top-level 'datasets:' mapping of name -> entry")
    return entries


def resolve_root(root: str, registry_file: Path, data_root: str | os.PathLike | None = None) -> Path:
    """Absolute folder for a registry ``root`` (rules in the ``datasets.yaml`` header)."""
    p = Path(os.path.expanduser(root))
    if p.is_absolute():
        return p
    if root.startswith(("./", "../")):
        return (registry_file.parent / p).resolve()
    base = data_root if data_root is not None else os.environ.get("MSLAM_DATA") or registry_file.parent
    return (Path(base).expanduser() / p).resolve()


def spec_from_entry(name: str, entry: dict[str, Any], registry_file: Path,
                    data_root: str | os.PathLike | None = None) -> SequenceSpec:
    """Validate one registry entry and resolve it into a :class:`SequenceSpec`."""
    where = f"{registry_file}: entry '{name}'"
    if not isinstance(entry, dict) or "root" not in entry or "format" not in entry:
        raise DatasetError(f"{where}: expected a mapping with at least 'root' and 'format'")
    fmt = str(entry["format"])
    if fmt not in FORMATS:
        raise DatasetError(f"{where}: format '{fmt}' unknown; expected one of {', '.join(FORMATS)}")
    intr = None
    if entry.get("intrinsics") is not None:
        k = entry["intrinsics"]
        size = entry.get("size") or [0, 0]
        dist = entry.get("dist")
        try:
            if len(k) != 4 or len(size) != 2 or (dist is not None and len(dist) not in (4, 5, 8)):
                raise ValueError
            fx, fy, cx, cy = (float(x) for x in k)  # 4 numbers, checked above
            intr = Intrinsics(fx, fy, cx, cy, int(size[0]), int(size[1]),
                              tuple(float(x) for x in dist) if dist is not None else None)
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: expected 'intrinsics: [fx, fy, cx, cy]' (+ optional 'size: [w, h]', "
                               f"'dist: [k1, k2, p1, p2, k3]'), got {k!r}") from None
    try:
        depth_scale = float(entry.get("depth_scale", 5000.0))
        if depth_scale <= 0:
            raise ValueError
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: depth_scale must be a positive number, "
                           f"got {entry.get('depth_scale')!r}") from None
    extra = {k: v for k, v in entry.items() if k not in _KNOWN_KEYS}
    gt = entry.get("gt")
    return SequenceSpec(name, resolve_root(str(entry["root"]), registry_file, data_root), fmt, intr,
                        depth_scale, str(gt) if gt else None, extra)


def list_datasets(registry_path: str | os.PathLike | None = None,
                  data_root: str | os.PathLike | None = None) -> list[SequenceSpec]:
    """All registry entries as specs, in file order."""
    path = _registry_path(registry_path)
    return [spec_from_entry(n, e, path, data_root) for n, e in _read_registry(path).items()]


def get_spec(name: str, registry_path: str | os.PathLike | None = None,
             data_root: str | os.PathLike | None = None) -> SequenceSpec:
    """The spec of one registry name; an unknown name lists the valid ones."""
    path = _registry_path(registry_path)
    entries = _read_registry(path)
    if name not in entries:
        raise DatasetError(f"{path}: unknown dataset '{name}'; valid names: {', '.join(entries)} "
                           "(or give a sequence folder path)")
    return spec_from_entry(name, entries[name], path, data_root)


def detect_format(folder: str | os.PathLike) -> str:
    """Format of a sequence folder from the files it holds.

    ``associations.txt`` + ``*.gt.freiburg`` → ``icl``; ``rgb.txt`` → ``tum`` (name holds a
    TUM family), ``synthetic`` (``intrinsics.txt`` present) or ``lab``; ``scene_00_*.png``
    → ``icl_loop``; ``associations.txt`` alone → ``icl`` when it lists depth first (the
    ICL-NUIM convention), else ``lab``.
    """
    root = Path(folder)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a dataset name nor a sequence folder")
    if (root / "associations.txt").is_file() and any(root.glob("*.gt.freiburg")):
        return "icl"
    if (root / "rgb.txt").is_file():
        if (root / "intrinsics.txt").is_file():
            return "synthetic"
        return "tum" if tum_family(root.name) else "lab"
    if any(NATIVE_RE.match(p.name) for p in root.iterdir()):
        return "icl_loop"
    if (root / "associations.txt").is_file():
        return "icl" if _depth_listed_first(root / "associations.txt") else "lab"
    raise DatasetError(
        f"{root}: unknown sequence layout; looked for associations.txt + *.gt.freiburg (ICL-NUIM), "
        "rgb.txt + depth.txt (TUM / lab / synthetic), scene_00_NNNN.png (native ICL-NUIM); "
        "a folder of images runs with a camera file (--camera)"
    )


def _depth_listed_first(path: Path) -> bool:
    lf = read_list_file(path, min_fields=4)
    return bool(len(lf)) and "depth" in lf.columns[0][0].lower() and "depth" not in lf.columns[0][2].lower()


def spec_from_folder(folder: str | os.PathLike) -> SequenceSpec:
    """A spec for a folder given directly (format autodetected, family/file defaults)."""
    root = Path(folder).expanduser().resolve()
    fmt = detect_format(root)
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", root.name) or "sequence"
    extra: JSONObject = {"fy_sign": "auto"} if fmt in ("icl", "icl_loop") else {}
    return SequenceSpec(name, root, fmt, None, 5000.0, None, extra)


def _registered_folder(folder: str, registry_path: str | os.PathLike | None,
                       data_root: str | os.PathLike | None) -> SequenceSpec:
    """The registry entry whose root is ``folder`` (keeps its depth scale etc.), else autodetect."""
    root = Path(folder).expanduser().resolve()
    try:
        specs = list_datasets(registry_path, data_root)
    except DatasetError:
        specs = []
    for spec in specs:
        if spec.root == root:
            return spec
    return spec_from_folder(root)


def subset_frames(seq: Sequence, max_frames: int = 0, stride: int = 1) -> Sequence:
    """Keep every ``stride``-th frame, then at most ``max_frames`` of them (0 = all); reindex."""
    if stride < 1 or max_frames < 0:
        raise DatasetError(f"{seq.root}: stride must be ≥ 1 and max_frames ≥ 0, got {stride}, {max_frames}")
    frames = seq.frames[::stride]
    if max_frames:
        frames = frames[:max_frames]
    seq.frames = [replace(f, index=k, pose=f.pose) for k, f in enumerate(frames)]
    seq.meta["subset"] = {"stride": stride, "max_frames": max_frames, "frames": len(frames)}
    return seq


def load_sequence(name_or_path: str | os.PathLike, data_root: str | os.PathLike | None = None,
                  registry_path: str | os.PathLike | None = None, max_frames: int = 0, stride: int = 1,
                  recording: RecordingOptions | None = None, progress: Callable[[int], None] | None = None) -> Sequence:
    """Load a sequence by registry name, folder path or recording.

    Args:
        name_or_path: a ``datasets.yaml`` name, a folder (format autodetected), or a recording (a ROS
            bag, a video, an image folder with ``recording.camera``: converted once,
            :mod:`~mutualslam_cli.datasets.recordings.recording`).
        data_root: base of relative registry roots (else ``$MSLAM_DATA``, else the yaml's folder).
        registry_path: the registry file (default: the repository's ``datasets.yaml``).
        max_frames: keep at most this many frames after striding (0 = all).
        stride: keep every ``stride``-th associated frame.
        recording: how to read a recording (topics, camera file, GT file, conversion cache); its
            ``camera`` and ``gt`` also replace a folder's intrinsics and GT file.
        progress: called with the frames converted so far while a recording is converted.

    Raises:
        DatasetError: unknown name (valid names listed), unknown layout, or any loader error.
    """
    s = str(name_or_path)
    opts = recording or RecordingOptions()
    if Path(s).expanduser().exists() and recording_kind(Path(s).expanduser(), opts) is not None:
        return load_spec(open_recording(s, opts, progress), max_frames=max_frames, stride=stride)
    if Path(s).is_file():  # a file that is not a recording: the one line says what is expected
        recording_kind(Path(s), opts)
    if Path(s).suffix.lower() in BAG_SUFFIXES + VIDEO_SUFFIXES and not Path(s).expanduser().exists():
        raise DatasetError(f"{s}: recording not found")
    is_path = isinstance(name_or_path, os.PathLike) or os.sep in s or "/" in s
    if not is_path:
        path = _registry_path(registry_path)
        is_path = s not in _read_registry(path) and Path(s).is_dir()
    spec = _registered_folder(s, registry_path, data_root) if is_path else get_spec(s, registry_path, data_root)
    if opts.camera is not None:
        from mutualslam_cli.datasets.recordings.camera_file import read_camera_file

        spec = replace(spec, intrinsics=read_camera_file(Path(opts.camera)))
    if opts.gt is not None:
        spec = replace(spec, gt_file=str(Path(opts.gt).expanduser().resolve()))
    return load_spec(spec, max_frames=max_frames, stride=stride)


def load_spec(spec: SequenceSpec, max_frames: int = 0, stride: int = 1) -> Sequence:
    """Load a resolved spec with its format's loader, then subset the frames."""
    if spec.format not in LOADERS:
        raise DatasetError(f"{spec.root}: format '{spec.format}' unknown; expected one of {', '.join(FORMATS)}")
    seq = LOADERS[spec.format](spec)
    seq.meta.setdefault("format", spec.format)
    if "recording" in spec.extra:  # where a converted recording came from, into the run's manifest
        seq.meta["recording"] = spec.extra["recording"]
    return subset_frames(seq, max_frames, stride)

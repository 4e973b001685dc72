"""Dataset checks (``mslam datasets check``) and the loader benchmark.

:func:`check_sequence` loads a sequence (which already validates list files, GT files,
referenced images, GT overlap and emptiness, raising :class:`DatasetError`), then decodes every
RGB and depth image (or an evenly spread sample of frames, ``sample=N``), so that a bad file is
reported before a long run rather than in its middle:

- a file the decoder cannot read, or a depth PNG that is not 16-bit single-channel;
- an image whose shape or dtype differs from the sequence's first image of its kind;
- a truncated or corrupted PNG or JPEG. OpenCV decodes some truncated PNGs partially with only a
  warning, so the file structure is checked first (:mod:`~mutualslam_cli.datasets.image_files`, shared
  with the recording converters).

Depth values only warn: a median valid depth outside :data:`PLAUSIBLE_DEPTH_M` suggests a wrong
``depth_scale``.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from mutualslam_cli.datasets.image_files import image_file_problem, jpeg_problem, png_problem
from mutualslam_cli.datasets.registry import get_spec, list_datasets, load_sequence, load_spec
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Info, Progress, SequenceSpec

__all__ = ["CheckReport", "bench_loader", "check_all", "check_sequence", "image_file_problem", "jpeg_problem",
           "png_problem"]

PLAUSIBLE_DEPTH_M = (0.2, 20.0)
"""Median valid depth outside this range (metres) suggests a wrong ``depth_scale``."""

#: ``progress("decode", info)`` after each decoded image; ``info``: ``done`` and ``total`` (images),
#: ``file`` (the image just decoded), ``sequence`` (its name). The pipeline's callback style.
CheckProgress = Progress

@dataclass
class CheckReport:
    """What :func:`check_sequence` found. Times in seconds, coverage in percent.

    ``images_decoded`` counts RGB and depth images, ``frames_decoded`` the frames they belong to
    (``frames`` when every frame was checked).
    """

    name: str
    root: str
    format: str
    frames: int
    time_span_s: float
    frames_with_depth: int
    frames_with_gt: int
    gt_coverage_pct: float
    intrinsics: list[float]
    image_size: tuple[int, int]
    depth_scale: float
    median_depth_m: float | None
    fy_sign: int | None = None
    fy_sign_errors: dict[str, float] | None = None
    warnings: list[str] = field(default_factory=list)
    images_decoded: int = 0
    frames_decoded: int = 0

    @property
    def ok(self) -> bool:
        """True when no warning was raised."""
        return not self.warnings

    def as_dict(self) -> Info:
        """Plain values for JSON/YAML and tables."""
        return dataclasses.asdict(self)


def _as_sequence(seq_or_spec: Sequence | SequenceSpec | str | os.PathLike, registry_path: str | os.PathLike | None,
                 data_root: str | os.PathLike | None) -> Sequence:
    if isinstance(seq_or_spec, Sequence):
        return seq_or_spec
    if isinstance(seq_or_spec, SequenceSpec):
        return load_spec(seq_or_spec)
    return load_sequence(seq_or_spec, data_root=data_root, registry_path=registry_path)


def _describe(img: np.ndarray, dtype: bool = True) -> str:
    """``W×H[×C] dtype``."""
    return "×".join(str(v) for v in (img.shape[1], img.shape[0], *img.shape[2:])) + (f" {img.dtype}" if dtype else "")


class _Decoder:
    """Decodes the images of one sequence and compares each with the first one of its kind."""

    def __init__(self, seq: Sequence):
        self.seq = seq
        self.first: dict[str, tuple[Path, np.ndarray]] = {}  # kind → (path, first image)

    def _same_as_first(self, kind: str, path: Path, img: np.ndarray) -> None:
        ref_path, ref = self.first.setdefault(kind, (path, img))
        raw = kind == "RGB"  # depth is compared after the loader's conversion to metres: by size only
        if img.shape != ref.shape or img.dtype != ref.dtype:
            raise DatasetError(f"{path}: {kind} image is {_describe(img, raw)}, expected {_describe(ref, raw)} "
                               f"like the sequence's first {kind} image {ref_path.name}")

    @staticmethod
    def _read(path: Path, kind: str) -> bytes:
        try:
            data = path.read_bytes()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read {kind} image ({e.strerror})") from None
        problem = image_file_problem(path, data)
        if problem:
            raise DatasetError(f"{path}: {problem}; expected a complete {kind} image file (copy it again)")
        return data

    def rgb(self, i: int) -> Path:
        path = Path(self.seq.frames[i].rgb_path)
        img = cv2.imdecode(np.frombuffer(self._read(path, "RGB"), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{path}: cannot decode RGB image (expected a PNG/JPEG colour image)")
        self._same_as_first("RGB", path, img)
        return path

    def depth(self, i: int) -> tuple[Path, np.ndarray]:
        path = Path(self.seq.frames[i].depth_path)  # type: ignore[arg-type]
        self._read(path, "depth")
        d = self.seq.load_depth(i)  # the loader's own checks (16-bit PNG, ICL .depth size), in metres
        assert d is not None
        self._same_as_first("depth", path, d)
        return path, d


def check_sequence(
    seq_or_spec: Sequence | SequenceSpec | str | os.PathLike,
    sample: int = 0,
    registry_path: str | os.PathLike | None = None,
    data_root: str | os.PathLike | None = None,
    on_progress: Callable[[str], None] | None = None,
    progress: CheckProgress | None = None,
) -> CheckReport:
    """Validate one sequence, decoding its images, and summarise it.

    Args:
        seq_or_spec: a loaded :class:`Sequence`, a spec, a registry name or a folder.
        sample: 0 (default): decode every RGB and depth image; N > 0: only those of N frames
            evenly spread over the sequence (a quick check).
        registry_path, data_root: as for :func:`load_sequence`.
        on_progress: optional callback receiving one-line status messages.
        progress: optional :data:`CheckProgress`, called after each decoded image.

    Raises:
        DatasetError: the first hard problem (missing/malformed files, an image that cannot be
            decoded, is truncated or corrupted, or differs in shape/dtype from the first one,
            an 8-bit depth PNG, no GT overlap, empty sequence, missing image), naming the file
            (and line) and what was expected.
    """
    seq = _as_sequence(seq_or_spec, registry_path, data_root)
    n = len(seq)
    frames = range(n) if sample <= 0 else np.unique(np.linspace(0, n - 1, min(sample, n)).round().astype(int))
    total = sum(1 + (seq.frames[i].depth_path is not None) for i in frames)
    if on_progress:
        on_progress(f"{seq.name}: {n} frames loaded, decoding {total} images of "
                    f"{'every frame' if sample <= 0 else f'{len(frames)} frames'}")
    warnings = list(seq.meta.get("warnings", []))
    times = np.array([f.timestamp for f in seq.frames])
    n_depth = sum(f.depth_path is not None for f in seq.frames)
    n_gt = sum(f.pose is not None for f in seq.frames)
    decoder, medians, done = _Decoder(seq), [], 0
    for i in frames:
        paths = [decoder.rgb(i)]
        if seq.frames[i].depth_path is not None:
            path, d = decoder.depth(i)
            paths.append(path)
            valid = d[::4, ::4]  # every 16th pixel: plenty for a plausibility median
            valid = valid[valid > 0]
            if valid.size:
                medians.append(float(np.median(valid)))
        for path in paths:
            done += 1
            if progress:
                progress("decode", {"done": done, "total": total, "file": str(path), "sequence": seq.name})
    K = seq.intrinsics
    for kind, (path, img) in decoder.first.items():
        if img.shape[:2] != (K.height, K.width):
            warnings.append(f"{path}: {kind} is {img.shape[1]}×{img.shape[0]}, the intrinsics are for "
                            f"{K.width}×{K.height}")
    med = float(np.median(medians)) if medians else None
    lo, hi = PLAUSIBLE_DEPTH_M
    if med is not None and not lo <= med <= hi:
        warnings.append(f"median valid depth {med:.3g} m outside {lo}–{hi} m: depth_scale {seq.depth_scale:g} "
                        "looks wrong for this data")
    if "depth" in decoder.first and med is None:
        warnings.append("decoded depth images have no valid pixel")
    if not n_depth:
        warnings.append("no frame has a depth image (depth metrics will be absent)")
    if not n_gt:
        warnings.append("no GT poses (trajectory metrics will be absent)")
    elif n_gt < 0.9 * n:
        warnings.append(f"GT covers only {n_gt} of {n} frames")
    return CheckReport(
        name=seq.name, root=str(seq.root), format=str(seq.meta.get("format", "?")), frames=n,
        time_span_s=float(times.max() - times.min()) if len(times) else 0.0,
        frames_with_depth=n_depth, frames_with_gt=n_gt,
        gt_coverage_pct=100.0 * n_gt / n if n else 0.0,
        intrinsics=K.as_list() + (list(K.dist) if K.dist else []), image_size=(K.width, K.height),
        depth_scale=seq.depth_scale, median_depth_m=med,
        fy_sign=seq.meta.get("fy_sign"), fy_sign_errors=seq.meta.get("fy_sign_errors"), warnings=warnings,
        images_decoded=done, frames_decoded=len(frames),
    )


def check_all(names: list[str] | None = None, registry_path: str | os.PathLike | None = None,
              data_root: str | os.PathLike | None = None, sample: int = 0) -> list[CheckReport | Exception]:
    """Check several registry entries (``sample`` as for :func:`check_sequence`); a failing entry
    gives its exception instead of a report."""
    specs = (list_datasets(registry_path, data_root) if names is None
             else [get_spec(n, registry_path, data_root) for n in names])
    out: list[CheckReport | Exception] = []
    for spec in specs:
        try:
            out.append(check_sequence(spec, sample=sample))
        except Exception as e:  # reported per entry by the caller
            out.append(e)
    return out


def bench_loader(seq: Sequence, n: int = 50, with_depth: bool = True) -> dict[str, float]:
    """Frames per second of reading + decoding RGB (and depth) for the first ``n`` frames.

    Returns:
        ``{"frames", "seconds", "fps", "rgb_ms", "depth_ms"}`` (ms are per frame).
    """
    n = min(n, len(seq))
    t_rgb = t_depth = 0.0
    for i in range(n):
        t0 = time.perf_counter()
        seq.load_rgb(i)
        t1 = time.perf_counter()
        if with_depth:
            seq.load_depth(i)
        t2 = time.perf_counter()
        t_rgb += t1 - t0
        t_depth += t2 - t1
    total = t_rgb + t_depth
    return {"frames": float(n), "seconds": total, "fps": n / total if total > 0 else float("inf"),
            "rgb_ms": 1e3 * t_rgb / max(n, 1), "depth_ms": 1e3 * t_depth / max(n, 1)}


"""Dataset checks (``mslam datasets --check``) and the loader benchmark.

:func:`check_sequence` loads a sequence (which already validates list files, GT files,
referenced images, GT overlap and emptiness, raising :class:`DatasetError`), then decodes a
sample of depth images to verify they are 16-bit and that the depth scale gives plausible
indoor depths.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mutualslam_cli.datasets.registry import get_spec, load_sequence, load_spec
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.types import SequenceSpec

PLAUSIBLE_DEPTH_M = (0.2, 20.0)
"""Median valid depth outside this range (metres) suggests a wrong ``depth_scale``."""


@dataclass
class CheckReport:
    """What :func:`check_sequence` found. Times in seconds, coverage in percent."""

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

    @property
    def ok(self) -> bool:
        """True when no warning was raised."""
        return not self.warnings

    def as_dict(self) -> dict[str, Any]:
        """Plain values for JSON/YAML and tables."""
        return dataclasses.asdict(self)


def _as_sequence(seq_or_spec: Sequence | SequenceSpec | str | os.PathLike, registry_path, data_root) -> Sequence:
    if isinstance(seq_or_spec, Sequence):
        return seq_or_spec
    if isinstance(seq_or_spec, SequenceSpec):
        return load_spec(seq_or_spec)
    return load_sequence(seq_or_spec, data_root=data_root, registry_path=registry_path)


def check_sequence(
    seq_or_spec: Sequence | SequenceSpec | str | os.PathLike,
    sample: int = 5,
    registry_path: str | os.PathLike | None = None,
    data_root: str | os.PathLike | None = None,
    on_progress: Callable[[str], None] | None = None,
) -> CheckReport:
    """Validate one sequence and summarise it.

    Args:
        seq_or_spec: a loaded :class:`Sequence`, a spec, a registry name or a folder.
        sample: number of depth images (evenly spread) to decode.
        registry_path, data_root: as for :func:`load_sequence`.
        on_progress: optional callback receiving one-line status messages.

    Raises:
        DatasetError: every hard problem (missing/malformed files, 8-bit depth PNG, no GT
            overlap, empty sequence, missing image), with file, line and expected format.
    """
    seq = _as_sequence(seq_or_spec, registry_path, data_root)
    if on_progress:
        on_progress(f"{seq.name}: {len(seq)} frames loaded, decoding {sample} depth images")
    warnings = list(seq.meta.get("warnings", []))
    times = np.array([f.timestamp for f in seq.frames])
    n_depth = sum(f.depth_path is not None for f in seq.frames)
    n_gt = sum(f.pose is not None for f in seq.frames)
    depth_idx = [k for k, f in enumerate(seq.frames) if f.depth_path is not None]
    medians = []
    if depth_idx and sample > 0:
        for k in np.unique(np.linspace(0, len(depth_idx) - 1, sample).round().astype(int)):
            d = seq.load_depth(depth_idx[k])  # raises DatasetError for a non-16-bit PNG
            assert d is not None
            if d.shape != (seq.intrinsics.height, seq.intrinsics.width):
                warnings.append(f"{seq.frames[depth_idx[k]].depth_path}: depth is {d.shape[1]}×{d.shape[0]}, "
                                f"images are {seq.intrinsics.width}×{seq.intrinsics.height}")
            valid = d[d > 0]
            if valid.size:
                medians.append(float(np.median(valid)))
    med = float(np.median(medians)) if medians else None
    lo, hi = PLAUSIBLE_DEPTH_M
    if med is not None and not lo <= med <= hi:
        warnings.append(f"median valid depth {med:.3g} m outside {lo}–{hi} m: depth_scale {seq.depth_scale:g} "
                        "looks wrong for this data")
    if depth_idx and sample > 0 and med is None:
        warnings.append("sampled depth images have no valid pixel")
    if not n_depth:
        warnings.append("no frame has a depth image (depth metrics will be absent)")
    if not n_gt:
        warnings.append("no GT poses (trajectory metrics will be absent)")
    elif n_gt < 0.9 * len(seq):
        warnings.append(f"GT covers only {n_gt} of {len(seq)} frames")
    K = seq.intrinsics
    return CheckReport(
        name=seq.name, root=str(seq.root), format=str(seq.meta.get("format", "?")), frames=len(seq),
        time_span_s=float(times.max() - times.min()) if len(times) else 0.0,
        frames_with_depth=n_depth, frames_with_gt=n_gt,
        gt_coverage_pct=100.0 * n_gt / len(seq) if len(seq) else 0.0,
        intrinsics=K.as_list() + (list(K.dist) if K.dist else []), image_size=(K.width, K.height),
        depth_scale=seq.depth_scale, median_depth_m=med,
        fy_sign=seq.meta.get("fy_sign"), fy_sign_errors=seq.meta.get("fy_sign_errors"), warnings=warnings,
    )


def check_all(names: list[str] | None = None, registry_path: str | os.PathLike | None = None,
              data_root: str | os.PathLike | None = None, sample: int = 5) -> list[CheckReport | Exception]:
    """Check several registry entries; a failing entry gives its exception instead of a report."""
    from mutualslam_cli.datasets.registry import list_datasets

    specs = (list_datasets(registry_path, data_root) if names is None
             else [get_spec(n, registry_path, data_root) for n in names])
    out: list[CheckReport | Exception] = []
    for spec in specs:
        try:
            out.append(check_sequence(spec, sample=sample))
        except Exception as e:  # noqa: BLE001 - reported per entry by the caller
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


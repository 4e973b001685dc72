"""Cut and splice a TUM-layout sequence into a new one: real images with a real jump at each join.

Re-entry test material for relocalisation and map merging: the colour frames of some ranges of a source
sequence, in the order given, re-stamped at a steady rate so that the output looks like one recording. A
range that starts far from where the previous one ended is a gap the front end cannot bridge by tracking
(a cut, or a kidnap when the next range is from elsewhere in the recording).

The output holds links to the source's image files (no copies), ``rgb.txt``, ``depth.txt`` and
``groundtruth.txt`` when the source has them, ``camera-intrinsics.txt`` copied, and ``splice.json``
naming the source, the ranges and each output frame's source frame.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT, associate, read_list_file, read_tum_trajectory, stamps_match
from mutualslam_cli.datasets.layout import check_files
from mutualslam_cli.errors import DatasetError

MANIFEST = "splice.json"


@dataclass(frozen=True)
class SpliceInfo:
    """What :func:`splice_sequence` wrote.

    Attributes:
        out: the output folder.
        sources: per output frame, its source colour frame index (0-based, ``rgb.txt`` order).
        joins: output frame indices where a range after the first starts.
        depth: output frames with a depth image; gt: output frames with a GT pose.
    """

    out: Path
    sources: list[int]
    joins: list[int]
    depth: int
    gt: int


def _nearest(ts: np.ndarray, t: float) -> int | None:
    """Index of the entry of sorted ``ts`` (s) nearest to ``t`` (s) within :data:`MAX_DT`, else None."""
    j = int(np.searchsorted(ts, t))
    best = min((k for k in (j - 1, j) if 0 <= k < len(ts)), key=lambda k: abs(ts[k] - t), default=None)
    return best if best is not None and stamps_match(float(ts[best] - t), MAX_DT) else None


def _link(out: Path, sub: str, k: int, target: Path) -> str:
    """Link ``out/sub/<k>-<name>`` to the real file behind ``target``; returns the relative path."""
    rel = f"{sub}/{k:06d}-{target.name}"
    os.symlink(target.resolve(strict=True), out / rel)
    return rel


def splice_sequence(src: Path, out: Path, keep: list[tuple[int, int]], rate_hz: float = 30.0) -> SpliceInfo:
    """Write the colour frames ``[a, b)`` of each range of ``keep`` (in that order) as a new TUM folder.

    Args:
        src: a TUM-layout folder with ``rgb.txt`` (``depth.txt``, ``groundtruth.txt`` optional).
        out: the output folder; written as ``out.tmp`` and renamed. An existing ``out`` is replaced
            only if it holds a ``splice.json`` (made by this function).
        keep: half-open ranges of 0-based colour frame indices in ``rgb.txt`` order; may overlap.
        rate_hz: output frame rate (Hz): frame ``k`` is stamped ``t0 + k / rate_hz`` seconds, ``t0``
            the source's first colour timestamp.

    A depth image is kept with the colour frame it pairs with (greedy, within 0.02 s, as TUM's
    ``associate.py``); a GT line is the source pose nearest in time to the colour frame within 0.02 s
    (none if there is none). Both are re-stamped with the frame's new time.

    Raises:
        DatasetError: a missing folder or ``rgb.txt``, a malformed line, a missing image, a bad range or rate.
    """
    src, out = Path(src), Path(out)
    rgb_txt, depth_txt, gt_txt = src / "rgb.txt", src / "depth.txt", src / "groundtruth.txt"
    if not rgb_txt.is_file():
        raise DatasetError(f"{rgb_txt}: not found (expected a TUM folder with lines 'timestamp rgb/<file>')")
    rgb = read_list_file(rgb_txt)
    n = len(rgb)
    if not keep:
        raise DatasetError("keep: no range given; expected at least one A:B")
    for a, b in keep:
        if not 0 <= a < b <= n:
            raise DatasetError(f"keep {a}:{b}: expected A:B with 0 <= A < B <= {n} (the frames of {rgb_txt})")
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise DatasetError(f"rate {rate_hz}: expected a positive frame rate (Hz)")
    if out.resolve() == src.resolve():
        raise DatasetError(f"{out}: the output folder is the source; expected another folder")
    if out.exists() and not (out / MANIFEST).is_file():
        raise DatasetError(f"{out}: exists and holds no {MANIFEST}; expected a new folder or an earlier splice")
    sources = [i for a, b in keep for i in range(a, b)]
    used = sorted(set(sources))
    rgb_files = dict(zip(used, check_files(src, rgb, [rgb.paths[i] for i in used], used)))
    depth_of: dict[int, Path] = {}
    if depth_txt.is_file():
        dl = read_list_file(depth_txt)
        pairs = associate(rgb.timestamps, dl.timestamps)
        kept = sorted(j for i, j in pairs if i in rgb_files)
        files = dict(zip(kept, check_files(src, dl, [dl.paths[j] for j in kept], kept)))
        depth_of = {i: files[j] for i, j in pairs if j in files}
    gt_of: dict[int, list[str]] = {}
    if gt_txt.is_file():
        read_tum_trajectory(gt_txt)  # every line checked: 8 numbers, a non-zero quaternion
        gl = read_list_file(gt_txt, min_fields=8)  # ... and copied as it is written
        order = np.argsort(gl.timestamps, kind="stable")
        for i in used:
            j = _nearest(gl.timestamps[order], float(rgb.timestamps[i]))
            if j is not None:
                gt_of[i] = gl.columns[order[j]]
    t0 = float(rgb.timestamps[0])
    head = f"# spliced from {src.resolve()} by mslam datasets splice: frames " + " + ".join(
        f"[{a}, {b})" for a, b in keep) + f"; timestamps t0 + k / {rate_hz:g} s"
    fields = {"rgb.txt": ("color images", "filename"), "depth.txt": ("depth maps", "filename"),
              "groundtruth.txt": ("ground truth trajectory", "tx ty tz qx qy qz qw")}
    lines = {name: [f"# {what}", head, f"# timestamp {cols}"] for name, (what, cols) in fields.items()}
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        (tmp / "rgb").mkdir(parents=True)
        if depth_of:
            (tmp / "depth").mkdir()
        for k, i in enumerate(sources):
            t = f"{t0 + k / rate_hz:.6f}"
            lines["rgb.txt"].append(f"{t} {_link(tmp, 'rgb', k, rgb_files[i])}")
            if i in depth_of:
                lines["depth.txt"].append(f"{t} {_link(tmp, 'depth', k, depth_of[i])}")
            if i in gt_of:
                lines["groundtruth.txt"].append(" ".join([t, *gt_of[i]]))
        for name, body in lines.items():
            if (src / name).is_file():
                (tmp / name).write_text("\n".join(body) + "\n", encoding="utf-8")
        if (src / "camera-intrinsics.txt").is_file():
            shutil.copyfile(src / "camera-intrinsics.txt", tmp / "camera-intrinsics.txt")
        joins = [sum(b - a for a, b in keep[:r]) for r in range(1, len(keep))]
        info = SpliceInfo(out, sources, joins, len(lines["depth.txt"]) - 3, len(lines["groundtruth.txt"]) - 3)
        manifest = {"source": str(src.resolve()), "keep": [[a, b] for a, b in keep], "rate_hz": rate_hz, "t0": t0,
                    "joins": joins, "source_frames": sources, "depth": info.depth, "gt": info.gt}
        text = ",\n".join(f" {json.dumps(k)}: {json.dumps(v)}" for k, v in manifest.items())  # one key a line
        (tmp / MANIFEST).write_text("{\n" + text + "\n}\n", encoding="utf-8")
        old = out.with_name(out.name + ".old")
        if out.exists():  # an earlier splice: moved aside, so that `out` is the old folder or the new one
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return info

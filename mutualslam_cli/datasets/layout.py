"""Pieces shared by the sequence-folder loaders (:mod:`.tum`, :mod:`.icl_nuim`).

Listed image files, ``associations.txt`` (``t_a path_a t_b path_b``), the GT trajectory file
(``timestamp tx ty tz qx qy qz qw``, camera-to-world) and GT poses at frame times, and the
frame list of a :class:`~mutualslam_cli.datasets.sequence.Sequence`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from mutualslam_cli.datasets.associate import ListFile, poses_at, read_list_file, read_tum_trajectory
from mutualslam_cli.datasets.sequence import Association
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import FrameRef, SequenceSpec, Trajectory


def image_size(path: Path, listed_in: str = "") -> tuple[int, int]:
    """``(width, height)`` of an image file (decodes it once)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        where = f"{listed_in}: " if listed_in else ""
        raise DatasetError(f"{where}{path}: cannot read image (expected a PNG/JPEG file)")
    return int(img.shape[1]), int(img.shape[0])


def check_files(root: Path, listing: ListFile, paths: list[str], entries: list[int]) -> list[Path]:
    """Resolve listed paths against ``root``; a missing file raises naming list file and line."""
    out = []
    for p, e in zip(paths, entries):
        full = root / p
        if not full.is_file():
            raise DatasetError(f"{listing.name}:{listing.lines[e]}: image file {p} not found under {root}")
        out.append(full)
    return out


def load_gt(spec: SequenceSpec, default: str | None = "groundtruth.txt") -> tuple[Trajectory | None, str | None]:
    """The stored GT trajectory and its file name, or ``(None, None)`` when there is none.

    A GT file named in the spec must exist; the default name is optional.
    """
    root = Path(spec.root)
    if spec.gt_file:
        path = root / spec.gt_file
        if not path.is_file():
            raise DatasetError(
                f"{path}: GT file named in the registry entry '{spec.name}' not found "
                "(expected lines 'timestamp tx ty tz qx qy qz qw')"
            )
        return read_tum_trajectory(path), spec.gt_file
    if default and (root / default).is_file():
        return read_tum_trajectory(root / default), default
    return None, None


def attach_gt(
    frames_t: np.ndarray, gt: Trajectory | None, gt_name: str | None, root: Path, max_gap: float
) -> list[np.ndarray | None]:
    """GT poses at the frame times; raises when a GT file exists but covers no frame."""
    if gt is None:
        return [None] * len(frames_t)
    if len(gt) == 0:
        raise DatasetError(f"{root / str(gt_name)}: GT file has no poses (expected 'timestamp tx ty tz qx qy qz qw')")
    poses = poses_at(gt, frames_t, max_gap=max_gap)
    if not any(p is not None for p in poses):
        raise DatasetError(
            f"{root / str(gt_name)}: no GT overlap: images span {frames_t.min():.6f}–{frames_t.max():.6f} s, "
            f"GT spans {gt.timestamps[0]:.6f}–{gt.timestamps[-1]:.6f} s"
        )
    return poses


def make_frames(
    times: np.ndarray, rgb: Sequence[Path], depth: Sequence[Path | None], poses: Sequence[np.ndarray | None]
) -> list[FrameRef]:
    """FrameRefs in time order."""
    order = np.argsort(times, kind="stable")
    return [FrameRef(k, float(times[i]), rgb[i], depth[i], poses[i]) for k, i in enumerate(order)]


def _associations_columns(listing: ListFile, depth_first: bool) -> tuple[list[int], bool]:
    """Decide whether the associations file lists depth first (by path names, else default)."""
    if not len(listing):
        return [], depth_first
    a, b = listing.columns[0][0].lower(), listing.columns[0][2].lower()
    if "depth" in a and "depth" not in b:
        depth_first = True
    elif "depth" in b and "depth" not in a:
        depth_first = False
    return list(range(len(listing))), depth_first


def frames_from_associations(root: Path, depth_first: bool) -> tuple[np.ndarray, list[Path], list[Path], Association]:
    """Frames from ``associations.txt`` (``t_a path_a t_b path_b``)."""
    path = root / "associations.txt"
    listing = read_list_file(path, min_fields=4)
    for k, cols in enumerate(listing.columns):
        try:
            float(cols[1])
        except ValueError:
            raise DatasetError(
                f"{listing.name}:{listing.lines[k]}: expected 't_a path_a t_b path_b', got {' '.join(cols)!r}"
            ) from None
    entries, depth_first = _associations_columns(listing, depth_first)
    ta = listing.timestamps
    pa = [c[0] for c in listing.columns]
    pb = [c[2] for c in listing.columns]
    if depth_first:
        rgb_rel, depth_rel, times = pb, pa, np.array([float(c[1]) for c in listing.columns])
    else:
        rgb_rel, depth_rel, times = pa, pb, ta
    rgb = check_files(root, listing, rgb_rel, entries)
    depth = check_files(root, listing, depth_rel, entries)
    meta: Association = {"source": "associations.txt", "pairs": len(listing), "depth_first": depth_first}
    return np.asarray(times, dtype=np.float64), rgb, depth, meta

"""Recovery of map points whose tracks were lost (SVO's "reprojection" step, KLT flavour).

At a new keyframe, every map point of the local window that is not tracked any more is
projected into the new frame with its pose; KLT then refines the position starting from that
prediction, matching from the most recent stored keyframe image that observed the point.
A match is kept when the forward–backward check passes and it lies within the reprojection
threshold of the prediction. Recovered points gain an observation and a track again, which
ties keyframes further apart together in the windowed BA.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import distort_points, to_normalized, undistort_points
from mutualslam_cli.vo.state import Map
from mutualslam_cli.vo.tracking import klt_track


def reproject_points(
    m: Map,
    kf_imgs: dict[int, np.ndarray],
    gray: np.ndarray,
    T_cw: np.ndarray,
    tracked: np.ndarray,
    window: list[int],
    intr: Intrinsics,
    win: int,
    levels: int,
    fb_px: float,
    thr: float,
    border: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Find untracked window points in the current frame.

    Args:
        m: the map; kf_imgs: stored grey images of recent keyframes (raw pixels).
        gray: ``(H, W)`` current image; T_cw: its pose.
        tracked: ids of points tracked already; window: keyframe ids whose points are tried.
        intr: camera (with distortion); win, levels, fb_px: KLT options.
        thr: acceptance threshold in normalised units.

    Returns:
        point ids ``(R,)`` and their raw pixels ``(R, 2)`` float32 in the current frame.
    """
    K = intr.K()
    cand = set().union(*(m.kf_points[k] for k in window)) - set(tracked.tolist())
    if not cand:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
    pids = np.array(sorted(cand), np.int64)
    pc = m.Xw[pids] @ T_cw[:3, :3].T + T_cw[:3, 3]
    ok = pc[:, 2] > 1e-6
    pids, pc = pids[ok], pc[ok]
    px = pc[:, :2] / pc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    h, w = gray.shape
    inside = in_image(px, w, h, border)
    pids = pids[inside]
    src_of = np.array([max((k for k in m.obs[p] if k in kf_imgs), default=-1) for p in pids], np.int64)
    has = src_of >= 0
    return match_points(m, kf_imgs.__getitem__, gray, T_cw, pids[has], src_of[has], intr, win, levels, fb_px, thr)


def match_points(
    m: Map,
    image_of: Callable[[int], np.ndarray],
    gray: np.ndarray,
    T_cw: np.ndarray,
    pids: np.ndarray,
    source: np.ndarray,
    intr: Intrinsics,
    win: int,
    levels: int,
    fb_px: float,
    thr: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match map points ``pids`` into the current frame by KLT from keyframe ``source[j]``'s image and observation.

    Args:
        m: the map; image_of: ``image_of(kf)`` → that keyframe's ``(H, W)`` grey image (raw pixels).
        gray: ``(H, W)`` current image; T_cw: its pose (the points are predicted there).
        pids, source: ``(R,)`` point ids and the keyframe each is matched from (it observes the point).
        intr: camera (with distortion); win, levels, fb_px: KLT options.
        thr: acceptance radius around the prediction in normalised units.

    Returns:
        point ids ``(R',)`` and their raw pixels ``(R', 2)`` float32 in the current frame.
    """
    K = intr.K()
    out_ids, out_raw = [], []
    if len(pids):
        pc = m.Xw[pids] @ T_cw[:3, :3].T + T_cw[:3, 3]
        px = pc[:, :2] / pc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    for k in sorted(set(source.tolist())):
        sel = np.flatnonzero(source == k)
        src_raw = distort_points(np.array([m.obs[pids[j]][k] for j in sel]), intr).astype(np.float32)
        pred = distort_points(px[sel], intr).astype(np.float32)
        # a match must land within ``thr`` of its prediction: no full-pyramid retry
        raw, good = klt_track(image_of(k), gray, src_raw, win, levels, fb_px, pred=pred, retry=False)
        if not good.any():
            continue
        xn = to_normalized(undistort_points(raw[good], intr), K)
        xp = to_normalized(px[sel[good]], K)
        close = np.linalg.norm(xn - xp, axis=1) < thr
        out_ids.append(pids[sel[good][close]])
        out_raw.append(raw[good][close])
    if not out_ids:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
    return np.concatenate(out_ids), np.concatenate(out_raw).astype(np.float32)

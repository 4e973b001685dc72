"""Recovery of map points whose tracks were lost (SVO's "reprojection" step, KLT flavour).

At a new keyframe, every map point of the local window that is not tracked any more is
projected into the new frame with its pose; KLT then refines the position starting from that
prediction, matching from the most recent stored keyframe image that observed the point.
A match is kept when the forward–backward check passes and it lies within the reprojection
threshold of the prediction. Recovered points gain an observation and a track again, which
ties keyframes further apart together in the windowed BA.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from mutualslam_cli.geometry import to_normalized
from mutualslam_cli.map.store import Map
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import distort_points, undistort_points
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


#: Side of each warped patch in the mosaic KLT runs on (pixels; room for its window at one pyramid level above).
TILE = 48
#: Source-image offset (pixels) whose images under the relative pose give the affine warp's columns.
WARP_STEP = 4.0


def affine_warps(m: Map, pids: np.ndarray, source: np.ndarray, T_cw: np.ndarray,
                 intr: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each point's patch of its source keyframe's (raw) image goes in the current (raw) image, to first order
    (SVO 2.0's affine warp, Forster et al., T-RO 2017, §V-A: the patch taken fronto-parallel at the point's depth in
    the source view and moved by the relative pose).

    Args:
        m: the map; pids, source: ``(R,)`` points and the keyframe each is matched from; T_cw: the current pose.
        intr: camera with distortion.

    Returns:
        ``(src_raw (R, 2), cur_raw (R, 2), A (R, 2, 2))``: the observation in the source image, its predicted raw pixel
        now, and the warp's linear part (current raw pixels per source raw pixel).
    """
    K = intr.K()
    Kinv = np.linalg.inv(K)
    src_px = np.array([m.obs[p][k] for p, k in zip(pids.tolist(), source.tolist())], np.float64).reshape(-1, 2)
    src_raw = distort_points(src_px, intr)
    T_sw = m.poses_cw()[source]  # (R, 4, 4) source keyframes' world-to-camera
    Xs = np.einsum("nij,nj->ni", T_sw[:, :3, :3], m.Xw[pids]) + T_sw[:, :3, 3]
    z = Xs[:, 2:3]
    T_cs = np.einsum("ij,njk->nik", T_cw, np.linalg.inv(T_sw))  # source camera → current camera
    out = []
    for off in ((0.0, 0.0), (WARP_STEP, 0.0), (0.0, WARP_STEP)):
        px = undistort_points(src_raw + np.array(off), intr)
        ray = np.c_[px, np.ones(len(px))] @ Kinv.T
        X = ray * z  # fronto-parallel in the source view: the same depth z
        Xc = np.einsum("nij,nj->ni", T_cs[:, :3, :3], X) + T_cs[:, :3, 3]
        pc = Xc[:, :2] / np.maximum(Xc[:, 2:3], 1e-9) @ K[:2, :2].T + K[:2, 2]
        out.append(distort_points(pc, intr))
    A = np.stack([(out[1] - out[0]) / WARP_STEP, (out[2] - out[0]) / WARP_STEP], axis=2)
    return src_raw, out[0], A


def warped_klt(image_of: Callable[[int], np.ndarray], gray: np.ndarray, source: np.ndarray, src_raw: np.ndarray,
               pred: np.ndarray, A: np.ndarray, win: int, levels: int, fb_px: float) -> tuple[np.ndarray, np.ndarray]:
    """KLT of each point's patch warped into the current view (:func:`affine_warps`) towards its prediction.

    Each source patch is resampled by its affine warp into a :data:`TILE` square of a mosaic (bilinear), so the
    mosaic shows every point as the current camera would; KLT then runs from the tile centres into the current
    image, started at the predictions, with the forward–backward check. Warps that shrink or stretch a patch by
    more than 2× (or mirror it) are not matched.

    Returns:
        ``(R, 2)`` float32 raw pixels in the current image and an ``(R,)`` bool mask of good matches.
    """
    n = len(source)
    res, ok = np.zeros((n, 2), np.float32), np.zeros(n, bool)
    det = np.linalg.det(A) if n else np.zeros(0)
    usable = (det > 0.25) & (det < 4.0)
    idx = np.flatnonzero(usable)
    if not len(idx):
        return res, ok
    h, w = gray.shape
    cols, rows = w // TILE, h // TILE  # KLT wants both images of one size: mosaics of the current image's
    per = cols * rows
    c = (TILE - 1) / 2.0
    for b in range(0, len(idx), per):
        part = idx[b:b + per]
        mosaic = np.zeros_like(gray)
        centres = np.zeros((len(part), 2), np.float32)
        for t, j in enumerate(part.tolist()):
            r0, c0 = (t // cols) * TILE, (t % cols) * TILE
            M = np.c_[A[j], np.array([c, c]) - A[j] @ src_raw[j]]  # source raw → tile pixels
            mosaic[r0:r0 + TILE, c0:c0 + TILE] = cv2.warpAffine(image_of(int(source[j])), M, (TILE, TILE),
                                                                flags=cv2.INTER_LINEAR,
                                                                borderMode=cv2.BORDER_REPLICATE)
            centres[t] = (c0 + c, r0 + c)
        raw, good = klt_track(mosaic, gray, centres, win, min(levels, 2), fb_px, pred=pred[part], retry=False)
        res[part], ok[part] = raw, good
    return res, ok


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
    warp: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Match map points ``pids`` into the current frame by KLT from keyframe ``source[j]``'s image and observation
    (with ``warp``, of the source patch warped into the current view: :func:`warped_klt`).

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
    if warp and len(pids):
        src_raw, pred, A = affine_warps(m, pids, source, T_cw, intr)
        raw, good = warped_klt(image_of, gray, source, src_raw, pred.astype(np.float32), A, win, levels, fb_px)
        if good.any():
            close = np.linalg.norm(to_normalized(undistort_points(raw[good], intr), K) - to_normalized(px[good], K),
                                   axis=1) < thr
            return pids[good][close], raw[good][close].astype(np.float32)
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
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

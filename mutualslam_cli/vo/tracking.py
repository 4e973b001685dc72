"""Per-frame tracking: KLT with a forward–backward check, PnP-RANSAC, robust pose refinement.

All pose maths runs in normalised image coordinates (``K⁻¹ [u v 1]``), so a negative ``fy``
(ICL-NUIM) needs no special case; pixel thresholds are divided by the focal length.
"""

from __future__ import annotations

import cv2
import numpy as np

from mutualslam_cli.pixels import in_image

KLT_ITERS = 10
"""Lucas–Kanade iterations per pyramid level (with a motion-model start, 10 suffice)."""

KLT_EPS_PX = 0.03
"""Lucas–Kanade stops when an update moves the point less than this (pixels)."""

BACK_ITERS, BACK_EPS_PX = 5, 0.1
"""The backward check only has to land well within ``fb_threshold_px`` (1 px): 0.1 px
convergence and 5 iterations per level do that at ~18 % less KLT work than the forward pass's
settings (instruction counts under callgrind on tum_fr1_xyz)."""

PRED_LEVELS = 1
"""Pyramid levels the forward KLT pass searches around a motion-model guess (capture range
≈ 2^(L+1)·win/2 px ≈ 40 px at 21 px windows); failures are re-tracked with all levels."""

STEP_TOL = 1e-6
"""Pose refinement stops when the SE(3) increment is smaller (normalised units: ~5e-4 px at f = 500)."""

RANSAC_TRIGGER = 0.9
"""Share of matches a refined prior must explain (within 2× threshold) to skip PnP-RANSAC."""

Pyramid = np.ndarray
"""What KLT consumes per frame. OpenCV 5's Python binding no longer takes prebuilt pyramids
(``buildOpticalFlowPyramid`` output) in ``calcOpticalFlowPyrLK``, so this is the image itself."""


def build_pyramid(gray: np.ndarray, win: int, levels: int) -> Pyramid:
    """The per-frame KLT input (see :data:`Pyramid`)."""
    return np.ascontiguousarray(gray)


def _fb_pass(prev: Pyramid, cur: Pyramid, p0: np.ndarray, guess: np.ndarray | None, win: int, levels: int,
             back_levels: int, fb_threshold_px: float) -> tuple[np.ndarray, np.ndarray]:
    """One forward KLT pass from ``p0`` (``(N, 1, 2)`` float32) and its backward check."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, KLT_ITERS, KLT_EPS_PX)
    crit_back = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, BACK_ITERS, BACK_EPS_PX)
    flags = 0 if guess is None else cv2.OPTFLOW_USE_INITIAL_FLOW
    start = None if guess is None else guess.copy()  # OpenCV writes the result into the initial-flow array
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, start, winSize=(win, win), maxLevel=levels,
                                          criteria=crit, flags=flags)
    # the backward pass starts where the prior says the point came from — p1 moved back by the
    # guessed flow (no guess: p1 itself) — so it cannot inherit the forward answer; it searches the
    # full pyramid with a smaller window (a consistency check, not the measurement: ~60 % of the cost)
    wb = max(9, (3 * win // 4) | 1)
    back = None if guess is None else np.ascontiguousarray(p1 - (guess - p0), np.float32)
    back_flags = 0 if back is None else cv2.OPTFLOW_USE_INITIAL_FLOW
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, back, winSize=(wb, wb), maxLevel=back_levels,
                                           criteria=crit_back, flags=back_flags)
    h, w = cur.shape[:2]
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < fb_threshold_px)
    ok &= in_image(p1, w, h, margin=2)
    return p1, ok


def klt_track(
    prev_pyr: Pyramid,
    cur_pyr: Pyramid,
    pts: np.ndarray,
    win: int,
    levels: int,
    fb_threshold_px: float,
    pred: np.ndarray | None = None,
    retry: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Track raw pixels from the previous to the current frame (Lucas–Kanade, Bouguet's pyramid).

    A track is kept when both directions converge, it stays inside the image and the
    forward–backward round trip lands within ``fb_threshold_px`` of the start
    (Kalal et al. 2010, "Forward-Backward Error"). With guesses (``pred``) the forward pass
    searches only :data:`PRED_LEVELS` pyramid levels around them; tracks failing that cheap
    pass are tracked again over all ``levels`` from their previous position, so a poor guess
    costs time, not the track.

    Args:
        prev_pyr, cur_pyr: frames from :func:`build_pyramid`.
        pts: ``(N, 2)`` float32 pixels in the previous frame.
        win, levels: KLT window size (px) and pyramid levels.
        fb_threshold_px: maximum forward–backward error.
        pred: optional ``(N, 2)`` initial guesses in the current frame.
        retry: re-track failures of the guided pass over all levels (off when a match far
            from its guess would be rejected anyway).

    Returns:
        ``(N, 2)`` float32 pixels in the current frame and an ``(N,)`` bool mask of good tracks.
    """
    n = len(pts)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(pts, np.float32).reshape(-1, 1, 2)
    guess = None if pred is None else np.ascontiguousarray(pred, np.float32).reshape(-1, 1, 2)
    if guess is None or levels <= PRED_LEVELS:
        return _fb_pass(prev_pyr, cur_pyr, p0, guess, win, levels, levels, fb_threshold_px)
    p1, ok = _fb_pass(prev_pyr, cur_pyr, p0, guess, win, PRED_LEVELS, levels, fb_threshold_px)
    again = np.flatnonzero(~ok) if retry else np.zeros(0, int)
    if len(again):
        # the guess may be what failed: the retry starts from the previous position (no guess)
        p1r, okr = _fb_pass(prev_pyr, cur_pyr, p0[again], None, win, levels, levels, fb_threshold_px)
        p1[again], ok[again] = p1r, okr
    return p1, ok


def _exp_se3(delta: np.ndarray) -> np.ndarray:
    """Left increment ``(ρ, φ)`` → 4×4 transform (rotation by Rodrigues, translation ρ)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(delta[3:6].reshape(3, 1))[0]
    T[:3, 3] = delta[:3]
    return T


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block of a 4×4 transform back onto SO(3) (SVD), in a copy."""
    T = T.copy()
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    T[:3, :3] = R
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


def reprojection_errors(T_cw: np.ndarray, Xw: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """``(N,)`` reprojection error norms in normalised units (inf for points behind)."""
    pc = Xw @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(pc[:, :2] / z[:, None] - xn, axis=1)
    return np.where(z > 1e-6, e, np.inf)


def refine_pose(
    T_cw: np.ndarray, Xw: np.ndarray, xn: np.ndarray, huber: float, iters: int = 8
) -> np.ndarray:
    """Robust Gauss–Newton refinement of a camera pose on 3D–2D matches.

    Minimises ``Σ ρ_H(‖π(R X + t) − x‖)`` (Huber with threshold ``huber`` in normalised
    units; iteratively reweighted least squares) over a left SE(3) increment.

    Args:
        T_cw: ``(4, 4)`` initial world-to-camera transform.
        Xw: ``(N, 3)`` world points; xn: ``(N, 2)`` normalised observations.

    Returns:
        ``(4, 4)`` refined ``T_cw``.
    """
    T = orthonormalize(T_cw)
    for _ in range(iters):
        pc = Xw @ T[:3, :3].T + T[:3, 3]
        ok = pc[:, 2] > 1e-6
        if ok.sum() < 6:
            break
        if not ok.all():
            pc, obs = pc[ok], xn[ok]
        else:
            obs = xn
        iz = 1.0 / pc[:, 2]
        x, y = pc[:, 0] * iz, pc[:, 1] * iz
        rx, ry = x - obs[:, 0], y - obs[:, 1]
        e = np.sqrt(rx * rx + ry * ry)
        w = np.where(e < huber, 1.0, huber / np.maximum(e, 1e-12))
        # rows of d(x, y)/d(ρ, φ) for P' = exp(δ) P: dP = [I | −[P]×] δ
        zero = np.zeros_like(x)
        Jx = np.stack([iz, zero, -x * iz, -x * y, 1 + x * x, -y], 1)
        Jy = np.stack([zero, iz, -y * iz, -(1 + y * y), x * y, x], 1)
        Jxw, Jyw = Jx * w[:, None], Jy * w[:, None]
        H = Jxw.T @ Jx + Jyw.T @ Jy
        g = Jxw.T @ rx + Jyw.T @ ry
        try:
            delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = _exp_se3(delta) @ T
        if np.linalg.norm(delta) < STEP_TOL:
            break
    return orthonormalize(T)


def huber_cost(T_cw: np.ndarray, Xw: np.ndarray, xn: np.ndarray, k: float) -> float:
    """Total Huber cost of the reprojection errors (points behind the camera count as ``k``)."""
    e = reprojection_errors(T_cw, Xw, xn)
    e = np.where(np.isfinite(e), e, 10 * k)
    return float(np.sum(np.where(e < k, 0.5 * e * e, k * (e - 0.5 * k))))


def estimate_pose(
    Xw: np.ndarray,
    xn: np.ndarray,
    T_priors: list[np.ndarray],
    thr: float,
    seed: int = 0,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Pose from 3D–2D matches: robust refinement from priors, PnP-RANSAC when they fail.

    The priors (constant-velocity prediction, previous pose) are refined with Huber IRLS,
    best-fitting first, until one puts ``RANSAC_TRIGGER`` of the matches within twice the
    threshold; when none does, PnP-RANSAC (AP3P minimal solver, threshold ``thr``) adds a
    hypothesis. The hypothesis with the lowest Huber cost wins: side-stepping the
    translation/rotation local minima a single start can fall into.

    Args:
        Xw: ``(N, 3)`` world points; xn: ``(N, 2)`` normalised observations.
        T_priors: candidate ``T_cw`` starts (``(4, 4)`` each).
        thr: inlier threshold in normalised units.
        seed: RANSAC RNG seed (OpenCV's global RNG is reset for determinism).

    Returns:
        ``T_cw`` (``None`` on failure) and the ``(N,)`` inlier mask.
    """
    n = len(Xw)
    if n < 6:
        return None, np.zeros(n, bool)
    # the prior that already fits best is refined first; the others only when it falls short
    order = np.argsort([huber_cost(T, Xw, xn, thr) for T in T_priors], kind="stable")
    cands: list[np.ndarray] = []
    frac = 0.0
    for j in order:
        cands.append(refine_pose(T_priors[j], Xw, xn, huber=thr, iters=10))
        frac = max(frac, float(np.mean(reprojection_errors(cands[-1], Xw, xn) < 2 * thr)))
        if frac >= RANSAC_TRIGGER:
            break
    if frac < RANSAC_TRIGGER:
        cv2.setRNGSeed(seed)
        ok, rvec, tvec, ransac_inl = cv2.solvePnPRansac(
            Xw.astype(np.float64), xn.astype(np.float64), np.eye(3), None,
            iterationsCount=100, reprojectionError=thr, confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if ok and ransac_inl is not None and len(ransac_inl) >= 6:
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(rvec)[0]
            T[:3, 3] = tvec.reshape(3)
            inl = reprojection_errors(T, Xw, xn) < 2 * thr
            cands.append(refine_pose(T, Xw[inl], xn[inl], huber=thr, iters=10))
    costs = [huber_cost(T, Xw, xn, thr) for T in cands]
    best = cands[int(np.argmin(costs))]
    best = refine_pose(best, Xw, xn, huber=thr, iters=4)
    inl = reprojection_errors(best, Xw, xn) < thr
    if inl.sum() < 6:
        return None, inl
    return best, inl

"""Per-frame tracking: KLT with a forward–backward check, PnP-RANSAC, robust pose refinement.

All pose maths runs in normalised image coordinates (``K⁻¹ [u v 1]``), so a negative ``fy``
(ICL-NUIM) needs no special case; pixel thresholds are divided by the focal length.
"""

from __future__ import annotations

import cv2
import numpy as np

KLT_ITERS = 10
"""Lucas–Kanade iterations per pyramid level (with a motion-model start, 10 suffice)."""

RANSAC_TRIGGER = 0.9
"""Share of matches a refined prior must explain (within 2× threshold) to skip PnP-RANSAC."""

Pyramid = np.ndarray
"""What KLT consumes per frame. OpenCV 5's Python binding no longer takes prebuilt pyramids
(``buildOpticalFlowPyramid`` output) in ``calcOpticalFlowPyrLK``, so this is the image itself."""


def build_pyramid(gray: np.ndarray, win: int, levels: int) -> Pyramid:
    """The per-frame KLT input (see :data:`Pyramid`)."""
    return np.ascontiguousarray(gray)


def klt_track(
    prev_pyr: Pyramid,
    cur_pyr: Pyramid,
    pts: np.ndarray,
    win: int,
    levels: int,
    fb_threshold_px: float,
    pred: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track raw pixels from the previous to the current frame (Lucas–Kanade, Bouguet's pyramid).

    A track is kept when both directions converge, it stays inside the image and the
    forward–backward round trip lands within ``fb_threshold_px`` of the start
    (Kalal et al. 2010, "Forward-Backward Error").

    Args:
        prev_pyr, cur_pyr: frames from :func:`build_pyramid`.
        pts: ``(N, 2)`` float32 pixels in the previous frame.
        win, levels: KLT window size (px) and pyramid levels.
        fb_threshold_px: maximum forward–backward error.
        pred: optional ``(N, 2)`` initial guesses in the current frame.

    Returns:
        ``(N, 2)`` float32 pixels in the current frame and an ``(N,)`` bool mask of good tracks.
    """
    n = len(pts)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(pts, np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, KLT_ITERS, 0.03)
    flags = 0
    guess = None
    if pred is not None:
        guess = np.ascontiguousarray(pred, np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_pyr, cur_pyr, p0, guess, winSize=(win, win),
                                          maxLevel=levels, criteria=crit, flags=flags)
    # the backward pass starts from p1 itself (no initial flow), so it cannot inherit the answer
    # and uses a smaller window (a consistency check, not the measurement: ~½ the cost)
    wb = max(9, (2 * win // 3) | 1)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur_pyr, prev_pyr, p1, None, winSize=(wb, wb),
                                           maxLevel=levels, criteria=crit)
    h, w = cur_pyr.shape[:2]
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < fb_threshold_px)
    ok &= (p1[:, 0] >= 2) & (p1[:, 0] <= w - 3) & (p1[:, 1] >= 2) & (p1[:, 1] <= h - 3)
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
        z = pc[:, 2]
        ok = z > 1e-6
        if ok.sum() < 6:
            break
        pc, obs = pc[ok], xn[ok]
        iz = 1.0 / pc[:, 2]
        x, y = pc[:, 0] * iz, pc[:, 1] * iz
        r = np.stack([x - obs[:, 0], y - obs[:, 1]], 1)
        e = np.linalg.norm(r, axis=1)
        w = np.where(e < huber, 1.0, huber / np.maximum(e, 1e-12))
        # d(x, y)/d(ρ, φ) for P' = exp(δ) P: dP = [I | −[P]×] δ
        J = np.zeros((len(pc), 2, 6))
        J[:, 0, 0] = iz
        J[:, 0, 2] = -x * iz
        J[:, 1, 1] = iz
        J[:, 1, 2] = -y * iz
        J[:, 0, 3] = -x * y
        J[:, 0, 4] = 1 + x * x
        J[:, 0, 5] = -y
        J[:, 1, 3] = -(1 + y * y)
        J[:, 1, 4] = x * y
        J[:, 1, 5] = x
        Jw = J * w[:, None, None]
        H = np.einsum("nij,nik->jk", Jw, J)
        g = np.einsum("nij,ni->j", Jw, r)
        try:
            delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = _exp_se3(delta) @ T
        if np.linalg.norm(delta) < 1e-8:
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

    Each prior (constant-velocity prediction, previous pose) is refined with Huber IRLS;
    when the best explains fewer than ``RANSAC_TRIGGER`` of the matches within twice the
    threshold, PnP-RANSAC (AP3P minimal solver,
    threshold ``thr``) adds a hypothesis. The hypothesis with the lowest Huber cost wins:
    side-stepping the translation/rotation local minima a single start can fall into.

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
    cands = [refine_pose(T, Xw, xn, huber=thr, iters=10) for T in T_priors]
    frac = max(np.mean(reprojection_errors(T, Xw, xn) < 2 * thr) for T in cands)
    if frac < RANSAC_TRIGGER:
        cv2.setRNGSeed(seed)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            Xw.astype(np.float64), xn.astype(np.float64), np.eye(3), None,
            iterationsCount=100, reprojectionError=thr, confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if ok and inl is not None and len(inl) >= 6:
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

"""Two-view monocular initialisation: homography or essential matrix, median depth 1.

Model selection follows ORB-SLAM (Mur-Artal et al. 2015, §IV): both models are fitted
with RANSAC, each is scored with the truncated chi-square score
``S_M = Σ_i Σ_views (Γ − d²/σ²)`` over correspondences with ``d²/σ² < T_M``
(``T_H = 5.99``, ``T_F = 3.84``, ``Γ = 5.99``), and the homography is chosen when
``R_H = S_H / (S_H + S_F) > 0.45`` (planar or low-parallax scenes).
All coordinates are normalised image coordinates.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from mutualslam_cli.vo.local_ba import BAProblem, solve

log = logging.getLogger(__name__)

RATIO_H = 0.45
"""R_H above which the homography is used (ORB-SLAM: 0.45)."""

AMBIGUITY = 0.75
"""A homography decomposition is rejected when the runner-up triangulates more than this
fraction of the winner's points (ORB-SLAM's ReconstructH test)."""

BA_ITERS = 10
"""LM iterations of the two-view refinement after model selection."""

MIN_PARALLAX_DEG = 1.0
"""Median triangulation angle below which the baseline is too short to initialise."""

PLAUSIBLE_COST_RATIO = 1.3
"""A motion hypothesis whose refined two-view cost is within this factor of the chosen one's
still explains the data; see :func:`_rival_too_short`."""


@dataclass
class InitResult:
    """A successful two-view initialisation.

    Attributes:
        method: ``"homography"`` or ``"essential"``.
        T_10: ``(4, 4)`` transform from view-0 to view-1 camera coordinates (scaled).
        points0: ``(M, 3)`` triangulated points in view-0 coordinates, median depth 1.
        index: ``(M,)`` indices of the correspondences the points belong to.
        ratio_h: ``R_H`` of the model selection.
        parallax_deg: ``(M,)`` triangulation angle of each point.
    """

    method: str
    T_10: np.ndarray
    points0: np.ndarray
    index: np.ndarray
    ratio_h: float
    parallax_deg: np.ndarray


def _score_h(H: np.ndarray, x0: np.ndarray, x1: np.ndarray, sigma: float) -> float:
    def transfer(M: np.ndarray, a: np.ndarray) -> np.ndarray:
        p = np.c_[a, np.ones(len(a))] @ M.T
        return p[:, :2] / p[:, 2:3]

    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return 0.0
    d1 = np.sum((transfer(H, x0) - x1) ** 2, 1) / sigma ** 2
    d0 = np.sum((transfer(Hi, x1) - x0) ** 2, 1) / sigma ** 2
    s = np.where(d1 < 5.99, 5.99 - d1, 0) + np.where(d0 < 5.99, 5.99 - d0, 0)
    return float(np.sum(np.nan_to_num(s)))


def _score_e(E: np.ndarray, x0: np.ndarray, x1: np.ndarray, sigma: float) -> float:
    h0, h1 = np.c_[x0, np.ones(len(x0))], np.c_[x1, np.ones(len(x1))]
    l1 = h0 @ E.T  # epipolar lines in view 1
    l0 = h1 @ E  # epipolar lines in view 0
    num = np.sum(h1 * l1, 1) ** 2
    d1 = num / (l1[:, 0] ** 2 + l1[:, 1] ** 2 + 1e-30) / sigma ** 2
    d0 = num / (l0[:, 0] ** 2 + l0[:, 1] ** 2 + 1e-30) / sigma ** 2
    s = np.where(d1 < 3.84, 5.99 - d1, 0) + np.where(d0 < 3.84, 5.99 - d0, 0)
    return float(np.sum(s))


def triangulate(x0: np.ndarray, x1: np.ndarray, T_10: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation, ``(N, 3)`` points in view-0 coordinates."""
    P0 = np.eye(3, 4)
    P1 = T_10[:3, :]
    X = cv2.triangulatePoints(P0, P1, x0.T.astype(np.float64), x1.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


def _check(x0: np.ndarray, x1: np.ndarray, T_10: np.ndarray,
           thr: float) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Points, good mask and median parallax (deg) of a motion hypothesis, and each point's parallax (deg)."""
    X = triangulate(x0, x1, T_10)
    X1 = X @ T_10[:3, :3].T + T_10[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        e0 = np.linalg.norm(X[:, :2] / X[:, 2:3] - x0, axis=1)
        e1 = np.linalg.norm(X1[:, :2] / X1[:, 2:3] - x1, axis=1)
        c1 = -T_10[:3, :3].T @ T_10[:3, 3]
        r0 = X / np.linalg.norm(X, axis=1, keepdims=True)
        r1 = (X - c1) / np.linalg.norm(X - c1, axis=1, keepdims=True)
        par = np.degrees(np.arccos(np.clip(np.sum(r0 * r1, 1), -1, 1)))
    good = (X[:, 2] > 0) & (X1[:, 2] > 0) & (e0 < 2 * thr) & (e1 < 2 * thr) & np.isfinite(par)
    med = float(np.median(par[good])) if good.any() else 0.0
    return X, good, med, par


def _two_view_ba(x0: np.ndarray, x1: np.ndarray, T_10: np.ndarray, X: np.ndarray, good: np.ndarray,
                 thr: float) -> np.ndarray:
    """Joint LM refinement of the second pose and the points' inverse depths (first view fixed)."""
    idx = np.flatnonzero(good & (X[:, 2] > 0))
    if len(idx) < 8:
        return T_10
    n = len(idx)
    prob = BAProblem(np.stack([np.eye(4), T_10]), np.array([False, True]), np.zeros(n, int),
                     np.c_[x0[idx], np.ones(n)], 1.0 / X[idx, 2], np.arange(n), np.ones(n, int), x1[idx])
    T_new, _, _ = solve(prob, thr, iters=BA_ITERS)
    return T_new[1]


def _cost(x0: np.ndarray, x1: np.ndarray, T_10: np.ndarray, X: np.ndarray, thr: float) -> float:
    """Mean two-view reprojection error of all correspondences, each capped at ``3 thr``
    (points behind a camera count as the cap), in units of ``thr``."""
    X1 = X @ T_10[:3, :3].T + T_10[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(X[:, :2] / X[:, 2:3] - x0, axis=1) + np.linalg.norm(X1[:, :2] / X1[:, 2:3] - x1, axis=1)
    e = np.where(np.isfinite(e) & (X[:, 2] > 0) & (X1[:, 2] > 0), e, 3 * thr)
    return float(np.mean(np.minimum(e, 3 * thr)) / thr)


def _hypotheses(x0: np.ndarray, x1: np.ndarray, H: np.ndarray | None, E: np.ndarray | None,
                me: np.ndarray | None) -> list[np.ndarray]:
    """Every motion the RANSAC models propose: each essential-matrix solution (cheirality by
    ``recoverPose``) and each homography decomposition, as unit-baseline ``T_10``."""
    out = []
    if E is not None and me is not None:
        inl = me.reshape(-1).astype(bool)
        for k in range(0, E.shape[0] - 2, 3):
            _, R, t, _ = cv2.recoverPose(E[k:k + 3], x0[inl], x1[inl], np.eye(3))
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t.reshape(3)
            out.append(T)
    if H is not None:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        for R, t in zip(Rs, ts):
            if np.linalg.norm(t) > 1e-9:
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t.reshape(3) / np.linalg.norm(t)
                out.append(T)
    return out


def _rival_too_short(x0: np.ndarray, x1: np.ndarray, thr: float, T_best: np.ndarray,
                     hyps: list[np.ndarray], min_points: int) -> bool:
    """Whether a rival interpretation of the two views fits nearly as well but sees too little
    baseline to be ruled out.

    Short baselines with forward motion are ambiguous (the rotation–translation ambiguity of
    small fields of view): on tum_fr1_xyz a lateral-motion solution with 3.5° parallax fits
    the first 4 frames *better* than the true forward motion with 0.6° parallax, and only
    loses after ~8 frames. So every hypothesis is refined (two-view BA); when one whose cost is
    within :data:`PLAUSIBLE_COST_RATIO` of the chosen motion's has a median parallax below
    :data:`MIN_PARALLAX_DEG`, the views cannot decide yet and initialisation waits.
    """
    X, _good, _, _ = _check(x0, x1, T_best, thr)
    c_best = _cost(x0, x1, T_best, X, thr)
    for T in hyps:
        Xh, gh, _, _ = _check(x0, x1, T, thr)
        if gh.sum() < min_points:
            continue
        T = _two_view_ba(x0, x1, T, Xh, gh, thr)
        Xh, gh, par, _ = _check(x0, x1, T, thr)
        if (gh.sum() >= min_points and par < MIN_PARALLAX_DEG
                and _cost(x0, x1, T, Xh, thr) <= PLAUSIBLE_COST_RATIO * c_best):
            return True
    return False


def initialize(x0: np.ndarray, x1: np.ndarray, thr: float, min_points: int = 30,
               seed: int = 0) -> InitResult | None:
    """Relative pose and structure from two views, or ``None`` when not (yet) possible.

    Args:
        x0, x1: ``(N, 2)`` corresponding normalised coordinates in the two views.
        thr: inlier threshold in normalised units (pixel threshold / focal length).
        min_points: fewest triangulated points accepted.
        seed: RANSAC seed (OpenCV's RNG is reset for determinism).

    Returns:
        :class:`InitResult` with the map scaled to median depth 1 in view 0.
    """
    n = len(x0)
    if n < max(min_points, 8):
        return None
    x0 = np.asarray(x0, np.float64)
    x1 = np.asarray(x1, np.float64)
    cv2.setRNGSeed(seed)
    H, _mh = cv2.findHomography(x0, x1, cv2.RANSAC, thr, maxIters=500, confidence=0.999)
    cv2.setRNGSeed(seed)
    E, me = cv2.findEssentialMat(x0, x1, np.eye(3), cv2.RANSAC, 0.999, thr)
    sh = _score_h(H, x0, x1, thr) if H is not None else 0.0
    se = _score_e(E[:3], x0, x1, thr) if E is not None and E.shape[0] >= 3 else 0.0
    if sh + se <= 0:
        return None
    ratio = sh / (sh + se)
    if E is None or E.shape[0] < 3:
        return None
    if ratio > RATIO_H:
        cands = []
        _, Rs, ts, ns = cv2.decomposeHomographyMat(H, np.eye(3))
        for R, t, nrm in zip(Rs, ts, ns):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t.reshape(3)
            if np.linalg.norm(T[:3, 3]) < 1e-9:
                continue
            X, good, par, par_pt = _check(x0, x1, T, thr)
            cands.append((int(good.sum()), abs(float(nrm.reshape(3)[2])), "homography", T, good, X, par, par_pt))
        if not cands:
            return None
        cands.sort(key=lambda c: -c[0])
        top = [c for c in cands if c[0] > AMBIGUITY * cands[0][0]]
        if len(top) > 1:
            # two views cannot tell the plane decompositions apart (collinear motion keeps them
            # ambiguous). Only when every contender already sees enough parallax (else the
            # baseline is too short and the wrong one may look best), take the plane that faces
            # the first camera most (PTAM/SVO-style tie-break).
            if min(c[6] for c in top) < MIN_PARALLAX_DEG:
                log.debug("init rejected: ambiguous homography, parallax %s deg (R_H %.2f)",
                          [round(c[6], 2) for c in top], ratio)
                return None
            cands = sorted(top, key=lambda c: -c[1])
    else:
        inl = me.reshape(-1).astype(bool)
        _, R, t, _ = cv2.recoverPose(E[:3], x0[inl], x1[inl], np.eye(3))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t.reshape(3)
        X, good, par, par_pt = _check(x0, x1, T, thr)
        cands = [(int(good.sum()), 0.0, "essential", T, good, X, par, par_pt)]
    _, _, method, T, good, X, par, par_pt = cands[0]
    T = _two_view_ba(x0, x1, T, X, good, thr)  # RANSAC models are not refined: do it jointly
    X, good, par, par_pt = _check(x0, x1, T, thr)
    if good.sum() < min_points or par < MIN_PARALLAX_DEG:
        log.debug("init rejected: %d points, parallax %.2f deg (%s, R_H %.2f)", good.sum(), par, method, ratio)
        return None
    if _rival_too_short(x0, x1, thr, T, _hypotheses(x0, x1, H, E, me), min_points):
        log.debug("init rejected: a rival motion fits nearly as well with parallax < %.1f deg", MIN_PARALLAX_DEG)
        return None
    scale = 1.0 / float(np.median(X[good, 2]))  # median depth 1 (SVO/ORB-SLAM convention)
    T = T.copy()
    T[:3, 3] *= scale
    return InitResult(method, T, X[good] * scale, np.flatnonzero(good), ratio, par_pt[good])

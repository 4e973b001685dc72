"""Windowed geometric bundle adjustment over the last ``core_kfs`` keyframes.

Unknowns: an SE(3) left increment per free keyframe and one inverse depth per point along
its fixed host ray (the host pixel is a measurement, so the point's parametrisation matches
``MapPoints``: host, pixel, inverse depth). Residuals: normalised reprojection errors of every
non-host observation, robustified with the Huber loss (iteratively reweighted). Solver:
Levenberg–Marquardt with analytic Jacobians and the Schur complement on the (diagonal)
inverse-depth block (Triggs et al. 2000, "Bundle adjustment — a modern synthesis", §6).
The oldest window keyframe and every older keyframe observing a window point stay fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mutualslam_cli.geometry import left_update
from mutualslam_cli.map.assemble import WindowStats


@dataclass
class BAProblem:
    """Inputs of one windowed BA.

    Attributes:
        T_cw: ``(K, 4, 4)`` world-to-camera of every involved keyframe.
        free: ``(K,)`` bool, poses being optimised.
        host: ``(P,)`` index into ``T_cw`` of each point's host.
        ray: ``(P, 3)`` host bearing ``[x, y, 1]`` (normalised coordinates).
        rho: ``(P,)`` inverse depth (``z``) in the host.
        obs_pt, obs_kf: ``(M,)`` point and keyframe index of each non-host observation.
        obs_xn: ``(M, 2)`` observed normalised coordinates.
        prior_rho: ``(P,)`` prior inverse depth of each point (NaN: none), or ``None`` (``vo.scale_prior``).
        prior_w: weight of a prior's log-depth residual: ``(log ρ − log ρ₀) · prior_w`` is added as a residual in
            normalised units (a log-depth error of ``1 / prior_w`` normalised units' worth of reprojection error).
    """

    T_cw: np.ndarray
    free: np.ndarray
    host: np.ndarray
    ray: np.ndarray
    rho: np.ndarray
    obs_pt: np.ndarray
    obs_kf: np.ndarray
    obs_xn: np.ndarray
    prior_rho: np.ndarray | None = None
    prior_w: float = 0.0


def _prior(prob: BAProblem, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scale prior's residuals ``(P,)`` (0 without a prior), their derivatives by ρ and the mask of points
    that have one: ``r = prior_w · (log ρ − log ρ₀)``, ``dr/dρ = prior_w / ρ``."""
    if prob.prior_rho is None or not np.any(np.asarray(prob.prior_w) > 0):
        z = np.zeros(len(rho))
        return z, z, np.zeros(len(rho), bool)
    has = np.isfinite(prob.prior_rho) & (prob.prior_rho > 0)
    r = np.where(has, prob.prior_w * (np.log(rho) - np.log(np.where(has, prob.prior_rho, 1.0))), 0.0)
    return r, np.where(has, prob.prior_w / rho, 0.0), has


def residuals(prob: BAProblem, T: np.ndarray, rho: np.ndarray, jac: bool = False) -> tuple[np.ndarray, ...]:
    """Reprojection residuals ``(M, 2)`` and, with ``jac``, the Jacobians.

    Returns:
        ``r`` and, if ``jac``: ``J_t`` ``(M, 2, 6)`` (target pose), ``J_h`` ``(M, 2, 6)``
        (host pose), ``J_p`` ``(M, 2)`` (inverse depth), and the ``(M,)`` bool "in front" mask.
    """
    h, k, p = prob.host[prob.obs_pt], prob.obs_kf, prob.obs_pt
    # host-to-target transforms for every keyframe pair (K is small), gathered per observation
    R_all, t_all = T[:, :3, :3], T[:, :3, 3]
    R_pair = np.einsum("aij,bkj->abik", R_all, R_all)  # R_a R_bᵀ
    t_pair = t_all[:, None, :] - np.einsum("abij,bj->abi", R_pair, t_all)
    R, t = R_pair[k, h], t_pair[k, h]
    ray = prob.ray[p]
    Xh = ray / rho[p, None]
    Xc = np.einsum("nij,nj->ni", R, Xh) + t
    front = Xc[:, 2] > 1e-6
    z = np.where(front, Xc[:, 2], 1e-6)
    iz = 1.0 / z
    u, v = Xc[:, 0] * iz, Xc[:, 1] * iz
    r = np.stack([u, v], 1) - prob.obs_xn
    if not jac:
        return r, front
    n = len(z)
    # target (left increment): dXc = [I | −[Xc]×] δ  →  rows of d(u, v)/dδ
    J_t = np.empty((n, 2, 6))
    J_t[:, 0, 0], J_t[:, 0, 1], J_t[:, 0, 2] = iz, 0.0, -u * iz
    J_t[:, 0, 3], J_t[:, 0, 4], J_t[:, 0, 5] = -u * v, 1 + u * u, -v
    J_t[:, 1, 0], J_t[:, 1, 1], J_t[:, 1, 2] = 0.0, iz, -v * iz
    J_t[:, 1, 3], J_t[:, 1, 4], J_t[:, 1, 5] = -(1 + v * v), u * v, u
    # G = dπ/dXc · R_pair: the projection's derivative with respect to the host-frame point
    G = np.empty((n, 2, 3))
    G[:, 0] = iz[:, None] * (R[:, 0] - u[:, None] * R[:, 2])
    G[:, 1] = iz[:, None] * (R[:, 1] - v[:, None] * R[:, 2])
    # host increment: Xw = T_h⁻¹ exp(−δ) Xh → dXh = −[I | −[Xh]×] δ; gᵀ[X]× = (g × X)ᵀ
    J_h = np.empty((n, 2, 6))
    J_h[:, :, :3] = -G
    J_h[:, :, 3:] = np.cross(G, Xh[:, None, :])
    J_p = np.einsum("nij,nj->ni", G, -ray / (rho[p, None] ** 2))
    return r, J_t, J_h, J_p, front


def _robust_cost(r: np.ndarray, front: np.ndarray, huber: float, r_prior: np.ndarray | None = None) -> float:
    e = np.linalg.norm(r, axis=1)
    c = np.where(e < huber, 0.5 * e * e, huber * (e - 0.5 * huber))
    prior = 0.0 if r_prior is None else 0.5 * float(np.sum(r_prior * r_prior))
    return float(np.sum(np.where(front, c, 0.5 * huber * huber))) + prior


def _apply(T: np.ndarray, fi: np.ndarray, dc: np.ndarray) -> np.ndarray:
    return left_update(T, fi, dc.reshape(-1, 6))


def solve(prob: BAProblem, huber: float, iters: int = 6) -> tuple[np.ndarray, np.ndarray, WindowStats]:
    """Levenberg–Marquardt on the window with a Schur complement on the points.

    Args:
        prob: the problem (see :class:`BAProblem`).
        huber: Huber threshold in normalised units.
        iters: LM iterations (accepted or rejected steps).

    Returns:
        New ``T_cw`` ``(K, 4, 4)``, new ``rho`` ``(P,)`` and stats (initial/final robust cost).
    """
    T, rho = prob.T_cw.copy(), prob.rho.copy()
    fi = np.flatnonzero(prob.free)
    F, P, M = len(fi), len(rho), len(prob.obs_pt)
    if M == 0:
        return T, rho, {"cost0": 0.0, "cost": 0.0, "iters": 0}
    col = -np.ones(len(T), int)
    col[fi] = np.arange(F)
    ct, ch = col[prob.obs_kf], col[prob.host[prob.obs_pt]]
    p = prob.obs_pt
    r, front = residuals(prob, T, rho)
    cost = cost0 = _robust_cost(r, front, huber, _prior(prob, rho)[0])
    lam = 1e-4
    for _ in range(iters):
        r, Jt, Jh, Jp, front = residuals(prob, T, rho, jac=True)
        e = np.linalg.norm(r, axis=1)
        w = np.where(e < huber, 1.0, huber / np.maximum(e, 1e-12)) * front  # IRLS Huber weights
        # camera Jacobian of every residual over the free poses (dense: F ≤ core_kfs), then
        # H_cc = Jcᵀ W Jc, H_cp and the point blocks accumulated per point with bincount
        Jc: np.ndarray = np.zeros((M, 2, F, 6))
        for Ja, ca in ((Jt, ct), (Jh, ch)):
            ma = np.flatnonzero(ca >= 0)
            Jc[ma, :, ca[ma], :] = Ja[ma]  # host ≠ target: the two never share a block
        Jc = Jc.reshape(M, 2, 6 * F)
        Jcw = Jc * w[:, None, None]
        Jc2, Jcw2 = Jc.reshape(2 * M, 6 * F), Jcw.reshape(2 * M, 6 * F)
        Hcc = Jcw2.T @ Jc2
        bc = Jcw2.T @ r.reshape(-1)
        v = np.einsum("nij,ni->nj", Jcw, Jp)  # (M, 6F): each residual's share of H_cp
        Hcp = np.stack([np.bincount(p, weights=v[:, j], minlength=P) for j in range(6 * F)]) \
            if F else np.zeros((0, P))
        Hpp = np.bincount(p, weights=w * np.sum(Jp * Jp, 1), minlength=P)
        bp = np.bincount(p, weights=w * np.sum(Jp * r, 1), minlength=P)
        r_pr, J_pr, _ = _prior(prob, rho)  # the scale prior: one more residual per point, on its depth alone
        Hpp, bp = Hpp + J_pr * J_pr, bp + J_pr * r_pr
        accepted = False
        for _try in range(4):
            Hd = Hpp * (1 + lam) + 1e-12
            Hc = Hcc + lam * np.diag(np.diag(Hcc)) + 1e-12 * np.eye(6 * F)
            S = Hc - (Hcp / Hd) @ Hcp.T
            g = bc - Hcp @ (bp / Hd)
            try:
                dc = -np.linalg.solve(S, g) if F else np.zeros(0)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dp = -(bp + Hcp.T @ dc) / Hd
            T_new = _apply(T, fi, dc)
            rho_new = np.maximum(rho + dp, 1e-4)
            r_new, f_new = residuals(prob, T_new, rho_new)
            c_new = _robust_cost(r_new, f_new, huber, _prior(prob, rho_new)[0])
            if c_new < cost:
                T, rho, cost = T_new, rho_new, c_new
                lam = max(lam / 10, 1e-7)
                accepted = True
                break
            lam *= 10
        if not accepted:
            break
    return T, rho, {"cost0": cost0, "cost": cost}

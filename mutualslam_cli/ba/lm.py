"""Levenberg–Marquardt for the photometric BA at one image resolution.

Each iteration builds the Gauss–Newton normal equations with IRLS weights of the Huber loss
(Alismail et al. 2016, "Photometric Bundle Adjustment for Vision-Based SLAM"), adds the
monocular scale prior ``w_s (‖c_1 − c_0‖ − s_0)²`` (keyframe 0 fixed as the gauge; paper
§III-C runs this BA after culling), and tries damped steps through the Schur complement
(:mod:`mutualslam_cli.ba.schur`) until the robust cost decreases. Pose increments are left
increments on ``T_cw`` (:func:`mutualslam_cli.geometry.left_update`), as in
:mod:`mutualslam_cli.vo.local_ba`.
"""

from __future__ import annotations

import logging

import numpy as np

from mutualslam_cli.ba.problem import NP
from mutualslam_cli.ba.residuals import PatchData, huber_cost, residuals
from mutualslam_cli.ba.schur import NormalEquations
from mutualslam_cli.geometry import left_update

log = logging.getLogger(__name__)


def normal_equations(d: PatchData, T: np.ndarray, ab: np.ndarray, rho: np.ndarray,
                     huber_delta: float, res: tuple | None = None) -> NormalEquations:
    """IRLS-weighted normal equations at the current state (Huber weights); ``res`` may pass
    the output of ``residuals(..., jac=True)`` at this state."""
    P = len(rho)
    r, valid, _, Jc, Jp = residuals(d, T, ab, rho, jac=True) if res is None else res
    a = np.abs(r)
    w = np.where(a < huber_delta, 1.0, huber_delta / np.maximum(a, 1e-12)) * valid  # IRLS
    Jw = Jc * w[..., None]
    bblk = np.einsum("msi,ms->mi", Jw, r)
    hcp = np.einsum("msi,ms->mi", Jw, Jp)  # (M, 16) column of H_cp per observation
    A = np.stack([np.bincount(d.p, hcp[:, i], minlength=P) for i in range(NP)], 1)  # host slots
    Hpp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, Jp), minlength=P)
    bp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, r), minlength=P)
    Hcc, bc = d.st.camera_system(Jc, Jw, bblk)
    return NormalEquations(d.st, Hcc, bc, A, hcp[:, NP:], Hpp, bp)


def centre_gauge(T: np.ndarray) -> np.ndarray:
    return -T[:3, :3].T @ T[:3, 3]


def apply_step(T, ab, rho, dc, dp, fidx):
    ab = ab.copy()
    d = dc.reshape(-1, NP)[fidx]
    T = left_update(T, fidx, d[:, :6])
    ab[fidx] += d[:, 6:]
    return T, ab, np.maximum(rho + dp, 1e-6)


def solve_level(d: PatchData, T, ab, rho, fidx, cols, s0, iterations, huber_delta, scale_weight,
                 lambda0, max_tries, callback, it_offset=0):
    """LM iterations at one resolution; returns ``(T, ab, rho, costs, iterations, accepted)``.
    ``s0`` is the scale-prior baseline (from the input state, shared by all levels)."""
    nk = d.nk
    k1 = int(fidx[0]) if len(fidx) else -1  # scale prior on the first free keyframe
    c0 = centre_gauge(T[0])
    ws = scale_weight / s0**2 if s0 > 1e-9 else 0.0

    def total(T_, res_):
        e = np.linalg.norm(centre_gauge(T_[k1]) - c0) - s0 if ws else 0.0
        return huber_cost(res_[0], res_[2], d.host_ok, huber_delta) + ws * e * e

    res = residuals(d, T, ab, rho, jac=iterations > 0)  # trial states keep Jacobians for reuse
    cost = total(T, res)
    costs, accepted, lam, it = [cost], 0, lambda0, 0
    for it in range(1, iterations + 1):
        ne = normal_equations(d, T, ab, rho, huber_delta, res)
        if ws:  # scale prior: ∂c_k/∂ρ_k = −R_kᵀ under the left increment, ∂c_k/∂φ_k = 0
            c1 = centre_gauge(T[k1])
            n = (c1 - c0) / np.linalg.norm(c1 - c0)
            Js = np.zeros(nk * NP)
            Js[k1 * NP:k1 * NP + 3] = -T[k1, :3, :3] @ n
            es = np.linalg.norm(c1 - c0) - s0
            ne.Hcc += 2 * ws * np.outer(Js, Js)
            ne.bc += 2 * ws * Js * es
        ok = False
        for _ in range(max_tries):
            try:
                dc, dp = ne.step(lam, cols)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T2, ab2, rho2 = apply_step(T, ab, rho, dc, dp, fidx)
            res2 = residuals(d, T2, ab2, rho2, jac=True)
            c_new = total(T2, res2)
            if c_new < cost:
                T, ab, rho, cost, res = T2, ab2, rho2, c_new, res2
                lam, ok = max(lam / 10, 1e-7), True
                accepted += 1
                break
            lam *= 10
        costs.append(cost)
        log.debug("photometric BA it %d cost %.6g lambda %.1e accepted %s", it, cost, lam, ok)
        if callback is not None:
            callback(it_offset + it, cost)
        if not ok:
            break
    return T, ab, rho, costs, it, accepted

"""Levenberg–Marquardt for the photometric BA at one image resolution and one set of active blocks.

Each iteration builds the Gauss–Newton normal equations of the active blocks with IRLS weights
(Huber × the host pixel's gradient weight, :mod:`mutualslam_cli.ba.residuals`; Alismail et al.
2016), adds the scale anchor, and tries damped steps through the Schur complement
(:mod:`mutualslam_cli.ba.schur`) until the robust cost decreases: within one call the cost never
increases across accepted steps. Given the cameras the cost is a sum over points, so a trial step
keeps the inverse depth of each point whose own cost it raised (:func:`_trial`): one point in a
narrow basin no longer forces up the damping of every unknown (on the unit tests' scene LM stalled
at the first iteration of its second round without this). Pose increments are left increments on ``T_cw``
(:func:`mutualslam_cli.geometry.left_update`), as in :mod:`mutualslam_cli.vo.local_ba`.

**Scale anchor.** Keyframe 0 fixes the position and orientation of the map; its unit would drift
freely in a monocular BA. It is held by the prior ``w_s (s − s_0)²`` on the *extent* of the keyframe
trajectory, ``s = sqrt(mean_k ‖c_k − c̄‖²)`` over every keyframe of the problem (``s_0``: its value
at the input), with ``w_s·s_0²`` the cost of a relative scale error of 1. A prior on the first
baseline alone — one short distance between two keyframes, often the noisiest — let the scale of a
whole map follow that pair.
"""

from __future__ import annotations

import logging

import numpy as np

from mutualslam_cli.ba.problem import NP
from mutualslam_cli.ba.residuals import PatchData, point_costs, residuals, robust_cost
from mutualslam_cli.ba.schur import NormalEquations
from mutualslam_cli.geometry import left_update

log = logging.getLogger(__name__)


def normal_equations(d: PatchData, T: np.ndarray, ab: np.ndarray, rho: np.ndarray, huber_delta: float,
                     active: np.ndarray | None = None, res: tuple | None = None) -> NormalEquations:
    """IRLS-weighted normal equations of the active blocks (``None``: all) at the current state;
    ``res`` may pass the output of ``residuals(..., jac=True)`` at this state."""
    P = len(rho)
    r, valid, _, Jc, Jp = residuals(d, T, ab, rho, jac=True) if res is None else res
    a = np.abs(r)
    w = np.where(a < huber_delta, 1.0, huber_delta / np.maximum(a, 1e-12)) * valid * d.wg[d.p]  # IRLS
    if active is not None:
        w = w * active[:, None]
    Jw = Jc * w[..., None]
    bblk = np.einsum("msi,ms->mi", Jw, r)
    hcp = np.einsum("msi,ms->mi", Jw, Jp)  # (M, 16) column of H_cp per observation
    A = np.stack([np.bincount(d.p, hcp[:, i], minlength=P) for i in range(NP)], 1)  # host slots
    Hpp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, Jp), minlength=P)
    bp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, r), minlength=P)
    Hcc, bc = d.st.camera_system(Jc, Jw, bblk)
    return NormalEquations(d.st, Hcc, bc, A, hcp[:, NP:], Hpp, bp)


def centres(T: np.ndarray) -> np.ndarray:
    """Camera centres ``(K, 3)`` of world-to-camera poses ``(K, 4, 4)``: ``c = −Rᵀt``."""
    return -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])


def extent(T: np.ndarray, anchor: np.ndarray | None = None) -> float:
    """The scale anchor's ``s``: RMS distance of the camera centres (of the ``anchor`` keyframes) from their mean."""
    c = centres(T if anchor is None else T[anchor])
    return float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1))))


def apply_step(T, ab, rho, dc, dp, fidx):
    ab = ab.copy()
    d = dc.reshape(-1, NP)[fidx]
    T = left_update(T, fidx, d[:, :6])
    ab[fidx] += d[:, 6:]
    return T, ab, np.maximum(rho + dp, 1e-6)


def _scale_prior(T: np.ndarray, fidx: np.ndarray, s0: float, ws: float,
                 anchor: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Gradient row ``J`` ``(8K,)`` and residual ``e = s − s0`` of the scale anchor over the ``anchor`` keyframes
    (default: all). Under the left increment ``∂c_k/∂ρ_k = −R_k``ᵀ, ``∂c_k/∂φ_k = 0``, and
    ``∂s/∂c_k = (c_k − c̄)/(A·s)`` for the ``A`` anchor keyframes (0 for the others)."""
    a = np.ones(len(T), bool) if anchor is None else np.asarray(anchor, bool)
    c = centres(T)
    s = extent(T, a)
    J = np.zeros(len(T) * NP)
    if s > 1e-12:
        g = np.zeros_like(c)
        g[a] = (c[a] - c[a].mean(0)) / (a.sum() * s)
        for k in fidx:
            J[k * NP:k * NP + 3] = -T[k, :3, :3] @ g[k]
    return J, s - s0


def _trial(d: PatchData, T, ab, rho, res, dc, dp, fidx, act, huber_delta, total):
    """The state after the step ``(dc, dp)`` and its residuals and cost. Given the cameras, the cost is a
    sum over points, each depending on its own inverse depth only: a point whose share of the cost
    rose with its step keeps its inverse depth instead (and its residuals at the new cameras). One
    point in a narrow basin (a sharp edge, a sub-pixel shift away) then no longer forces the damping
    of every unknown up; the cost returned is still the exact cost of the state returned."""
    T2, ab2, rho2 = apply_step(T, ab, rho, dc, dp, fidx)
    res2 = residuals(d, T2, ab2, rho2, jac=True)
    P = len(rho)
    worse = point_costs(d, res2[0], res2[2], act, huber_delta, P) > point_costs(d, res[0], res[2], act, huber_delta, P)
    if worse.any():
        rho3 = np.where(worse, rho, rho2)
        res3 = residuals(d, T2, ab2, rho3, jac=True)
        pick = worse[d.p]
        res2 = tuple(np.where(pick.reshape((-1,) + (1,) * (a.ndim - 1)), b, a) for a, b in zip(res2, res3))
        rho2 = rho3
    return T2, ab2, rho2, res2, total(T2, res2)


def solve_level(d: PatchData, T, ab, rho, fidx, cols, s0, iterations, huber_delta, scale_weight,
                lambda0, max_tries, callback, it_offset=0, active=None, anchor=None):
    """LM iterations at one resolution over the ``active`` blocks (``None``: all); returns
    ``(T, ab, rho, costs, iterations, accepted)``. ``s0``: the scale anchor's target (from the
    input state, shared by all levels and rounds), the extent of the ``anchor`` keyframes (``None``: all)."""
    ws = scale_weight / s0 ** 2 if s0 > 1e-9 and len(fidx) else 0.0
    act = np.ones(len(d.p), bool) if active is None else active

    def total(T_, res_):
        e = _scale_prior(T_, fidx, s0, ws, anchor)[1] if ws else 0.0
        return robust_cost(d, res_[0], res_[2], act, huber_delta) + ws * e * e

    res = residuals(d, T, ab, rho, jac=iterations > 0)  # trial states keep Jacobians for reuse
    cost = total(T, res)
    costs, accepted, lam, it = [cost], 0, lambda0, 0
    for it in range(1, iterations + 1):
        ne = normal_equations(d, T, ab, rho, huber_delta, act, res)
        if ws:
            Js, es = _scale_prior(T, fidx, s0, ws, anchor)
            ne.Hcc += 2 * ws * np.outer(Js, Js)
            ne.bc += 2 * ws * Js * es
        ok = False
        for _ in range(max_tries):
            try:
                dc, dp = ne.step(lam, cols)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T2, ab2, rho2, res2, c_new = _trial(d, T, ab, rho, res, dc, dp, fidx, act, huber_delta, total)
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

"""Levenberg–Marquardt for the photometric BA at one image resolution and one set of active blocks.

Each iteration builds the Gauss–Newton normal equations of the active blocks with IRLS weights
(Huber × the host pixel's gradient weight, :mod:`mutualslam_cli.backend.ba.residuals`; Alismail et al.
2016), adds the scale anchor, and tries damped steps through the Schur complement
(:mod:`mutualslam_cli.backend.ba.schur`) until the robust cost decreases: within one call the cost never
increases across accepted steps. Given the cameras the cost is a sum over points, so a trial step
keeps the inverse depth of each point whose own cost it raised (:meth:`_Level.trial`): one point in a
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
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from mutualslam_cli.backend.ba.problem import NP
from mutualslam_cli.backend.ba.residuals import PatchData, Residuals, point_costs, residuals, robust_cost
from mutualslam_cli.backend.ba.schur import NormalEquations
from mutualslam_cli.geometry import left_update

log = logging.getLogger(__name__)


class BAState(NamedTuple):
    """The unknowns of one BA: ``T`` ``(K, 4, 4)`` world-to-camera poses, ``ab`` ``(K, 2)`` affine brightness
    ``(a, b)``, ``rho`` ``(P,)`` inverse depths (1 / map units) in the host keyframes."""

    T: np.ndarray
    ab: np.ndarray
    rho: np.ndarray


@dataclass(frozen=True)
class LMSettings:
    """How LM runs: ``huber_delta`` (intensity in [0, 1]), ``scale_weight`` (the scale anchor's cost of a relative
    error of 1), the initial damping ``lambda0``, ``max_tries`` damping increases per iteration, and ``callback``
    ``(iteration, cost)`` after each iteration."""

    huber_delta: float
    scale_weight: float
    lambda0: float
    max_tries: int
    callback: Callable[[int, float], None] | None = None


@dataclass(frozen=True)
class Gauge:
    """What moves in one round: ``fidx`` the free keyframes, ``cols`` their unknowns' columns (8 per keyframe,
    or the 6 of the pose without the affine brightness), ``s0`` the scale anchor's target extent over the
    ``anchor`` keyframes (``None``: all)."""

    fidx: np.ndarray
    cols: np.ndarray
    s0: float
    anchor: np.ndarray | None = None


@dataclass(frozen=True)
class LevelResult:
    """One call of :func:`solve_level`: the final ``state``, the cost after each iteration (``costs[0]``: at the
    start), the ``iterations`` run and the steps ``accepted``."""

    state: BAState
    costs: list[float]
    iterations: int
    accepted: int


def normal_equations(d: PatchData, T: np.ndarray, ab: np.ndarray, rho: np.ndarray, huber_delta: float,
                     active: np.ndarray | None = None, res: Residuals | None = None) -> NormalEquations:
    """IRLS-weighted normal equations of the active blocks (``None``: all) at the current state;
    ``res`` may pass the output of ``residuals(..., jac=True)`` at this state."""
    P = len(rho)
    res = residuals(d, T, ab, rho, jac=True) if res is None else res
    r, valid, Jc, Jp = res.values, res.valid, res.d_cameras, res.d_inv_depth
    assert Jc is not None, "normal_equations needs residuals(..., jac=True)"
    assert Jp is not None, "normal_equations needs residuals(..., jac=True)"
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
    Hcc, bc = d.structure.camera_system(Jc, Jw, bblk)
    return NormalEquations(d.structure, Hcc, bc, A, hcp[:, NP:], Hpp, bp)


def centres(T: np.ndarray) -> np.ndarray:
    """Camera centres ``(K, 3)`` of world-to-camera poses ``(K, 4, 4)``: ``c = −Rᵀt``."""
    return -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])


def extent(T: np.ndarray, anchor: np.ndarray | None = None) -> float:
    """The scale anchor's ``s``: RMS distance of the camera centres (of the ``anchor`` keyframes) from their mean."""
    c = centres(T if anchor is None else T[anchor])
    return float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1))))


def apply_step(T: np.ndarray, ab: np.ndarray, rho: np.ndarray, dc: np.ndarray, dp: np.ndarray,
               fidx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LM step ``(dc (8K,), dp (P,))`` applied to the free keyframes ``fidx``: new poses ``T`` ``(K, 4, 4)``,
    affine brightness ``ab`` ``(K, 2)`` and inverse depths ``rho`` ``(P,)`` (kept ≥ 1e-6)."""
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


class _Level:
    """The cost of one call of :func:`solve_level` (active blocks, free keyframes, scale anchor) and its trial steps."""

    def __init__(self, d: PatchData, active: np.ndarray, gauge: Gauge, lm: LMSettings):
        self.d, self.act, self.gauge, self.lm = d, active, gauge, lm
        s0 = gauge.s0
        self.ws = lm.scale_weight / s0 ** 2 if s0 > 1e-9 and len(gauge.fidx) else 0.0

    def prior(self, T: np.ndarray) -> tuple[np.ndarray, float]:
        return _scale_prior(T, self.gauge.fidx, self.gauge.s0, self.ws, self.gauge.anchor)

    def total(self, T: np.ndarray, res: Residuals) -> float:
        e = self.prior(T)[1] if self.ws else 0.0
        return robust_cost(self.d, res.values, res.counted, self.act, self.lm.huber_delta) + self.ws * e * e

    def trial(self, st: BAState, res: Residuals, dc: np.ndarray,
              dp: np.ndarray) -> tuple[BAState, Residuals, float]:
        """The state after the step ``(dc, dp)``, its residuals and cost. Given the cameras, the cost is a
        sum over points, each depending on its own inverse depth only: a point whose share of the cost
        rose with its step keeps its inverse depth instead (and its residuals at the new cameras). One
        point in a narrow basin (a sharp edge, a sub-pixel shift away) then no longer forces the damping
        of every unknown up; the cost returned is still the exact cost of the state returned."""
        d, hd = self.d, self.lm.huber_delta
        new = BAState(*apply_step(*st, dc, dp, self.gauge.fidx))
        res2 = residuals(d, *new, jac=True)
        P = len(st.rho)
        worse = (point_costs(d, res2.values, res2.counted, self.act, hd, P)
                 > point_costs(d, res.values, res.counted, self.act, hd, P))
        if worse.any():
            new = new._replace(rho=np.where(worse, st.rho, new.rho))
            res3 = residuals(d, *new, jac=True)
            res2 = res2.where(worse[d.p], res3)  # the blocks of the points kept: their residuals at the new cameras
        return new, res2, self.total(new.T, res2)


def solve_level(d: PatchData, state: BAState, gauge: Gauge, iterations: int, lm: LMSettings,
                active: np.ndarray | None = None, it_offset: int = 0) -> LevelResult:
    """LM iterations at one resolution over the ``active`` blocks (``None``: all), the keyframes of ``gauge``
    free; ``it_offset``: iterations already run (for ``lm.callback``)."""
    level = _Level(d, np.ones(len(d.p), bool) if active is None else active, gauge, lm)
    res = residuals(d, *state, jac=iterations > 0)  # trial states keep Jacobians for reuse
    cost = level.total(state.T, res)
    costs, accepted, lam, it = [cost], 0, lm.lambda0, 0
    for it in range(1, iterations + 1):
        ne = normal_equations(d, *state, lm.huber_delta, level.act, res)
        if level.ws:
            Js, es = level.prior(state.T)
            ne.Hcc += 2 * level.ws * np.outer(Js, Js)
            ne.bc += 2 * level.ws * Js * es
        ok = False
        for _ in range(lm.max_tries):
            try:
                dc, dp = ne.step(lam, gauge.cols)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            new, res_new, c_new = level.trial(state, res, dc, dp)
            if c_new < cost:
                state, cost, res = new, c_new, res_new
                lam, ok = max(lam / 10, 1e-7), True
                accepted += 1
                break
            lam *= 10
        costs.append(cost)
        log.debug("photometric BA it %d cost %.6g lambda %.1e accepted %s", it, cost, lam, ok)
        if lm.callback is not None:
            lm.callback(it_offset + it, cost)
        if not ok:
            break
    return LevelResult(state, costs, it, accepted)

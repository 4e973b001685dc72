"""Global photometric bundle adjustment (DSO-style direct BA over keyframes).

Unknowns: per free keyframe an SE(3) left increment ``(ρ, φ)`` on ``T_cw`` plus the affine
brightness ``(a, b)`` (8 values); per point its inverse depth in the host keyframe. One
residual per (point, target keyframe) pair and per pixel of a ``patch × patch`` pattern around
the host pixel, all sharing the point's inverse depth (fronto-parallel patch), with DSO's affine
brightness model (Engel et al. 2018, "Direct Sparse Odometry", eq. 4):

    r = (I_t(π(T_t T_h⁻¹ π⁻¹(p + δ, ρ))) − b_t) − exp(a_t − a_h) · (I_h(p + δ) − b_h)

robustified with the Huber loss through IRLS weights (Alismail et al. 2016, "Photometric
Bundle Adjustment for Vision-Based SLAM"). Solver: Levenberg–Marquardt with the Schur
complement on the diagonal inverse-depth block (Triggs et al. 2000, §6); the reduced camera
system (8 unknowns per free keyframe) is solved densely. Gauge: keyframe 0 fixed; the
monocular scale is held by the prior ``w_s (‖c_1 − c_0‖ − s_0)²`` (paper §III-C runs this BA
after culling). Conventions follow :mod:`mutualslam_cli.vo.local_ba` (left increments on
``T_cw``, :func:`mutualslam_cli.geometry.left_update`).

Image derivatives are those of the bilinear interpolant itself (not interpolated central-
difference gradient images): the Jacobians are then exact for the cost being minimised, which
the LM acceptance test compares. Residuals beyond the 2-px margin get weight 0 but keep their
(clamped) value in the cost, so the cost is continuous and a step is never rejected only
because one patch crossed the margin.

Modules, each importing only those listed before it:
:mod:`~mutualslam_cli.ba.problem` (inputs, outputs, validation),
:mod:`~mutualslam_cli.ba.schur` (sparsity, reduced camera system, LM step),
:mod:`~mutualslam_cli.ba.residuals` (residuals, Jacobians, robust cost),
:mod:`~mutualslam_cli.ba.lm` (LM iterations at one resolution),
:mod:`~mutualslam_cli.ba.pyramid` (image pyramid, coarse-to-fine levels) and this module
(:func:`solve`, the entry point).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from mutualslam_cli.ba import pyramid
from mutualslam_cli.ba.lm import apply_step, centre_gauge, normal_equations, solve_level
from mutualslam_cli.ba.problem import NP, PhotoBAProblem, PhotoBAResult, validate
from mutualslam_cli.ba.residuals import PatchData, residuals
from mutualslam_cli.errors import ConfigError

# the parts the BA tests reach as ``photometric.<name>`` stay importable from here
__all__ = ["PhotoBAProblem", "PhotoBAResult", "PatchData", "apply_step", "normal_equations", "residuals", "solve",
           "validate"]


def solve(prob: PhotoBAProblem, iterations: int = 10, huber_delta: float = 0.1, patch: int = 3,
          max_targets: int = 5, scale_weight: float = 1e4, margin: float = 2.0,
          lambda0: float = 1e-3, max_tries: int = 4, affine: bool = True,
          callback: Callable[[int, float], None] | None = None, levels: int = 1,
          coarse_iterations: int = 5) -> PhotoBAResult:
    """Levenberg–Marquardt photometric BA with a Schur complement on the inverse depths,
    optionally coarse-to-fine over an image pyramid (:mod:`mutualslam_cli.ba.pyramid`).

    Args:
        prob: the problem (see :class:`PhotoBAProblem`).
        iterations: LM iterations at full resolution (each tries at most ``max_tries`` dampings).
        huber_delta: Huber threshold in intensity units.
        patch: side of the square residual pattern, pixels of each level.
        max_targets: largest allowed number of targets per point.
        scale_weight: ``w_s · s_0²`` of the scale prior ``w_s (‖c_1 − c_0‖ − s_0)²``, i.e. the
            cost of a relative scale error of 1 (``s_0`` from the input, shared by all levels).
        margin: pixels (of each level) at the border where a projection is invalid.
        lambda0: initial LM damping (reset at each level).
        max_tries: damping increases per iteration before giving up (ends that level).
        affine: optimise the affine brightness ``(a, b)`` (else keep it fixed).
        callback: ``callback(iteration, cost)`` after each iteration (iterations count across
            levels; the cost is the current level's).
        levels: pyramid levels. 1 (default): full resolution only, bit-identical to the solver
            before the pyramid existed. ``L > 1``: ``coarse_iterations`` at each level
            ``L−1 … 1`` (resolution / 2^level), then ``iterations`` at full resolution. An
            iteration costs about the same at every level (it scales with points, not pixels).
        coarse_iterations: LM iterations at each coarse level.

    Returns:
        :class:`PhotoBAResult`. Within each level the robust cost never increases across
        accepted steps; costs of different levels are not comparable. ``stats``: ``cost0`` and
        ``cost`` full-resolution costs of the input and final states (``cost <= cost0``),
        ``costs`` the full-resolution stage's sequence, ``levels`` per level (coarsest first)
        ``{level, shape, costs, iterations, accepted}``, ``iterations``/``accepted`` totals.
    """
    t0 = time.perf_counter()
    free = validate(prob, max_targets)
    if patch < 1 or patch % 2 == 0:
        raise ConfigError(f"solve: patch must be a positive odd integer, got {patch}")
    if coarse_iterations < 0:
        raise ConfigError(f"solve: coarse_iterations must be >= 0, got {coarse_iterations}")
    stack = pyramid.build(np.asarray(prob.images), levels)
    state = tuple(np.asarray(x, float).copy() for x in (prob.T_cw, prob.affine, prob.inv_depth))
    fidx = np.flatnonzero(free)
    cols = (fidx[:, None] * NP + np.arange(NP if affine else 6)).ravel()
    k1 = int(fidx[0]) if len(fidx) else -1
    T = state[0]
    s0 = float(np.linalg.norm(centre_gauge(T[k1]) - centre_gauge(T[0]))) if k1 > 0 else 0.0

    def run(d, T_, ab_, rho_, n, offset):
        return solve_level(d, T_, ab_, rho_, fidx, cols, s0, n, huber_delta, scale_weight,
                            lambda0, max_tries, callback, offset)

    def make_data(p):
        return PatchData(p, patch, margin)

    per_level, n_it, n_acc, cost0 = [], 0, 0, None
    if levels > 1:
        state, per_level, n_it, n_acc, d, cost0 = pyramid.coarse_to_fine(
            prob, stack, state, coarse_iterations, make_data, run)
    else:
        d = make_data(prob)
    T, ab, rho, costs, it, acc = run(d, *state, iterations, n_it)
    costs = [float(c) for c in costs]
    per_level.append({"level": 0, "shape": stack[0].shape[1:], "costs": costs,
                      "iterations": it, "accepted": acc})
    stats = {"cost0": float(costs[0] if cost0 is None else cost0), "cost": costs[-1],
             "costs": costs, "iterations": n_it + it, "accepted": n_acc + acc,
             "levels": per_level, "seconds": time.perf_counter() - t0}
    return PhotoBAResult(T, ab, rho, stats)

"""Global photometric bundle adjustment (DSO-style direct BA over keyframes).

Unknowns: per free keyframe an SE(3) left increment ``(ρ, φ)`` on ``T_cw`` plus the affine
brightness ``(a, b)`` (8 values); per point its inverse depth in the host keyframe. One *block* of
residuals per (point, target keyframe) pair, one residual per pixel of a pattern around the host pixel
(the paper's 3×3 patch by default, or DSO's eight pixels), with DSO's affine brightness model (Engel et al. 2018,
"Direct Sparse Odometry", eq. 4), weighted and robustified as DSO does (Huber on grey levels, a
gradient-dependent weight, blocks above an energy threshold out: :mod:`mutualslam_cli.backend.ba.residuals`).
Solver: Levenberg–Marquardt with the Schur complement on the diagonal inverse-depth block (Triggs et
al. 2000, §6); the reduced camera system (8 unknowns per free keyframe) is solved densely. Gauge:
keyframe 0 fixed; the monocular scale held by a prior on the keyframe trajectory's extent
(:mod:`mutualslam_cli.backend.ba.lm`).

**Levels and rounds.** Optionally coarse-to-fine over an image pyramid (each coarse level one round
of ``coarse_iterations``); at full resolution ``rounds`` rounds share ``iterations``. Each round starts
by deciding which blocks take part (:func:`~mutualslam_cli.backend.ba.residuals.classify`, at the round's
start state) and keeps that set: within a round the robust cost never increases across accepted
steps. A point whose blocks are mostly outliers (more than ``drop_ratio`` of them, or all) takes no
part in the round (its inlier blocks neither: the point itself is in doubt), and at the end it is
*dropped*: no map point of this scene the images agree on (``stats["dropped"]``). A free keyframe
with fewer than ``min_blocks`` active blocks in a round is held fixed in it: nearly unconstrained,
LM's damped step moved one such keyframe of a 161-keyframe synthetic sequence by half a metre.

Modules, each importing only those listed before it:
:mod:`~mutualslam_cli.backend.ba.problem` (inputs, outputs, validation),
:mod:`~mutualslam_cli.backend.ba.schur` (sparsity, reduced camera system, LM step),
:mod:`~mutualslam_cli.backend.ba.residuals` (residuals, Jacobians, weights, block energies, robust cost),
:mod:`~mutualslam_cli.backend.ba.lm` (LM iterations at one resolution, the scale anchor),
:mod:`~mutualslam_cli.backend.ba.pyramid` (image pyramid, problems per level) and this module
(:func:`solve`, the entry point).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from mutualslam_cli.backend.ba import pyramid
from mutualslam_cli.backend.ba.lm import BAState, Gauge, LMSettings, apply_step, extent, normal_equations, solve_level
from mutualslam_cli.backend.ba.problem import NP, PhotoBAProblem, PhotoBAResult, validate
from mutualslam_cli.backend.ba.residuals import GRADIENT_C, SQUARE3, PatchData, classify, residuals, robust_cost
from mutualslam_cli.errors import ConfigError

log = logging.getLogger(__name__)

# the parts the BA tests reach as ``photometric.<name>`` stay importable from here
__all__ = [
    "PatchData",
    "PhotoBAProblem",
    "PhotoBAResult",
    "apply_step",
    "normal_equations",
    "residuals",
    "solve",
    "validate",
]

#: Huber threshold and outlier threshold of a residual, intensity in [0, 1] (5 and 12 grey levels; DSO: 9 and 12).
HUBER_DELTA, OUTLIER_DELTA = 5.0 / 255.0, 12.0 / 255.0
#: Fewest active blocks (as host or target) that let a keyframe's pose move in a round.
MIN_BLOCKS = 30


def _mostly_outliers(d: PatchData, inlier: np.ndarray, n_points: int, drop_ratio: float) -> np.ndarray:
    """``(P,)`` points with blocks of which more than ``drop_ratio`` (or all) are not ``inlier``."""
    n_blocks = np.bincount(d.p, minlength=n_points)
    n_inlier = np.bincount(d.p, inlier.astype(float), minlength=n_points)
    return (n_blocks > 0) & ((n_inlier == 0) | (n_blocks - n_inlier > drop_ratio * n_blocks))


def _blocks_per_keyframe(d: PatchData, active: np.ndarray) -> np.ndarray:
    """``(K,)`` active blocks per keyframe, as host or as target."""
    return np.bincount(d.h[active], minlength=d.nk) + np.bincount(d.t[active], minlength=d.nk)


class _Rounds:
    """The rounds of one :func:`solve`, in order: each decides its active blocks and held keyframes, runs LM
    (:func:`~mutualslam_cli.backend.ba.lm.solve_level`) and keeps its record in :attr:`records`."""

    def __init__(self, free: np.ndarray, affine: bool, min_blocks: int, drop_ratio: float, outlier_delta: float,
                 s0: float, anchor: np.ndarray | None, lm: LMSettings):
        self.free, self.affine, self.min_blocks, self.drop_ratio = free, affine, min_blocks, drop_ratio
        self.outlier_delta, self.s0, self.anchor, self.lm = outlier_delta, s0, anchor, lm
        self.records: list[dict] = []

    @property
    def iterations(self) -> int:
        """LM iterations run so far, over every round."""
        return sum(r["iterations"] for r in self.records)

    def run(self, d: PatchData, st: BAState, n: int, level: int) -> BAState:
        """One round of ``n`` LM iterations on ``d`` (at pyramid ``level``) from ``st``; returns the state after."""
        res = residuals(d, *st)
        active = classify(d, res.values, res.valid, res.counted, self.lm.huber_delta, self.outlier_delta)
        active &= ~_mostly_outliers(d, active, len(st.rho), self.drop_ratio)[d.p]  # the rest of a dropped point too
        fidx = np.flatnonzero(self.free & (_blocks_per_keyframe(d, active) >= self.min_blocks))
        cols = (fidx[:, None] * NP + np.arange(NP if self.affine else 6)).ravel()
        r = solve_level(d, st, Gauge(fidx, cols, self.s0, self.anchor), n, self.lm, active, self.iterations)
        self.records.append({"level": level, "shape": (d.H, d.W), "costs": [float(c) for c in r.costs],
                             "iterations": r.iterations, "accepted": r.accepted, "active": int(active.sum()),
                             "held": int(self.free.sum() - len(fidx))})
        return r.state


def solve(prob: PhotoBAProblem, iterations: int = 10, huber_delta: float = HUBER_DELTA,
          outlier_delta: float = OUTLIER_DELTA, pattern: np.ndarray = SQUARE3, max_targets: int = 5,
          scale_weight: float = 1e4, margin: float = 2.0, lambda0: float = 1e-3, max_tries: int = 4,
          affine: bool = True, callback: Callable[[int, float], None] | None = None, levels: int = 1,
          coarse_iterations: int = 5, rounds: int = 2, grad_c: float = GRADIENT_C,
          drop_ratio: float = 0.5, min_blocks: int = MIN_BLOCKS) -> PhotoBAResult:
    """Levenberg–Marquardt photometric BA with a Schur complement on the inverse depths, coarse-to-fine
    over an image pyramid, with DSO's outlier handling (module docstring).

    Args:
        prob: the problem (see :class:`PhotoBAProblem`); host pixels should lie on integer positions
            at full resolution (the host intensities are then exact samples, not interpolations).
        iterations: LM iterations at full resolution, shared by its ``rounds``.
        huber_delta, outlier_delta: Huber threshold and per-pixel outlier threshold, intensity in [0, 1].
        pattern: ``(S, 2)`` residual pattern offsets, pixels of each level.
        max_targets: largest allowed number of targets per point.
        scale_weight: cost of a relative error of 1 in the scale anchor (:mod:`mutualslam_cli.backend.ba.lm`).
        margin: pixels (of each level) at the border where a projection is invalid.
        lambda0: initial LM damping (reset at each round).
        max_tries: damping increases per iteration before giving up (ends that round).
        affine: optimise the affine brightness ``(a, b)`` (else keep it fixed).
        callback: ``callback(iteration, cost)`` after each iteration (counted across levels).
        levels: pyramid levels (1: full resolution only).
        coarse_iterations: LM iterations at each coarse level.
        rounds: rounds of outlier classification at full resolution.
        grad_c: ``c`` of the gradient weight (``inf``: all weights 1).
        drop_ratio: a point with more than this share of its blocks outliers (or all) is dropped.
        min_blocks: a free keyframe with fewer active blocks (as host or target) in a round is held
            fixed in that round (module docstring).

    Returns:
        :class:`PhotoBAResult`; ``stats``: ``cost0``/``cost`` the full-resolution cost of the input
        and final states over the final active blocks, ``rounds`` per round ``{level, shape, costs,
        iterations, accepted, active}`` (coarsest first; within each the cost never increases),
        ``iterations``, ``accepted``, ``n_blocks``, ``n_outlier_blocks`` (at the end), ``n_dropped``.
    """
    t0 = time.perf_counter()
    free = validate(prob, max_targets)
    if rounds < 1 or coarse_iterations < 0 or not 0 <= drop_ratio <= 1:
        raise ConfigError(f"solve: expected rounds >= 1, coarse_iterations >= 0, drop_ratio in [0, 1]; got {rounds}, "
                          f"{coarse_iterations}, {drop_ratio}")
    stack = pyramid.build(np.asarray(prob.images), levels)
    state0 = BAState(*(np.asarray(x, float).copy() for x in (prob.T_cw, prob.affine, prob.inv_depth)))
    state = state0
    rounds_ = _Rounds(free, affine, min_blocks, drop_ratio, outlier_delta, extent(state0.T, prob.anchor), prob.anchor,
                      LMSettings(huber_delta, scale_weight, lambda0, max_tries, callback))
    for lv in range(len(stack) - 1, 0, -1):  # coarse levels, coarsest first
        d = PatchData(pyramid.level_problem(prob, stack[lv], lv, *state), pattern, margin, grad_c)
        state = rounds_.run(d, state, coarse_iterations, lv)
    d0 = PatchData(prob, pattern, margin, grad_c)
    if levels > 1:  # the coarse levels are other cost functions: keep their result only if full resolution agrees
        res_in, res_coarse = residuals(d0, *state0), residuals(d0, *state)
        act0 = classify(d0, res_in.values, res_in.valid, res_in.counted, huber_delta, outlier_delta)
        before = robust_cost(d0, res_in.values, res_in.counted, act0, huber_delta)
        if robust_cost(d0, res_coarse.values, res_coarse.counted, act0, huber_delta) > before:
            log.warning("photometric BA: the coarse levels raised the full-resolution cost; restarting from the input")
            state = state0
    share = [iterations // rounds + (1 if k < iterations % rounds else 0) for k in range(rounds)]
    for n in share:
        state = rounds_.run(d0, state, n, 0)
    per_round = rounds_.records
    T, ab, rho = state
    res_in, res_out = residuals(d0, *state0), residuals(d0, *state)
    final = classify(d0, res_out.values, res_out.valid, res_out.counted, huber_delta, outlier_delta)
    dropped = _mostly_outliers(d0, final, len(rho), drop_ratio)
    final &= ~dropped[d0.p]
    stats = {"cost0": robust_cost(d0, res_in.values, res_in.counted, final, huber_delta),
             "cost": robust_cost(d0, res_out.values, res_out.counted, final, huber_delta),
             "costs": per_round[-1]["costs"], "rounds": per_round, "iterations": rounds_.iterations,
             "accepted": sum(r["accepted"] for r in per_round),
             "n_blocks": len(final), "n_outlier_blocks": int((~final).sum()), "n_dropped": int(dropped.sum()),
             "dropped": dropped, "seconds": time.perf_counter() - t0}
    return PhotoBAResult(T, ab, rho, stats)

"""Image pyramid for coarse-to-fine photometric BA.

Each level halves the resolution by 2×2 box averaging, so the centre of coarse pixel ``x`` is
the centre of fine pixels ``2x`` and ``2x + 1``, i.e. fine coordinate ``2x + 0.5``. Pixel
coordinates and principal points therefore map as ``c → (c + 0.5) / 2 − 0.5`` and focal lengths
as ``f → f / 2`` (the same half-pixel convention as DSO's pyramid, Engel et al. 2018 §II-C;
coarse-to-fine direct alignment follows Lucas & Kanade / Baker & Matthews 2004).
Odd trailing rows/columns are dropped before averaging (this does not move pixel centres).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np

from mutualslam_cli.ba.problem import PhotoBAProblem
from mutualslam_cli.errors import ConfigError

log = logging.getLogger(__name__)


def downsample(images: np.ndarray) -> np.ndarray:
    """Halve ``(K, H, W)`` images by 2×2 averaging → ``(K, H // 2, W // 2)`` float32."""
    K, H, W = images.shape
    h, w = H // 2, W // 2
    im = np.asarray(images[:, :2 * h, :2 * w], np.float32)
    return im.reshape(K, h, 2, w, 2).mean(axis=(2, 4), dtype=np.float32)


def scale_intrinsics(K: np.ndarray, level: int) -> np.ndarray:
    """Intrinsics ``(3, 3)`` of pyramid ``level`` (0 = full resolution)."""
    s = 2.0 ** -level
    Kl = np.asarray(K, float).copy()
    Kl[0, 0] *= s
    Kl[1, 1] *= s
    Kl[0, 2] = (Kl[0, 2] + 0.5) * s - 0.5
    Kl[1, 2] = (Kl[1, 2] + 0.5) * s - 0.5
    return Kl


def build(images: np.ndarray, levels: int, min_size: int = 16) -> list[np.ndarray]:
    """Image stacks of levels ``0 .. levels−1`` (level 0 = ``images`` itself).

    Raises:
        ConfigError: ``levels < 1`` or the coarsest level would be smaller than ``min_size``
            pixels on a side.
    """
    if levels < 1:
        raise ConfigError(f"solve: levels must be >= 1, got {levels}")
    H, W = images.shape[1:]
    if min(H, W) >> (levels - 1) < min_size:
        raise ConfigError(f"solve: levels={levels} makes the coarsest image of a {W}x{H} input "
                          f"smaller than {min_size} px; use fewer levels")
    out = [images]
    for _ in range(levels - 1):
        out.append(downsample(out[-1]))
    return out


def level_problem(prob: PhotoBAProblem, images: np.ndarray, level: int, T_cw: np.ndarray,
                  affine: np.ndarray, inv_depth: np.ndarray) -> PhotoBAProblem:
    """Copy of ``prob`` at pyramid ``level`` with the given images ``(K, H_l, W_l)`` and state:
    intrinsics and host pixels ``(P, 2)`` rescaled; poses, affine, inverse depths unchanged
    (they do not depend on the resolution)."""
    s = 2.0 ** -level
    pixel = (np.asarray(prob.pixel, float) + 0.5) * s - 0.5
    return dataclasses.replace(prob, images=images, K=scale_intrinsics(prob.K, level), T_cw=T_cw,
                               affine=affine, inv_depth=inv_depth, pixel=pixel)


def coarse_to_fine(prob: PhotoBAProblem, stack: list[np.ndarray], state: tuple,
                   coarse_iterations: int, make_data: Callable, run_level: Callable):
    """Run the levels coarser than full resolution, coarsest first, and guard the result.

    Args:
        prob: the full-resolution problem.
        stack: images per level from :func:`build` (``stack[0]`` full resolution).
        state: ``(T_cw (K, 4, 4), affine (K, 2), inv_depth (P,))`` at the input.
        coarse_iterations: LM iterations per coarse level.
        make_data: ``make_data(problem) → data`` for :func:`run_level`.
        run_level: ``run_level(data, T, ab, rho, iterations, it_offset)`` →
            ``(T, ab, rho, costs, iterations, accepted)`` (one LM stage at one resolution).

    Returns:
        ``(state, per_level, iterations, accepted, data0, cost0)``: the state where the
        full-resolution stage starts, per coarse level ``{level, shape, costs, iterations,
        accepted}``, total iterations/accepted steps, the full-resolution data and the
        full-resolution cost of the input. Costs of different levels are different functions;
        if the coarse state has a higher full-resolution cost than the input, the input state is
        returned instead (so the full-resolution cost never ends above the input's).
    """
    T, ab, rho = state
    per_level, n_it, n_acc = [], 0, 0
    for lv in range(len(stack) - 1, 0, -1):
        d = make_data(level_problem(prob, stack[lv], lv, T, ab, rho))
        T, ab, rho, costs, it, acc = run_level(d, T, ab, rho, coarse_iterations, n_it)
        per_level.append({"level": lv, "shape": stack[lv].shape[1:],
                          "costs": [float(c) for c in costs], "iterations": it, "accepted": acc})
        n_it, n_acc = n_it + it, n_acc + acc
    d0 = make_data(prob)
    cost0 = run_level(d0, *state, 0, n_it)[3][0]
    if run_level(d0, T, ab, rho, 0, n_it)[3][0] > cost0:
        log.warning("photometric BA: coarse levels increased the full-resolution cost; "
                    "restarting full resolution from the input state")
        T, ab, rho = (x.copy() for x in state)
    return (T, ab, rho), per_level, n_it, n_acc, d0, cost0

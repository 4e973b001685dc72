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

import numpy as np

from mutualslam_cli.backend.ba.problem import PhotoBAProblem
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

"""Grid feature detection for new keyframes (SVO's one-corner-per-cell policy).

Shi–Tomasi corners (minimum eigenvalue of the structure tensor, Shi & Tomasi 1994) are
scored over the whole image once; every ``grid_size`` cell keeps its strongest response,
cells already holding a tracked feature are skipped, and the ``max_fts`` strongest cells win.
"""

from __future__ import annotations

import cv2
import numpy as np

MIN_EIG = 1e-4
"""Minimum-eigenvalue response (OpenCV's scale for uint8 input) below which a cell is textureless."""


def detect_grid(
    gray: np.ndarray,
    grid_size: int,
    max_fts: int,
    occupied_px: np.ndarray | None = None,
    border: int = 8,
) -> np.ndarray:
    """Detect at most one corner per grid cell.

    Args:
        gray: ``(H, W)`` uint8 image (raw camera pixels).
        grid_size: cell size in pixels.
        max_fts: maximum number of features in total (existing ones included).
        occupied_px: ``(M, 2)`` pixels of features already tracked; their cells are skipped.
        border: pixels at the image border where no corner is taken.

    Returns:
        ``(N, 2)`` float32 pixels ``(u, v)``, strongest first, ``N ≤ max_fts − M``.
    """
    h, w = gray.shape
    n_occ = 0 if occupied_px is None else len(occupied_px)
    budget = max_fts - n_occ
    if budget <= 0:
        return np.zeros((0, 2), np.float32)
    resp = cv2.cornerMinEigenVal(gray, blockSize=3, ksize=3)
    resp[:border] = 0
    resp[h - border:] = 0
    resp[:, :border] = 0
    resp[:, w - border:] = 0
    gh, gw = h // grid_size, w // grid_size
    cells = resp[: gh * grid_size, : gw * grid_size].reshape(gh, grid_size, gw, grid_size)
    cells = cells.transpose(0, 2, 1, 3).reshape(gh, gw, grid_size * grid_size)
    arg = np.argmax(cells, axis=2)
    best = np.take_along_axis(cells, arg[..., None], axis=2)[..., 0]
    mask = best > MIN_EIG
    if occupied_px is not None and len(occupied_px):
        occ = np.asarray(occupied_px, np.float64)
        ci = np.clip((occ[:, 1] // grid_size).astype(int), 0, gh - 1)
        cj = np.clip((occ[:, 0] // grid_size).astype(int), 0, gw - 1)
        mask[ci, cj] = False
    ii, jj = np.nonzero(mask)
    if len(ii) == 0:
        return np.zeros((0, 2), np.float32)
    score = best[ii, jj]
    order = np.argsort(-score, kind="stable")[:budget]
    ii, jj, a = ii[order], jj[order], arg[ii[order], jj[order]]
    v = ii * grid_size + a // grid_size
    u = jj * grid_size + a % grid_size
    return np.stack([u, v], axis=1).astype(np.float32)

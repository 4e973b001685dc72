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


#: Largest Hamming distance of an ORB match (of 256 bits) and Lowe's ratio of best to second best.
ORB_MAX_HAMMING, ORB_RATIO = 64, 0.8


def orb_features(gray: np.ndarray, n: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """ORB keypoints and descriptors of a grey image (Rublee et al. 2011): ``(N, 2)`` float64 raw
    pixels and ``(N, 32)`` uint8 descriptors (``N`` may be 0)."""
    kps, desc = cv2.ORB.create(nfeatures=n).detectAndCompute(gray, None)
    if desc is None:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
    return np.array([k.pt for k in kps], np.float64), desc


def orb_matches(desc_a: np.ndarray, desc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i, j)`` of ORB descriptors ``a[i]`` ↔ ``b[j]`` that pass the Hamming bound and Lowe's
    ratio test (``(0,)`` arrays when there are none)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc_a, desc_b, k=2)
    good = [(p[0].queryIdx, p[0].trainIdx) for p in pairs
            if len(p) == 2 and p[0].distance <= ORB_MAX_HAMMING and p[0].distance < ORB_RATIO * p[1].distance]
    if not good:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = np.array(good, np.int64).T
    return i, j

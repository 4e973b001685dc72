"""Trajectory alignment for the ATE: least-squares Sim(3) / SE(3) of two position sets.

Umeyama, "Least-Squares Estimation of Transformation Parameters Between Two Point Patterns",
IEEE PAMI 13(4), 1991: the similarity (monocular, Sim(3)) or rigid (SE(3)) transform that
moves the estimated positions onto the reference positions (Sturm et al., IROS 2012, §VI-A).
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.errors import ConfigError, GeometryError
from mutualslam_cli.types import check_shape

__all__ = ["ALIGNMENTS", "GeometryError", "align_positions", "check_alignment", "sim3_matrix", "umeyama"]

ALIGNMENTS = ("sim3", "se3", "none")


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Similarity (or rigid) transform minimising ``Σ ‖dst_i − (s·R·src_i + t)‖²`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points to move (estimated positions).
        dst: ``(N, 3)`` target points (reference positions).
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``R`` ``(3, 3)`` rotation (det +1), ``t`` ``(3,)``, ``s`` float.

    Raises:
        ShapeError: shapes differ or are not ``(N, 3)``.
        GeometryError: ``N < 3``, non-finite input, or a covariance of rank < 2 (all points
            identical or collinear: the rotation is not determined).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    check_shape(src, ["N", 3], "umeyama src")
    check_shape(dst, [len(src), 3], "umeyama dst")
    n = len(src)
    if n < 3:
        raise GeometryError(f"Umeyama alignment needs at least 3 point pairs, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise GeometryError("Umeyama alignment: positions contain NaN or inf")
    mu_src = src.mean(axis=0)  # Umeyama eq. 34
    mu_dst = dst.mean(axis=0)  # Umeyama eq. 35
    xs = src - mu_src
    xd = dst - mu_dst
    var_src = float(np.sum(xs * xs)) / n  # Umeyama eq. 36 (σ_x²)
    cov = xd.T @ xs / n  # Umeyama eq. 38 (Σ_xy, dst × src)
    u, d, vt = np.linalg.svd(cov)  # text between eqs. 38 and 39
    tol = np.finfo(np.float64).eps * max(1.0, float(d[0]))
    if np.count_nonzero(d > tol) < 2:
        raise GeometryError(
            f"degenerate alignment: covariance rank {np.count_nonzero(d > tol)} < 2 over {n} pairs "
            "(positions identical or collinear)"
        )
    S = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:  # Umeyama eq. 43 (reflection → rotation)
        S[2, 2] = -1.0
    R = u @ S @ vt  # Umeyama eq. 40
    s = float(np.trace(np.diag(d) @ S) / var_src) if with_scale else 1.0  # Umeyama eq. 42
    t = mu_dst - s * R @ mu_src  # Umeyama eq. 41
    return R, t, s


def sim3_matrix(R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """``(4, 4)`` matrix ``[[s·R, t], [0, 1]]``; applied to homogeneous positions."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = t
    return T


def check_alignment(align: str) -> None:
    """Raise :class:`ConfigError` unless ``align`` is one of :data:`ALIGNMENTS`."""
    if align not in ALIGNMENTS:
        raise ConfigError(f"unknown alignment {align!r}; valid: {', '.join(ALIGNMENTS)}")


def align_positions(
    p_ref: np.ndarray, p_est: np.ndarray, align: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Estimate positions aligned to the reference for one alignment mode.

    Args:
        p_ref, p_est: ``(K, 3)`` associated positions (metres).
        align: ``sim3`` | ``se3`` | ``none``.

    Returns:
        ``(K, 3)`` aligned estimate ``s·R·p_est + t``, the ``(4, 4)`` transform, ``R`` ``(3, 3)``
        and ``s`` (identity and 1 for ``none``).
    """
    if align == "none":
        return p_est.copy(), np.eye(4), np.eye(3), 1.0
    R, t, s = umeyama(p_est, p_ref, with_scale=(align == "sim3"))
    return s * p_est @ R.T + t, sim3_matrix(R, t, s), R, s

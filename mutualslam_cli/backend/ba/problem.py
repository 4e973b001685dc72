"""Inputs and outputs of the global photometric BA (:mod:`mutualslam_cli.backend.ba.photometric`).

Unknowns: per free keyframe an SE(3) left increment ``(ρ, φ)`` on ``T_cw`` plus the affine
brightness ``(a, b)`` (:data:`NP` values); per point its inverse depth in the host keyframe.
Gauge: keyframe 0 is fixed (:func:`validate` rejects a free keyframe 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mutualslam_cli.errors import ConfigError, ShapeError

NP = 8  # unknowns per keyframe: (ρx, ρy, ρz, φx, φy, φz, a, b)


@dataclass
class PhotoBAProblem:
    """Inputs of one global photometric BA.

    Attributes:
        images: ``(K, H, W)`` float grey images in [0, 1], undistorted pinhole.
        K: ``(3, 3)`` intrinsics (``fy`` may be negative).
        T_cw: ``(K, 4, 4)`` initial world-to-camera poses.
        affine: ``(K, 2)`` initial brightness parameters ``(a, b)``.
        host: ``(P,)`` host keyframe of each point.
        pixel: ``(P, 2)`` host pixel ``(u, v)``.
        inv_depth: ``(P,)`` inverse z-depth in the host (> 0).
        obs_pt, obs_kf: ``(M,)`` point and target keyframe of each (point, target) pair.
        free: ``(K,)`` bool, keyframes whose pose and affine are optimised (``None``: all but 0).
        anchor: ``(K,)`` bool, keyframes whose trajectory extent holds the scale (``None``: all); a map joined
            from segments anchors on the one the others were bridged onto, so a bridge's scale can move.
    """

    images: np.ndarray
    K: np.ndarray
    T_cw: np.ndarray
    affine: np.ndarray
    host: np.ndarray
    pixel: np.ndarray
    inv_depth: np.ndarray
    obs_pt: np.ndarray
    obs_kf: np.ndarray
    free: np.ndarray | None = None
    anchor: np.ndarray | None = None


@dataclass
class PhotoBAResult:
    """Output of :func:`~mutualslam_cli.backend.ba.photometric.solve`: ``T_cw`` ``(K, 4, 4)``, ``affine`` ``(K, 2)``,
    ``inv_depth`` ``(P,)`` and ``stats`` (cost0, cost, costs, iterations, accepted, seconds)."""

    T_cw: np.ndarray
    affine: np.ndarray
    inv_depth: np.ndarray
    stats: dict


def _shape(x: np.ndarray, want: tuple, name: str) -> None:
    if x.shape != want:
        raise ShapeError(f"PhotoBAProblem.{name}: expected shape {want}, got {x.shape}")


def validate(prob: PhotoBAProblem, max_targets: int = 5) -> np.ndarray:
    """Check shapes and values; returns the ``(K,)`` free mask.

    Raises:
        ShapeError: an array has the wrong shape.
        ConfigError: non-finite values, bad indices, a target equal to its host, a duplicate
            (point, target) pair, more than ``max_targets`` targets, or keyframe 0 free.
    """
    im = np.asarray(prob.images)
    if im.ndim != 3:
        raise ShapeError(f"PhotoBAProblem.images: expected shape (K, H, W), got {im.shape}")
    nk, P, M = im.shape[0], len(np.atleast_1d(prob.host)), len(np.atleast_1d(prob.obs_pt))
    _shape(np.asarray(prob.K), (3, 3), "K")
    _shape(np.asarray(prob.T_cw), (nk, 4, 4), "T_cw")
    _shape(np.asarray(prob.affine), (nk, 2), "affine")
    _shape(np.asarray(prob.host), (P,), "host")
    _shape(np.asarray(prob.pixel), (P, 2), "pixel")
    _shape(np.asarray(prob.inv_depth), (P,), "inv_depth")
    _shape(np.asarray(prob.obs_pt), (M,), "obs_pt")
    _shape(np.asarray(prob.obs_kf), (M,), "obs_kf")
    for name in ("images", "K", "T_cw", "affine", "pixel", "inv_depth"):
        if not np.all(np.isfinite(getattr(prob, name))):
            raise ConfigError(f"PhotoBAProblem.{name}: contains NaN or inf; expected finite values")
    if np.any(np.asarray(prob.inv_depth) <= 0):
        raise ConfigError("PhotoBAProblem.inv_depth: expected inverse depths > 0")
    for name, arr, n in (("host", prob.host, nk), ("obs_kf", prob.obs_kf, nk), ("obs_pt", prob.obs_pt, P)):
        a = np.asarray(arr)
        if a.dtype.kind not in "iu" or (len(a) and (a.min() < 0 or a.max() >= n)):
            raise ConfigError(f"PhotoBAProblem.{name}: expected integer indices in [0, {n})")
    host, obs_pt, obs_kf = np.asarray(prob.host), np.asarray(prob.obs_pt), np.asarray(prob.obs_kf)
    bad = np.flatnonzero(obs_kf == host[obs_pt])
    if len(bad):
        raise ConfigError(f"PhotoBAProblem.obs_kf[{bad[0]}]: target keyframe equals the host of "
                          f"point {obs_pt[bad[0]]}; targets must differ from the host")
    if len(np.unique(obs_pt.astype(np.int64) * nk + obs_kf)) != M:
        raise ConfigError("PhotoBAProblem.obs_pt/obs_kf: duplicate (point, target) pair")
    cnt = np.bincount(obs_pt, minlength=P)
    if M and cnt.max() > max_targets:
        raise ConfigError(f"PhotoBAProblem.obs_pt: point {int(cnt.argmax())} has {cnt.max()} "
                          f"targets; expected at most max_targets={max_targets}")
    free = np.arange(nk) > 0 if prob.free is None else np.asarray(prob.free, bool)
    _shape(free, (nk,), "free")
    if free[0]:
        raise ConfigError("PhotoBAProblem.free[0]: keyframe 0 must be fixed (gauge)")
    return free

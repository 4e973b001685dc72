"""Rigid-body and camera geometry in numpy (float64). Torch versions live in ``adapt``.

Quaternions are ``(qx, qy, qz, qw)`` as in TUM files; poses are 4×4 ``T_wc``. The SO(3)/SE(3)
increments (:func:`exp_so3`, :func:`left_update`) are shared by the windowed geometric BA
(:mod:`mutualslam_cli.vo.local_ba`) and the global photometric BA (:mod:`mutualslam_cli.backend.ba`),
which both optimise world-to-camera ``T_cw`` by left increments ``(ρ, φ)``. The pinhole camera's pixels ↔
normalised coordinates (:func:`to_normalized`, :func:`to_pixels`) are here too, for the map and the VO alike.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mutualslam_cli.errors import ShapeError
from mutualslam_cli.types import Intrinsics, check_shape


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` ``(qx, qy, qz, qw)`` → rotation matrices ``(..., 3, 3)``.

    The quaternion is normalised first; a zero quaternion raises :class:`ShapeError`.
    """
    q = np.asarray(q, dtype=np.float64)
    check_shape(q, ["*", 4], "quaternion")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ShapeError("quaternion: zero-norm quaternion")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    r = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` → unit quaternions ``(..., 4)`` ``(qx, qy, qz, qw)``, qw ≥ 0."""
    r = np.asarray(r, dtype=np.float64)
    check_shape(r, ["*", 3, 3], "rotation")
    flat = r.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for k, m in enumerate(flat):
        t = np.trace(m)
        if t > 0:
            s = np.sqrt(t + 1.0) * 2
            out[k] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
            out[k] = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif m[1, 1] > m[2, 2]:
            s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
            out[k] = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
            out[k] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[out[:, 3] < 0] *= -1
    return out.reshape(r.shape[:-2] + (4,))


def pose_from_tq(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Translations ``(..., 3)`` and quaternions ``(..., 4)`` → poses ``(..., 4, 4)``."""
    t = np.asarray(t, dtype=np.float64)
    rot = quat_to_rot(q)
    out = np.zeros(rot.shape[:-2] + (4, 4))
    out[..., :3, :3] = rot
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)`` using ``R^T``."""
    T = np.asarray(T, dtype=np.float64)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions ``(4,)`` at fraction ``a`` ∈ [0, 1]."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Pose between ``T0`` and ``T1`` (``(4, 4)``) at fraction ``a``: lerp translation, slerp rotation."""
    q = slerp(rot_to_quat(T0[:3, :3]), rot_to_quat(T1[:3, :3]), a)
    return pose_from_tq((1 - a) * T0[:3, 3] + a * T1[:3, 3], q)


def backproject(pixels: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` ``(u, v)`` with depths ``(N,)`` → camera points ``(N, 3)``.

    Works for negative ``fy`` (ICL-NUIM): the formula divides by ``K[1, 1]`` as is.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    check_shape(pixels, [len(depth), 2], "pixels")
    x = (pixels[:, 0] - K[0, 2]) / K[0, 0]
    y = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    return np.stack([x * depth, y * depth, depth], axis=1)


def project(points_c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera points ``(N, 3)`` → pixels ``(N, 2)`` and depths ``(N,)`` (z; ≤ 0 means behind)."""
    points_c = np.asarray(points_c, dtype=np.float64)
    check_shape(points_c, ["N", 3], "points")
    z = points_c[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    u = K[0, 0] * points_c[:, 0] / zs + K[0, 2]
    v = K[1, 1] * points_c[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to points ``(N, 3)``."""
    return points @ T[:3, :3].T + T[:3, 3]


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised: ``(N, 3)`` axis-angle → ``(N, 3, 3)``."""
    th = np.linalg.norm(phi, axis=1)
    k = phi / np.maximum(th, 1e-12)[:, None]
    K = np.zeros((len(phi), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Axis-angle ``(3,)`` of a rotation matrix ``(3, 3)`` (the inverse of :func:`exp_so3`), angle in [0, π]."""
    q = rot_to_quat(R)  # qw ≥ 0: the angle is at most π
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return np.zeros(3)
    return q[:3] / s * 2.0 * np.arctan2(s, q[3])


def scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """A relative motion ``T`` ``(4, 4)`` stretched in time by ``s``: rotation ``R^s`` (axis-angle × s),
    translation × s. Exact for the rotation; for the translation it is the constant-velocity model's
    first order (the motion of one frame turns a few degrees at most)."""
    out = np.eye(4)
    out[:3, :3] = exp_so3((s * log_so3(T[:3, :3]))[None])[0]
    out[:3, 3] = s * T[:3, 3]
    return out


def left_update(T: np.ndarray, idx: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T[idx] ← exp(d) · T[idx]`` for left increments ``d`` ``(len(idx), 6)`` = ``(ρ, φ)``,
    rotations projected back onto SO(3) (SVD); returns an updated copy of ``T`` ``(K, 4, 4)``."""
    T = T.copy()
    if len(idx):
        inc = np.tile(np.eye(4), (len(idx), 1, 1))
        inc[:, :3, :3] = exp_so3(d[:, 3:6])
        inc[:, :3, 3] = d[:, :3]
        T[idx] = inc @ T[idx]
        U, _, Vt = np.linalg.svd(T[idx, :3, :3])  # stay on SO(3)
        T[idx, :3, :3] = U @ Vt
    return T


def pinhole(intr: Intrinsics) -> Intrinsics:
    """The same camera without distortion (what ``VOResult.intrinsics`` holds)."""
    return replace(intr, dist=None)


def to_normalized(pix: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole pixels ``(N, 2)`` → normalised image coordinates ``(N, 2)`` (``K⁻¹ [u v 1]``)."""
    pix = np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    return np.stack([(pix[:, 0] - K[0, 2]) / K[0, 0], (pix[:, 1] - K[1, 2]) / K[1, 1]], axis=1)


def to_pixels(xn: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised coordinates ``(N, 2)`` → pinhole pixels ``(N, 2)``."""
    xn = np.asarray(xn, dtype=np.float64).reshape(-1, 2)
    return np.stack([xn[:, 0] * K[0, 0] + K[0, 2], xn[:, 1] * K[1, 1] + K[1, 2]], axis=1)

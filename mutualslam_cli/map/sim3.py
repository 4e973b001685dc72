"""Similarities ``x ↦ s·R·x + t`` and following a reference keyframe: the map's moves in one place.

A bridge joins a segment to the map before it by a :class:`Sim3`; its keyframe poses move by
:meth:`Sim3.apply_pose` (``T_wc ↦ [R·R_wc | s·R·t_wc + t]``) and the inverse depths of the points they
host shrink by ``s``. A keyframe's correction (a global BA's, a pose graph's) carries what was placed
relative to it — later keyframes, tracked frames, the front end's current pose — by :func:`follow`, with
the relative translation in the keyframe's new unit (:func:`rescaled`).

Poses are ``(4, 4)`` ``T_wc`` (camera to world) in map units; the arithmetic of each function is fixed
(the order of its products), so a map moved here is the same, bit for bit, wherever it is moved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Sim3:
    """The similarity ``x ↦ s·R·x + t``.

    Attributes:
        R: ``(3, 3)`` rotation; t: ``(3,)`` translation (map units of the target); s: scale (> 0).

    >>> import numpy as np
    >>> S = Sim3(np.eye(3), np.array([1.0, 0.0, 0.0]), 2.0)
    >>> S.apply_points(np.array([[1.0, 2.0, 3.0]])).tolist()
    [[3.0, 4.0, 6.0]]
    >>> S.inverse().compose(S).apply_points(np.array([[1.0, 2.0, 3.0]])).tolist()
    [[1.0, 2.0, 3.0]]
    """

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    @staticmethod
    def identity() -> Sim3:
        """``x ↦ x``."""
        return Sim3(np.eye(3), np.zeros(3), 1.0)

    @staticmethod
    def onto(T_from: np.ndarray, T_to: np.ndarray, s: float) -> Sim3:
        """The similarity of scale ``s`` that moves the pose ``T_from`` ``(4, 4)`` onto ``T_to`` ``(4, 4)``:
        ``R = R_to·R_fromᵀ``, ``t = t_to − s·R·t_from`` (a bridge: the new segment's first keyframe onto the
        pose the old segment predicts for it)."""
        R = T_to[:3, :3] @ T_from[:3, :3].T
        return Sim3(R, T_to[:3, 3] - s * R @ T_from[:3, 3], float(s))

    def as_float64(self) -> Sim3:
        """This similarity with ``R`` and ``t`` as float64 arrays (what the map's arrays are moved by)."""
        return Sim3(np.asarray(self.R, np.float64), np.asarray(self.t, np.float64), self.s)

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` ``[s·R | t]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def compose(self, other: Sim3) -> Sim3:
        """``self ∘ other``: ``x ↦ s₁R₁(s₂R₂x + t₂) + t₁`` (``other`` first)."""
        return Sim3(self.R @ other.R, self.s * self.R @ other.t + self.t, self.s * other.s)

    def inverse(self) -> Sim3:
        """``y ↦ R⁻¹(y − t)/s``."""
        Rt = self.R.T
        return Sim3(Rt, -(Rt @ self.t) / self.s, 1.0 / self.s)

    def apply_points(self, X: np.ndarray) -> np.ndarray:
        """Points ``(n, 3)`` → ``(n, 3)`` moved."""
        return np.asarray(X, np.float64) @ (self.s * self.R).T + self.t

    def apply_pose(self, T_wc: np.ndarray) -> np.ndarray:
        """A pose ``(4, 4)`` ``T_wc`` moved: ``[R·R_wc | s·R·t_wc + t]`` (a new array)."""
        T = np.array(T_wc, np.float64)
        T[:3, :3] = self.R @ T[:3, :3]
        T[:3, 3] = self.s * self.R @ T[:3, 3] + self.t
        return T

    def apply_poses(self, T_wc: np.ndarray) -> np.ndarray:
        """Poses ``(n, 4, 4)`` moved, one by one as :meth:`apply_pose`."""
        T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
        return np.array([self.apply_pose(T) for T in T_wc]).reshape(-1, 4, 4)


def rescaled(T_rel: np.ndarray, s: float) -> np.ndarray:
    """A relative pose ``(4, 4)`` in a unit ``s`` times larger: its translation ×``s`` (a new array).

    >>> rescaled(np.eye(4), 2.0)[:3, 3].tolist()
    [0.0, 0.0, 0.0]
    """
    T = np.array(T_rel, np.float64)
    T[..., :3, 3] *= s
    return T


def follow(T_wc: np.ndarray, ref_cw_old: np.ndarray, ref_wc_new: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Poses that keep their place relative to a reference keyframe that moved.

    Args:
        T_wc: ``(4, 4)`` or ``(n, 4, 4)`` poses placed relative to the reference.
        ref_cw_old: ``(4, 4)`` or ``(n, 4, 4)`` the reference's ``T_cw`` (world to camera) before its move.
        ref_wc_new: the same shape, the reference's ``T_wc`` after it.
        scale: ``None`` for a rigid correction: ``T ↦ (T_ref,new·T_ref,old⁻¹)·T``; a factor: the reference's unit
            grew by it too, so the pose relative to it is :func:`rescaled` first: ``T ↦ T_ref,new·s(T_ref,old⁻¹·T)``.

    Returns:
        The moved poses, the shape of ``T_wc``.

    >>> T = np.eye(4); T[0, 3] = 1.0
    >>> moved = np.eye(4); moved[1, 3] = 5.0
    >>> follow(T, np.eye(4), moved).tolist()[1][3], follow(T, np.eye(4), moved, 2.0).tolist()[0][3]
    (5.0, 2.0)
    """
    if scale is None:
        return ref_wc_new @ ref_cw_old @ T_wc
    return ref_wc_new @ rescaled(ref_cw_old @ T_wc, scale)

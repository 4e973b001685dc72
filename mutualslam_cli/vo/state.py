"""Mutable bookkeeping of the front end: active tracks and the growing map.

:class:`Tracks` holds one row per feature currently tracked by KLT (map-point tracks and
depth-filter seeds alike, aligned arrays so every per-frame step is vectorised);
:class:`Map` holds keyframes and map points (host, host pixel, inverse depth, observations).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mutualslam_cli.geometry import se3_inv

_SEED_KEYS = ("a", "b", "mu", "sigma2", "z_range")


@dataclass
class Tracks:
    """Aligned per-track arrays (N rows).

    Attributes:
        raw: ``(N, 2)`` float32 raw pixels in the current frame (what KLT tracks).
        px: ``(N, 2)`` undistorted pinhole pixels in the current frame.
        xn: ``(N, 2)`` normalised coordinates in the current frame.
        pid: ``(N,)`` map point id, −1 for a seed.
        host: ``(N,)`` host keyframe of the seed (unused for map points).
        f_h: ``(N, 3)`` unit bearing of the seed in its host.
        px_h: ``(N, 2)`` undistorted pixel of the seed in its host.
        seed: depth-filter state (``a, b, mu, sigma2, z_range``), each ``(N,)``.
        kf_px: ``(N, 2)`` undistorted pixel at the last keyframe (parallax test).
        at_kf: ``(N,)`` bool, the track existed at the last keyframe.
        obs: per-track list of ``(kf_id, px)`` keyframe observations gathered while a seed.
    """

    raw: np.ndarray
    px: np.ndarray
    xn: np.ndarray
    pid: np.ndarray
    host: np.ndarray
    f_h: np.ndarray
    px_h: np.ndarray
    seed: dict[str, np.ndarray]
    kf_px: np.ndarray
    at_kf: np.ndarray
    obs: list[list[tuple[int, np.ndarray]]]

    @staticmethod
    def empty() -> "Tracks":
        z2 = np.zeros((0, 2))
        return Tracks(np.zeros((0, 2), np.float32), z2, z2, np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros((0, 3)), z2, {k: np.zeros(0) for k in _SEED_KEYS}, z2, np.zeros(0, bool), [])

    def __len__(self) -> int:
        return len(self.pid)

    def select(self, keep: np.ndarray) -> "Tracks":
        """Rows where the bool mask (or index array) ``keep`` selects."""
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        return Tracks(self.raw[idx], self.px[idx], self.xn[idx], self.pid[idx], self.host[idx],
                      self.f_h[idx], self.px_h[idx], {k: v[idx] for k, v in self.seed.items()},
                      self.kf_px[idx], self.at_kf[idx], [self.obs[i] for i in idx])

    def extend(self, other: "Tracks") -> "Tracks":
        """Concatenation of two track sets."""
        cat = np.concatenate
        return Tracks(cat([self.raw, other.raw]).astype(np.float32), cat([self.px, other.px]),
                      cat([self.xn, other.xn]), cat([self.pid, other.pid]), cat([self.host, other.host]),
                      cat([self.f_h, other.f_h]), cat([self.px_h, other.px_h]),
                      {k: cat([self.seed[k], other.seed[k]]) for k in _SEED_KEYS},
                      cat([self.kf_px, other.kf_px]), cat([self.at_kf, other.at_kf]), self.obs + other.obs)


@dataclass
class Map:
    """Keyframes and map points of all segments.

    Map points are stored as (host keyframe, host pixel, inverse depth z⁻¹ along the host ray),
    the ``MapPoints`` parametrisation; ``Xw`` caches their world positions.
    """

    kf_frame: list[int] = field(default_factory=list)
    kf_time: list[float] = field(default_factory=list)
    kf_T_wc: list[np.ndarray] = field(default_factory=list)
    kf_segment: list[int] = field(default_factory=list)
    kf_points: list[set[int]] = field(default_factory=list)
    host: list[int] = field(default_factory=list)
    px_h: list[np.ndarray] = field(default_factory=list)
    xn_h: list[np.ndarray] = field(default_factory=list)
    rho: list[float] = field(default_factory=list)
    sigma: list[float] = field(default_factory=list)
    obs: list[dict[int, np.ndarray]] = field(default_factory=list)
    Xw: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    _wc: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    _cw: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))

    def add_keyframe(self, frame: int, t: float, T_wc: np.ndarray, segment: int) -> int:
        """Append a keyframe, return its id."""
        self.kf_frame.append(frame)
        self.kf_time.append(t)
        self.kf_T_wc.append(T_wc.copy())
        self.kf_segment.append(segment)
        self.kf_points.append(set())
        k = len(self.kf_frame) - 1
        if k >= len(self._wc):  # grow the stacked pose arrays geometrically
            grow = np.tile(np.eye(4), (max(16, len(self._wc)), 1, 1))
            self._wc = np.concatenate([self._wc, grow])
            self._cw = np.concatenate([self._cw, grow.copy()])
        self._wc[k] = T_wc
        self._cw[k] = se3_inv(T_wc)
        return k

    def set_pose(self, kf: int, T_wc: np.ndarray) -> None:
        """Replace the pose of keyframe ``kf`` (``T_wc``)."""
        self.kf_T_wc[kf] = T_wc.copy()
        self._wc[kf] = T_wc
        self._cw[kf] = se3_inv(T_wc)

    def poses_wc(self) -> np.ndarray:
        """``(K, 4, 4)`` stacked ``T_wc`` of all keyframes (a view; do not modify)."""
        return self._wc[: len(self.kf_frame)]

    def poses_cw(self) -> np.ndarray:
        """``(K, 4, 4)`` stacked ``T_cw`` of all keyframes (a view; do not modify)."""
        return self._cw[: len(self.kf_frame)]

    def add_points(self, host: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray, rho: np.ndarray,
                   sigma: np.ndarray, obs: list[dict[int, np.ndarray]]) -> np.ndarray:
        """Append points (host observation included in ``obs``), return their ids."""
        start = len(self.host)
        ids = np.arange(start, start + len(host))
        for j, pid in enumerate(ids):
            self.host.append(int(host[j]))
            self.px_h.append(px_h[j])
            self.xn_h.append(xn_h[j])
            self.rho.append(float(rho[j]))
            self.sigma.append(float(sigma[j]))
            self.obs.append(obs[j])
            for k in obs[j]:
                self.kf_points[k].add(int(pid))
        self.Xw = np.concatenate([self.Xw, np.zeros((len(ids), 3))])
        self.refresh(ids)
        return ids

    def refresh(self, ids: np.ndarray) -> None:
        """Recompute cached world positions of points ``ids`` from host pose and inverse depth."""
        if len(ids) == 0:
            return
        ids = np.asarray(ids)
        h = np.array([self.host[i] for i in ids])
        ray = np.c_[np.array([self.xn_h[i] for i in ids]), np.ones(len(ids))]
        rho = np.array([self.rho[i] for i in ids])
        T = self._wc[h]
        Xh = ray / rho[:, None]
        self.Xw[ids] = np.einsum("nij,nj->ni", T[:, :3, :3], Xh) + T[:, :3, 3]

    def add_observation(self, pid: int, kf: int, px: np.ndarray) -> None:
        """Record that keyframe ``kf`` observes point ``pid`` at undistorted pixel ``px``."""
        self.obs[pid][kf] = px
        self.kf_points[kf].add(int(pid))

    def T_cw(self, kf: int) -> np.ndarray:
        """World-to-camera transform of keyframe ``kf``."""
        return self._cw[kf].copy()

"""Mutable bookkeeping of the front end: active tracks and the growing map.

:class:`Tracks` holds one row per feature currently tracked by KLT (map-point tracks and
depth-filter seeds alike, aligned arrays so every per-frame step is vectorised);
:class:`Map` holds keyframes and map points (host, host pixel, inverse depth, observations).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.vo.journal import Journal

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
class TrackerState:
    """What the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) carries from one frame to the next
    besides its map: one declared object its parts share (and :mod:`~mutualslam_cli.vo.checkpoint` saves).

    Attributes:
        mode: ``"init"`` (bringing up a segment) or ``"tracking"``.
        segment: the current tracking segment (−1 before the first).
        ref: the initialisation's reference frame (``init`` only): its grey image, its features and
            their tracks so far; ``None`` otherwise.
        T_cw: ``(4, 4)`` pose of the last tracked frame (world to camera, map units).
        vel: ``(4, 4)`` the last frame-to-frame motion (camera frames); vel_dt: the time it took (s; 0:
            unknown); t_prev: timestamp of the last tracked frame (s).
        tracks: the KLT tracks, map points and depth-filter seeds (:class:`Tracks`).
        n_at_kf: tracks alive at the last keyframe; last_kf: the keyframe frames are tracked against.
        n_tracked: PnP inliers of the last tracked frame; n_reprojected: points re-attached so far (n_reused:
            of them, points from outside the newest keyframes, ``vo.reuse_map``).
        old_share_sum, old_share_frames: the sum over tracked frames of the share of their tracked map points first
            seen more than :data:`~mutualslam_cli.vo.frontend.OLD_AGE_KFS` keyframes before, and the frames summed.
        ba_due: the frame at which the windowed BA in flight is applied.
        lost_at: the frame of the last tracking loss (−1: none).
        kf_imgs: grey images of the newest ``core_kfs`` keyframes (reprojection sources).
        prev_pyr: the previous frame's KLT pyramid; frame: the last frame processed.
        timing: seconds per stage so far; wall_s: seconds in ``process`` so far.
    """

    mode: str = "init"
    segment: int = -1
    ref: dict | None = None
    T_cw: np.ndarray = field(default_factory=lambda: np.eye(4))
    vel: np.ndarray = field(default_factory=lambda: np.eye(4))
    vel_dt: float = 0.0
    t_prev: float = 0.0
    tracks: Tracks = field(default_factory=Tracks.empty)
    n_at_kf: int = 0
    last_kf: int = -1
    n_tracked: int = 0
    n_reprojected: int = 0
    n_reused: int = 0
    n_fused: int = 0
    old_share_sum: float = 0.0
    old_share_frames: int = 0
    ba_due: int = 0
    lost_at: int = -1
    kf_imgs: dict[int, np.ndarray] = field(default_factory=dict)
    prev_pyr: object = None
    frame: int = -1
    timing: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0


@dataclass
class Map:
    """Keyframes and map points of all segments.

    Map points are stored as (host keyframe, host pixel, inverse depth z⁻¹ along the host ray),
    the ``MapPoints`` parametrisation; ``Xw`` caches their world positions (recomputed by
    :meth:`refresh`, which the callers ask for where a pose or a depth changed). A removed point
    keeps its id with a NaN depth and no observation.

    Every change goes through a method here and is recorded in ``journal`` (when given) as an
    :class:`~mutualslam_cli.vo.journal.Event`; a map built by replaying those events
    (:meth:`~mutualslam_cli.vo.map_state.MapState.apply`) is identical to this one.
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
    journal: Journal | None = field(default=None, repr=False, compare=False)

    def _emit(self, kind: str, **data) -> None:
        if self.journal is not None:
            self.journal.emit(kind, **data)

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
        self._emit("keyframe", kf=k, frame=frame, t=t, segment=segment, T_wc=T_wc)
        return k

    def set_poses(self, kfs: np.ndarray, T_wc: np.ndarray) -> None:
        """Replace the poses ``T_wc`` ``(n, 4, 4)`` of keyframes ``kfs`` (points' ``Xw``: :meth:`refresh`)."""
        kfs = np.asarray(kfs, np.int64).reshape(-1)
        T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
        for k, T in zip(kfs.tolist(), T_wc):
            self.kf_T_wc[k] = T.copy()
            self._wc[k] = T
            self._cw[k] = se3_inv(T)
        if len(kfs):
            self._emit("pose", kfs=kfs, T_wc=T_wc)

    def set_pose(self, kf: int, T_wc: np.ndarray) -> None:
        """Replace the pose of keyframe ``kf`` (``T_wc``)."""
        self.set_poses(np.array([kf]), T_wc[None])

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
        px_h, xn_h = np.asarray(px_h, np.float64), np.asarray(xn_h, np.float64)  # as a replayed journal holds them
        obs = [{int(k): np.asarray(x, np.float64) for k, x in o.items()} for o in obs]
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
        self.refresh(ids, emit=False)
        if len(ids):
            self._emit("points", first=start, host=host, px_h=px_h, xn_h=xn_h, rho=rho, sigma=sigma,
                       obs_n=[len(o) for o in obs], obs_kf=[k for o in obs for k in o],
                       obs_px=np.array([p for o in obs for p in o.values()], np.float64).reshape(-1, 2))
        return ids

    def refresh(self, ids: np.ndarray, emit: bool = True) -> None:
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
        if emit:
            self._emit("refresh", pids=ids)

    def observe(self, kf: int, pids: np.ndarray, px: np.ndarray) -> None:
        """Record that keyframe ``kf`` observes points ``pids`` at undistorted pixels ``px`` ``(n, 2)``."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for p, x in zip(pids.tolist(), np.asarray(px, np.float64)):
            self.obs[p][kf] = x
            self.kf_points[kf].add(p)
        if len(pids):
            self._emit("observe", kf=kf, pids=pids, px=px)

    def set_depths(self, pids: np.ndarray, rho: np.ndarray) -> None:
        """Replace the inverse depths of points ``pids`` (``Xw``: :meth:`refresh`)."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for p, r in zip(pids.tolist(), np.asarray(rho, np.float64).reshape(-1).tolist()):
            self.rho[p] = r
        if len(pids):
            self._emit("depth", pids=pids, rho=rho)

    def remove_observations(self, pids: np.ndarray, kfs: np.ndarray) -> None:
        """Forget that keyframe ``kfs[j]`` observes point ``pids[j]``."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        kfs = np.asarray(kfs, np.int64).reshape(-1)
        for p, k in zip(pids.tolist(), kfs.tolist()):
            self.obs[p].pop(k, None)
            self.kf_points[k].discard(p)
        if len(pids):
            self._emit("unobserve", pids=pids, kfs=kfs)

    def remove_points(self, pids: np.ndarray) -> None:
        """Take points out of the map: no observation left, depth NaN (their ids stay taken)."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for p in pids.tolist():
            for k in self.obs[p]:
                self.kf_points[k].discard(p)
            self.obs[p] = {}
            self.rho[p] = float("nan")
        if len(pids):
            self.Xw[pids] = np.nan
            self._emit("remove", pids=pids)

    def fuse_points(self, young: np.ndarray, old: np.ndarray) -> None:
        """Point ``young[j]`` is found to be point ``old[j]`` seen again: its observations go to ``old[j]`` (where
        that keyframe does not observe ``old[j]`` already) and it leaves the map (ORB-SLAM's point fusion). Journaled
        as the observations and the removal it is made of."""
        young = np.asarray(young, np.int64).reshape(-1)
        old = np.asarray(old, np.int64).reshape(-1)
        by_kf: dict[int, tuple[list[int], list[np.ndarray]]] = {}
        for y, o in zip(young.tolist(), old.tolist()):
            for k, x in self.obs[y].items():
                if k not in self.obs[o]:
                    by_kf.setdefault(k, ([], []))[0].append(o)
                    by_kf[k][1].append(x)
        for k in sorted(by_kf):
            self.observe(k, np.array(by_kf[k][0], np.int64), np.array(by_kf[k][1], np.float64).reshape(-1, 2))
        self.remove_points(young)

    def set_host_pixels(self, pids: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray) -> None:
        """Move points' host pixels (undistorted ``px_h`` and normalised ``xn_h``, ``(n, 2)`` each)."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for j, p in enumerate(pids.tolist()):
            self.px_h[p] = np.array(px_h[j], np.float64)
            self.xn_h[p] = np.array(xn_h[j], np.float64)
        if len(pids):
            self._emit("pixel", pids=pids, px_h=px_h, xn_h=xn_h)

    def transform_segment(self, segment: int, R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
        """Move segment ``segment`` by the similarity ``x ↦ s·R·x + t``: its keyframes' ``T_wc ↦ [R·R_wc |
        s·R·t_wc + t]``, the inverse depths (and σ) of the points they host ÷ ``s`` (points follow their
        hosts). Not journaled here (:meth:`~mutualslam_cli.vo.map_state.MapState.transform_segment` is).

        Returns:
            ids of the points hosted in the segment.
        """
        kfs = [k for k, sg in enumerate(self.kf_segment) if sg == segment]
        for k in kfs:
            T = self.kf_T_wc[k].copy()
            T[:3, :3] = R @ T[:3, :3]
            T[:3, 3] = s * R @ T[:3, 3] + t
            self.kf_T_wc[k] = T
            self._wc[k] = T
            self._cw[k] = se3_inv(T)
        in_seg = set(kfs)
        hosted = np.array([p for p, h in enumerate(self.host) if h in in_seg], np.int64)
        for p in hosted.tolist():
            self.rho[p] = self.rho[p] / s
            self.sigma[p] = self.sigma[p] / s
        live = hosted[np.isfinite(np.array([self.rho[p] for p in hosted.tolist()]))] if len(hosted) else hosted
        self.refresh(live, emit=False)
        return hosted

    def T_cw(self, kf: int) -> np.ndarray:
        """World-to-camera transform of keyframe ``kf``."""
        return self._cw[kf].copy()

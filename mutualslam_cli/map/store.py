"""The map's store: keyframes and map points of all segments, as arrays (DESIGN §2).

Written only by :class:`~mutualslam_cli.map.state.MapState`: its mutators here are private (``_add_keyframe``,
``_set_poses``, …) and each is reached through the public method of the same name on the map state, which is
the map's one writer; everyone else reads the fields and the pose views.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.map.journal import Journal
from mutualslam_cli.map.sim3 import Sim3


@dataclass
class Map:
    """Keyframes and map points of all segments.

    Map points are stored as (host keyframe, host pixel, inverse depth z⁻¹ along the host ray),
    the ``MapPoints`` parametrisation; ``Xw`` caches their world positions (recomputed by
    :meth:`_refresh`, which the callers ask for where a pose or a depth changed). A removed point
    keeps its id with a NaN depth and no observation.

    Every change goes through a private method here, called by the
    :class:`~mutualslam_cli.map.state.MapState` method of the same name (the map's one writer), and is recorded
    in ``journal`` (when given) as an :class:`~mutualslam_cli.map.journal.Event`; a map built by replaying those
    events (:meth:`~mutualslam_cli.map.state.MapState.apply`) is identical to this one. Readers use the fields
    (``kf_T_wc``, ``kf_segment``, ``host``, ``rho``, ``Xw``, …) and :meth:`poses_wc` / :meth:`poses_cw`.
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

    def _emit(self, kind: str, **data: object) -> None:
        if self.journal is not None:
            self.journal.emit(kind, **data)

    def _add_keyframe(self, frame: int, t: float, T_wc: np.ndarray, segment: int) -> int:
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

    def _set_poses(self, kfs: np.ndarray, T_wc: np.ndarray) -> None:
        """Replace the poses ``T_wc`` ``(n, 4, 4)`` of keyframes ``kfs`` (points' ``Xw``: :meth:`_refresh`)."""
        kfs = np.asarray(kfs, np.int64).reshape(-1)
        T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
        for k, T in zip(kfs.tolist(), T_wc):
            self.kf_T_wc[k] = T.copy()
            self._wc[k] = T
            self._cw[k] = se3_inv(T)
        if len(kfs):
            self._emit("pose", kfs=kfs, T_wc=T_wc)

    def poses_wc(self) -> np.ndarray:
        """``(K, 4, 4)`` stacked ``T_wc`` of all keyframes (a view; do not modify)."""
        return self._wc[: len(self.kf_frame)]

    def poses_cw(self) -> np.ndarray:
        """``(K, 4, 4)`` stacked ``T_cw`` of all keyframes (a view; do not modify)."""
        return self._cw[: len(self.kf_frame)]

    def _add_points(self, host: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray, rho: np.ndarray,
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
        self._refresh(ids, emit=False)
        if len(ids):
            self._emit("points", first=start, host=host, px_h=px_h, xn_h=xn_h, rho=rho, sigma=sigma,
                       obs_n=[len(o) for o in obs], obs_kf=[k for o in obs for k in o],
                       obs_px=np.array([p for o in obs for p in o.values()], np.float64).reshape(-1, 2))
        return ids

    def _refresh(self, ids: np.ndarray, emit: bool = True) -> None:
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

    def _observe(self, kf: int, pids: np.ndarray, px: np.ndarray) -> None:
        """Record that keyframe ``kf`` observes points ``pids`` at undistorted pixels ``px`` ``(n, 2)``."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for p, x in zip(pids.tolist(), np.asarray(px, np.float64)):
            self.obs[p][kf] = x
            self.kf_points[kf].add(p)
        if len(pids):
            self._emit("observe", kf=kf, pids=pids, px=px)

    def _set_depths(self, pids: np.ndarray, rho: np.ndarray) -> None:
        """Replace the inverse depths of points ``pids`` (``Xw``: :meth:`_refresh`)."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for p, r in zip(pids.tolist(), np.asarray(rho, np.float64).reshape(-1).tolist()):
            self.rho[p] = r
        if len(pids):
            self._emit("depth", pids=pids, rho=rho)

    def _remove_observations(self, pids: np.ndarray, kfs: np.ndarray) -> None:
        """Forget that keyframe ``kfs[j]`` observes point ``pids[j]``."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        kfs = np.asarray(kfs, np.int64).reshape(-1)
        for p, k in zip(pids.tolist(), kfs.tolist()):
            self.obs[p].pop(k, None)
            self.kf_points[k].discard(p)
        if len(pids):
            self._emit("unobserve", pids=pids, kfs=kfs)

    def _remove_points(self, pids: np.ndarray) -> None:
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

    def _fuse_points(self, young: np.ndarray, old: np.ndarray) -> None:
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
            self._observe(k, np.array(by_kf[k][0], np.int64), np.array(by_kf[k][1], np.float64).reshape(-1, 2))
        self._remove_points(young)

    def _set_host_pixels(self, pids: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray) -> None:
        """Move points' host pixels (undistorted ``px_h`` and normalised ``xn_h``, ``(n, 2)`` each)."""
        pids = np.asarray(pids, np.int64).reshape(-1)
        for j, p in enumerate(pids.tolist()):
            self.px_h[p] = np.array(px_h[j], np.float64)
            self.xn_h[p] = np.array(xn_h[j], np.float64)
        if len(pids):
            self._emit("pixel", pids=pids, px_h=px_h, xn_h=xn_h)

    def _transform_segment(self, segment: int, S: Sim3) -> np.ndarray:
        """Move segment ``segment`` by the similarity ``S`` (``x ↦ s·R·x + t``): its keyframes' ``T_wc ↦ [R·R_wc |
        s·R·t_wc + t]`` (:meth:`~mutualslam_cli.map.sim3.Sim3.apply_pose`), the inverse depths (and σ) of the
        points they host ÷ ``s`` (points follow their hosts). Not journaled here (the map state's
        :meth:`~mutualslam_cli.map.state.MapState.transform_segment` is).

        Returns:
            ids of the points hosted in the segment.
        """
        kfs = [k for k, sg in enumerate(self.kf_segment) if sg == segment]
        s = S.s
        for k in kfs:
            T = S.apply_pose(self.kf_T_wc[k])
            self.kf_T_wc[k] = T
            self._wc[k] = T
            self._cw[k] = se3_inv(T)
        in_seg = set(kfs)
        hosted = np.array([p for p, h in enumerate(self.host) if h in in_seg], np.int64)
        for p in hosted.tolist():
            self.rho[p] = self.rho[p] / s
            self.sigma[p] = self.sigma[p] / s
        live = hosted[np.isfinite(np.array([self.rho[p] for p in hosted.tolist()]))] if len(hosted) else hosted
        self._refresh(live, emit=False)
        return hosted

    def T_cw(self, kf: int) -> np.ndarray:
        """World-to-camera transform of keyframe ``kf``."""
        return self._cw[kf].copy()

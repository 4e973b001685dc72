"""What the network's side hands back to the map while the front end runs (the mutual loop, DESIGN §5).

Two changes reach the map between frames: a new segment joined to the map before it
(:meth:`FeedbackMixin.transform_segment`, a similarity from :mod:`~mutualslam_cli.backend.bridges`) and
a global BA's refinement (:class:`MapRefinement`: keyframe poses, point depths and host pixels,
removed points). Each is applied to a :class:`~mutualslam_cli.vo.map_state.MapState` — the live
front end's (journaled, so the adaptation loop's replica follows) or, when there is no live front
end (hindsight labels, an oracle), the loop's own — and the front end goes on from it: its current
pose follows its reference keyframe, seeds follow their hosts, tracks of removed points end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.vo.camera import to_normalized
from mutualslam_cli.vo.map_state import MapState
from mutualslam_cli.vo.result import VOResult


@dataclass
class MapRefinement:
    """A global BA's changes to a map.

    Attributes:
        kfs: ``(n,)`` keyframes whose pose changed; T_wc: ``(n, 4, 4)`` their new poses.
        pids: ``(m,)`` points whose inverse depth or host pixel changed; rho: ``(m,)`` new inverse
            depths (1/map units); px_h: ``(m, 2)`` new host pixels (undistorted pinhole).
        removed: ``(r,)`` points culled (Eq. 10) or dropped as outliers.
        scale: ``(n,)`` the unit of each moved keyframe grew by (a pose graph's Sim(3)); ``None``: all 1 (a BA).
            Frames tracked from it keep their place relative to it, in its new unit; the depths of the points
            it hosts are in ``rho`` like any other change.
    """

    kfs: np.ndarray
    T_wc: np.ndarray
    pids: np.ndarray
    rho: np.ndarray
    px_h: np.ndarray
    removed: np.ndarray
    scale: np.ndarray | None = None

    def scale_of(self, kf: int) -> float:
        """The factor keyframe ``kf``'s unit grew by (1 when it did not move or no scale was given)."""
        if self.scale is None:
            return 1.0
        hit = np.flatnonzero(self.kfs == kf)
        return float(self.scale[hit[0]]) if len(hit) else 1.0

    @staticmethod
    def between(before: VOResult, after: VOResult, removed: np.ndarray) -> "MapRefinement":
        """What changed from ``before`` to ``after`` (same keyframes, same point ids), plus ``removed`` ids."""
        kfs = [k.id for k, a in zip(before.keyframes, after.keyframes) if not np.array_equal(k.pose, a.pose)]
        pb, pa = before.points, after.points
        if not np.array_equal(pb.ids, pa.ids):
            raise ValueError("MapRefinement.between: the two maps hold different points")
        changed = (pb.inv_depth != pa.inv_depth) | np.any(pb.pixel != pa.pixel, axis=1)
        changed &= ~np.isin(pb.ids, removed)
        by_id = {k.id: k for k in after.keyframes}
        return MapRefinement(np.array(kfs, np.int64), np.array([by_id[k].pose for k in kfs]).reshape(-1, 4, 4),
                             pa.ids[changed], pa.inv_depth[changed], pa.pixel[changed],
                             np.asarray(removed, np.int64).reshape(-1))

    def carried(self, state: MapState, last_kf: int) -> "MapRefinement":
        """This refinement, made on the map as it stood when keyframe ``last_kf`` was the newest, for ``state``
        now: every later keyframe follows the correction of its map unit's newest keyframe at or before
        ``last_kf`` (its pose relative to that one kept, in its new unit), and the points it hosts take
        that unit (a delayed BA or loop closure: the realtime clock's). Returns ``self`` when nothing came later."""
        m, later = state.map, range(last_kf + 1, state.n_keyframes)
        moved = dict(zip(self.kfs.tolist(), range(len(self.kfs))))
        kfs, poses, scales, pids, rho = [], [], [], [], []
        for k in later:
            unit = state.unit(m.kf_segment[k])
            ref = next((j for j in range(min(last_kf, k - 1), -1, -1) if state.unit(m.kf_segment[j]) == unit), None)
            if ref is None or ref not in moved:  # its unit's newest keyframe then did not move: nor does it
                continue
            s = self.scale_of(ref)
            rel = np.linalg.inv(m.kf_T_wc[ref]) @ m.kf_T_wc[k]
            rel[:3, 3] *= s
            kfs.append(k)
            poses.append(self.T_wc[moved[ref]] @ rel)
            scales.append(s)
            if s != 1.0:
                own = [p for p in m.kf_points[k] if m.host[p] == k and np.isfinite(m.rho[p])]
                pids += own
                rho += [m.rho[p] / s for p in own]
        if not kfs:
            return self
        own_px = np.array([m.px_h[p] for p in pids], float).reshape(-1, 2)
        return MapRefinement(np.concatenate([self.kfs, np.array(kfs, np.int64)]),
                             np.concatenate([self.T_wc.reshape(-1, 4, 4), np.array(poses)]),
                             np.concatenate([self.pids, np.array(pids, np.int64)]),
                             np.concatenate([self.rho, np.array(rho, float)]),
                             np.concatenate([self.px_h.reshape(-1, 2), own_px]), self.removed,
                             None if self.scale is None else np.concatenate([self.scale, np.array(scales, float)]))


def apply_refinement(state: MapState, r: MapRefinement) -> None:
    """Write ``r`` into ``state``'s map: poses, depths, host pixels, removals, then the world positions
    of every point whose host moved or which changed."""
    m = state.map
    m.set_poses(r.kfs, r.T_wc)
    if r.scale is not None:
        state.rescale_frames(r.kfs, r.scale)
    m.set_depths(r.pids, r.rho)
    m.set_host_pixels(r.pids, r.px_h, to_normalized(r.px_h, state.K))
    m.remove_points(r.removed)
    moved = set(r.kfs.tolist())
    touched = set(r.pids.tolist()) | {p for p, h in enumerate(m.host) if h in moved}
    touched -= set(r.removed.tolist())
    ids = np.array(sorted(p for p in touched if np.isfinite(m.rho[p])), np.int64)
    m.refresh(ids)


class FeedbackMixin:
    """Methods of the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) that take the network
    side's changes between two frames."""

    def settle(self) -> None:
        """Apply the pending windowed BA now, so the map is whole before it is read or changed."""
        self._collect_ba()

    def transform_segment(self, segment: int, R: np.ndarray, t: np.ndarray, s: float, onto: int) -> None:
        """Move ``segment`` by ``x ↦ s·R·x + t`` into segment ``onto``'s frame and unit (a bridge) and go on
        tracking in them."""
        self.settle()
        self.state_map.transform_segment(segment, R, t, s, onto)
        if segment != self.st.segment or self.st.mode != "tracking":
            return
        T = se3_inv(self.st.T_cw)
        T[:3, :3] = R @ T[:3, :3]
        T[:3, 3] = s * R @ T[:3, 3] + t
        self.st.T_cw = se3_inv(T)
        self.st.vel = self.st.vel.copy()
        self.st.vel[:3, 3] *= s  # a motion between two camera frames: its translation in the new unit
        tr = self.st.tracks
        in_seg = np.array([sg == segment for sg in self.map.kf_segment], bool)
        seeds = (tr.pid < 0) & in_seg[np.clip(tr.host, 0, len(in_seg) - 1)] if len(tr) else np.zeros(0, bool)
        tr.seed["mu"][seeds] /= s  # inverse distances along the host bearings
        tr.seed["sigma2"][seeds] /= s * s
        tr.seed["z_range"][seeds] /= s

    def refine(self, r: MapRefinement) -> None:
        """Take a global BA's (or a pose graph's) refinement and go on from it: the current pose follows its
        reference keyframe's correction (in its new unit), as do the seeds of the keyframes whose unit
        changed; tracks of removed points end."""
        self.settle()
        st, ref = self.st, self.st.last_kf
        old = self.map.kf_T_wc[ref].copy() if ref >= 0 else None
        apply_refinement(self.state_map, r)
        if old is not None and st.mode == "tracking":
            rel = se3_inv(old) @ se3_inv(st.T_cw)
            rel[:3, 3] *= r.scale_of(ref)
            st.T_cw = se3_inv(self.map.kf_T_wc[ref] @ rel)
            st.vel = st.vel.copy()
            st.vel[:3, 3] *= r.scale_of(ref)
        if r.scale is not None and len(st.tracks):
            seeds = np.flatnonzero(st.tracks.pid < 0)
            s = np.array([r.scale_of(int(h)) for h in st.tracks.host[seeds]])
            st.tracks.seed["mu"][seeds] /= s  # inverse distances along the host bearings
            st.tracks.seed["sigma2"][seeds] /= s * s
            st.tracks.seed["z_range"][seeds] /= s
        if len(r.removed) and len(st.tracks):
            st.tracks = st.tracks.select(~np.isin(st.tracks.pid, r.removed))

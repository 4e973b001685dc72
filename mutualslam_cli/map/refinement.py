"""A global BA's (or a pose graph's) changes to a map, and how they are written (DESIGN §5).

:class:`MapRefinement` is the change (keyframe poses, point depths and host pixels, removed points, the units
that grew); :meth:`MapRefinement.carried` moves a change made on an older map onto the map now (a delayed BA);
:func:`apply_refinement` writes it through the map state's methods (the map's one writer).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mutualslam_cli.geometry import to_normalized
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.sim3 import follow

if TYPE_CHECKING:
    from mutualslam_cli.map.state import MapState


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
    def between(before: VOResult, after: VOResult, removed: np.ndarray) -> MapRefinement:
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

    def carried(self, state: MapState, last_kf: int) -> MapRefinement:
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
            kfs.append(k)
            poses.append(follow(m.kf_T_wc[k], np.linalg.inv(m.kf_T_wc[ref]), self.T_wc[moved[ref]], s))
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
    """Write ``r`` into ``state``'s map through its writers (journaled when it is): poses, depths, host pixels,
    removals, then the world positions of every point whose host moved or which changed."""
    m = state.map
    state.set_poses(r.kfs, r.T_wc)
    if r.scale is not None:
        state.rescale_frames(r.kfs, r.scale)
    state.set_depths(r.pids, r.rho)
    state.set_host_pixels(r.pids, r.px_h, to_normalized(r.px_h, state.K))
    state.remove_points(r.removed)
    moved = set(r.kfs.tolist())
    touched = set(r.pids.tolist()) | {p for p, h in enumerate(m.host) if h in moved}
    touched -= set(r.removed.tolist())
    ids = np.array(sorted(p for p in touched if np.isfinite(m.rho[p])), np.int64)
    state.refresh(ids)

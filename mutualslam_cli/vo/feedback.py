"""What the network's side hands back to the map while the front end runs (the mutual loop, DESIGN §5).

Two changes reach the map between frames: a new segment joined to the map before it
(:meth:`FeedbackMixin.transform_segment`, a similarity from :mod:`~mutualslam_cli.backend.bridges`) and
a global BA's refinement (:class:`~mutualslam_cli.map.refinement.MapRefinement`: keyframe poses, point depths
and host pixels, removed points). Each is applied to a :class:`~mutualslam_cli.map.state.MapState` — the live
front end's (journaled, so the adaptation loop's replica follows) or, when there is no live front
end (hindsight labels, an oracle), the loop's own — and the front end goes on from it: its current
pose follows its reference keyframe, seeds follow their hosts, tracks of removed points end.
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.map.refinement import MapRefinement, apply_refinement
from mutualslam_cli.map.sim3 import Sim3, follow, rescaled
from mutualslam_cli.vo.frontend_base import FrontEndBase


class FeedbackMixin(FrontEndBase):
    """Methods of the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) that take the network
    side's changes between two frames."""

    def settle(self) -> None:
        """Apply the pending windowed BA now, so the map is whole before it is read or changed."""
        self._collect_ba()

    def transform_segment(self, segment: int, S: Sim3, onto: int) -> None:
        """Move ``segment`` by the similarity ``S`` (``x ↦ s·R·x + t``) into segment ``onto``'s frame and unit (a
        bridge) and go on tracking in them."""
        self.settle()
        self.state_map.transform_segment(segment, S, onto)
        if segment != self.st.segment or self.st.mode != "tracking":
            return
        s = S.s
        self.st.T_cw = se3_inv(S.as_float64().apply_pose(se3_inv(self.st.T_cw)))
        self.st.vel = rescaled(self.st.vel, s)  # a motion between two camera frames: its translation in the new unit
        tr = self.st.tracks
        in_seg = np.array([sg == segment for sg in self.state_map.map.kf_segment], bool)
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
        old = self.state_map.map.kf_T_wc[ref].copy() if ref >= 0 else None
        apply_refinement(self.state_map, r)
        if old is not None and st.mode == "tracking":
            s = r.scale_of(ref)
            st.T_cw = se3_inv(follow(se3_inv(st.T_cw), se3_inv(old), self.state_map.map.kf_T_wc[ref], s))
            st.vel = rescaled(st.vel, s)
        if r.scale is not None and len(st.tracks):
            seeds = np.flatnonzero(st.tracks.pid < 0)
            scales = np.array([r.scale_of(int(h)) for h in st.tracks.host[seeds]])
            st.tracks.seed["mu"][seeds] /= scales  # inverse distances along the host bearings
            st.tracks.seed["sigma2"][seeds] /= scales * scales
            st.tracks.seed["z_range"][seeds] /= scales
        if len(r.removed) and len(st.tracks):
            st.tracks = st.tracks.select(~np.isin(st.tracks.pid, r.removed))

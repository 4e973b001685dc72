"""What the front end does when tracking is lost: relocalise against the map's keyframes
(:mod:`~mutualslam_cli.vo.relocalise`) and continue the matched keyframe's segment, or else start
a new segment from a fresh reference frame (:mod:`~mutualslam_cli.vo.bootstrap`).

A lost frame is looked for twice. First where the camera just was, at the front end's own threshold: the
newest keyframes and the best thumbnail matches. Then anywhere in the map by appearance alone (thumbnails,
the best :data:`~mutualslam_cli.vo.relocalise.OLD_PLACE_RERANK` ranked again by ORB matches), at the
thresholds a loop closure verifies an old place with (:data:`OLD_INLIER_PX`, :data:`OLD_WITNESS_RATIO`): a
camera that re-enters a part of the map made long ago meets points that drifted since (RedKitchen's true
revisits miss their own image by a median 2–3 px), so at 2 px most of a true re-entry's matches look like
outliers and it would be refused."""

from __future__ import annotations

import logging

import numpy as np

from mutualslam_cli.map.records import Relocalised
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.frontend_base import FrontEndBase
from mutualslam_cli.vo.relocalise import OLD_PLACE_RERANK, RelocSettings
from mutualslam_cli.vo.state import Tracks

log = logging.getLogger("mutualslam_cli.vo.frontend")

OLD_INLIER_PX, OLD_WITNESS_RATIO = 4.0, 0.3
"""The old-map query's PnP inlier threshold (pixels) and witness ratio: the loop closure's defaults
(``loop.inlier_px``, ``loop.witness_ratio``)."""


class RecoveryMixin(FrontEndBase):
    """Methods of the front end (``_Frontend``) for a lost frame."""

    def _lost(self, i: int, gray: np.ndarray, reason: str, why: str) -> None:
        if self._relocalise(i, gray):
            return
        log.info("tracking lost at frame %d (%s: %s)", i, reason, why)
        self.state_map.lose(i, reason, why)
        self._collect_ba()
        self.st.mode = "init"
        self.st.lost_at = i
        self.st.tracks = Tracks.empty()
        self._start_ref(i, gray)

    def _relocalise(self, i: int, gray: np.ndarray) -> bool:
        """Find frame ``i`` in the map (:mod:`~mutualslam_cli.vo.relocalise`); on success continue the
        matched keyframe's segment from it: tracks on the verified points, a keyframe at this frame."""
        if self.reloc is None or not self.state_map.map.kf_frame:
            return False
        r = self.reloc.query(gray, self.state_map.map, self.thr, seed=self.seed + i)
        if r is None:  # anywhere in the map, by appearance, at an old place's thresholds
            old = RelocSettings(inlier_factor=OLD_INLIER_PX / (self.f * self.thr), witness_ratio=OLD_WITNESS_RATIO,
                                rerank=OLD_PLACE_RERANK)
            r = self.reloc.query(gray, self.state_map.map, self.thr, seed=self.seed + i, newest=0, settings=old)
        if r is None:
            return False
        self._collect_ba()
        m, n = self.state_map.map, len(r.pids)
        self.st.segment = m.kf_segment[r.keyframe]
        t = Tracks.empty()
        t.raw = r.raw
        t.px, t.xn = self._undist(r.raw)
        t.pid = r.pids.astype(np.int64)
        t.host = np.array([m.host[p] for p in r.pids], np.int64)
        t.f_h, t.px_h = np.zeros((n, 3)), np.zeros((n, 2))
        t.seed = dfl.new_seeds(n, dfl.SeedInit(1.0, 0.5))
        t.kf_px, t.at_kf, t.obs = t.px.copy(), np.ones(n, bool), [[] for _ in range(n)]
        self.st.tracks, self.st.T_cw, self.st.n_tracked = t, r.T_cw, r.inliers
        self.st.vel, self.st.vel_dt, self.st.t_prev = np.eye(4), 0.0, self.seq.frames[i].timestamp
        self.st.mode, self.st.ref = "tracking", None
        self.state_map.relocalise(Relocalised(i, float(self.seq.frames[i].timestamp), int(r.keyframe), int(r.inliers),
                                              0 if self.st.lost_at < 0 else i - self.st.lost_at,
                                              int(r.candidates_tried)))
        log.info("relocalised frame %d against keyframe %d (%d inliers)", i, r.keyframe, r.inliers)
        self._keyframe(i, gray)
        self._record(i)
        return True


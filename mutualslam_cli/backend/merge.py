"""Merging a segment into the map before it (``vo.merge_segments``; ORB-SLAM3's map merging, Campos et al.,
T-RO 2021, §VI-B): the measured join that replaces the network's bridge.

A tracking loss the relocalisation could not repair starts a new segment in its own frame and unit; the
adaptation loop then *bridges* it (:mod:`~mutualslam_cli.backend.bridges`): placed at the last tracked pose, scaled
by the network's depth ratio on the two sides of the gap — an estimate that put whole TUM fr1_desk segments
20–25 % off in scale. A merge measures instead. At each keyframe of a segment not merged yet, the keyframe is
looked for among the keyframes of the segments before it with the loop closure's place recognition and
verification (:class:`~mutualslam_cli.backend.loop_detector.LoopDetector`: ORB homography, KLT from the old image,
PnP-RANSAC, inlier halves, other old keyframes as witnesses, the old points' depths agreeing with the
network's), which gives the keyframe's pose ``T_o`` in the old map and the scale ``s`` between the two maps
from pairs of nearby old and new points (old units per new unit). Then:

* a segment in a map unit of its own (its bridge refused, or ``vo.bridge_segments`` off) moves whole: with
  ``T_n`` the keyframe's pose in its segment, ``x ↦ s·R·x + t``, ``R = R_oᵀ R_n``, ``t = R_oᵀ (s t_n − t_o)``
  puts it exactly at ``T_o``; the front end goes on in the old frame and unit, and re-observes the old map there
  (map reuse);
* a segment a bridge already put into that map unit is corrected as a loop is (the Sim(3) pose graph, whose
  bridge edges are loose in scale, then culling + BA: :meth:`~mutualslam_cli.backend.loop_closer.LoopCloser.close`):
  the map between the two ends has drifted too, and a rigid move would only shift the tear to the bridge (on
  a 2,000-frame rendered room a rigid merge raised the ATE from 0.152 to 0.187 m).

A segment is merged at most once.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import numpy as np

from mutualslam_cli.backend.loop_closer import LoopCloser, close_on_graph
from mutualslam_cli.backend.loop_detector import LoopClosure, LoopDetector
from mutualslam_cli.backend.records import MergeRecord, MergeSite
from mutualslam_cli.backend.refine import MapTarget
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.sim3 import Sim3

#: The old segments' newest keyframes a merge query tries before the appearance ranking: a segment started after a
#: loss most often sees again what the camera saw when it lost track (TUM fr1_desk: the appearance ranking alone
#: offered the window's first keyframes and no merge was verified).
MERGE_NEWEST = 2


def merge_similarity(T_new: np.ndarray, loop: LoopClosure) -> Sim3:
    """The similarity ``x ↦ s·R·x + t`` that moves the query keyframe from its pose ``T_new`` ``(4, 4)`` (world to
    camera, its segment's frame) to the verified ``loop.T_cw`` in the old map, its unit scaled by ``loop.scale``."""
    R_o, t_o = loop.T_cw[:3, :3], loop.T_cw[:3, 3]
    R_n, t_n = T_new[:3, :3], T_new[:3, 3]
    s = float(loop.scale)
    return Sim3(R_o.T @ R_n, R_o.T @ (s * t_n - t_o), s)


class SegmentMerger:
    """Merges of one run's segments (module docstring).

    Args:
        seq: the sequence (keyframe images); seed: the run's seed (each query's RANSAC draws ``seed + kf``).
        source: where the map is (:class:`~mutualslam_cli.backend.refine.MapTarget`): its ``state`` is the map now;
            ``transform_segment`` moves a segment.
        detector: its place recognition, with records of its own
            (:meth:`~mutualslam_cli.backend.loop_detector.LoopDetector.sharing` of the loop closer's, so one
            keyframe index serves both; :func:`~mutualslam_cli.backend.loop_closer.place_detector` without one).
        closer: the run's loop closure (``loop.enabled``): a merge within one map unit is closed its way (pose
            graph + BA); ``None``: the pose graph alone.

    Attributes:
        merges: one record per merge (``segment``, ``onto``, ``query``, ``match``, ``scale``, ``inliers``, …).
        tried: keyframes queried.
    """

    def __init__(self, seq: Sequence, seed: int, source: MapTarget, detector: LoopDetector,
                 closer: LoopCloser | None = None) -> None:
        self.seq, self.seed, self.source, self.detector, self.closer = seq, seed, source, detector, closer
        self.merges: list[MergeRecord] = []
        self.tried = 0
        self._merged: set[int] = set()

    def after_keyframe(self, kf: int, depth_of: Callable[[int], np.ndarray],
                       val_loss: Callable[[list[int]], Mapping[int, float]]) -> float:
        """Keep keyframe ``kf``; merge its segment into an older one when it is found there. Returns the seconds.

        Args:
            depth_of: ``kf_id → (h, w)`` the adapted network's depth now; val_loss: L_val of keyframe ids now.
        """
        t = time.perf_counter()
        state = self.source.state
        gray = None
        if kf not in self.detector.index.images:
            gray = self.seq.load_gray(state.frame_of(kf))
            self.detector.add(kf, gray)
        seg = state.segment(kf)
        first = state.first_keyframe(seg)
        if seg in self._merged or first == 0:
            return time.perf_counter() - t
        pool = [k for k in sorted(self.detector.index.images) if k < first and state.segment(k) != seg]
        if not pool:
            return time.perf_counter() - t
        gray = self.seq.load_gray(state.frame_of(kf)) if gray is None else gray
        self.tried += 1
        loop = self.detector.query(state, kf, gray, depth_of(kf), seed=self.seed + kf, pool=pool,
                                   newest=MERGE_NEWEST)
        if loop is None:
            return time.perf_counter() - t
        onto = state.segment(loop.match)
        where = MergeSite(segment=int(seg), onto=int(onto), frame=int(state.frame_of(kf)),
                          timestamp=float(state.time_of(kf)))
        if state.unit(seg) == state.unit(onto):  # bridged into that map already: the measured loop corrects it
            if self.detector.already_closed(state, loop):
                return time.perf_counter() - t
            if self.closer is not None:
                rec = MergeRecord(loop, **where, how="pose graph + BA",
                                  closed=self.closer.close(loop, depth_of, val_loss))
            else:
                close_on_graph(self.source, loop)
                rec = MergeRecord(loop, **where, how="pose graph")
        else:  # a segment in a unit of its own (its bridge refused): moved onto the old map whole
            self.source.settle()  # the windowed BA in flight first: the keyframe's pose as it now stands
            self.source.transform_segment(seg, merge_similarity(state.pose_cw(kf), loop), onto)
            rec = MergeRecord(loop, **where, how="similarity")
        self._merged.add(seg)
        self.merges.append(rec)
        return time.perf_counter() - t

"""Loop closure inside the adaptation loop (``loop.enabled``; the paper's future work, §V).

:class:`LoopCloser` keeps every keyframe's image for place recognition and, for each new keyframe, looks
for it among the keyframes of its map unit at least ``loop.min_gap`` older
(:class:`~mutualslam_cli.backend.loop_detector.LoopDetector`: appearance, geometry, and the adapted network's
depth for the scale and as a check). A verified loop is closed on the map as it stands — like the
global BA's feedback, in the live front end with causal labels: a Sim(3) pose graph spreads the
correction over the keyframes it closes (:func:`~mutualslam_cli.backend.pose_graph.close_loop`), then culling +
the robust global BA refine the unit, the loop's two ends now close enough for nearby-keyframe targets to
tie them (the loop's correspondences). The refined poses and points feed training as the BA's do.

What it records — the loops closed, the detector's queries and rejections, the keyframes not queried — the
stages write out: ``loop.{candidates,accepted,rejected}``
(:func:`~mutualslam_cli.stages.adaptation_summary.summarise_loops`), the loops in ``manifest.json`` (``loops``),
drawn on the trajectory figure, and with GT, after the run, the recall of true revisits (``loop.recall.*``,
``loop_recall.csv``: :mod:`~mutualslam_cli.stages.loop_recall`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

import numpy as np

from mutualslam_cli.backend.loop_detector import LoopClosure, LoopDetector
from mutualslam_cli.backend.pose_graph import close_loop
from mutualslam_cli.backend.records import LoopRecord
from mutualslam_cli.backend.refine import MapBA, MapTarget, refine_map
from mutualslam_cli.config import LoopConfig, VOConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.vo.camera import focal_px

log = logging.getLogger(__name__)


def place_detector(seq: Sequence, vo: VOConfig, loop: LoopConfig, source: MapTarget) -> LoopDetector:
    """The run's place recognition: a :class:`~mutualslam_cli.backend.loop_detector.LoopDetector` over ``seq``'s
    keyframes as ``source`` holds them (images decoded again when asked), its PnP threshold the front end's
    (``vo.ransac_threshold_px``), its other thresholds ``loop``'s. The loop closer takes it; the merger takes
    :meth:`~mutualslam_cli.backend.loop_detector.LoopDetector.sharing` of it (one keyframe index for both)."""
    return LoopDetector(seq.intrinsics, vo.ransac_threshold_px / focal_px(seq.intrinsics), loop,
                        load=lambda kf: seq.load_gray(source.state.frame_of(kf)))


def close_on_graph(source: MapTarget, loop: LoopClosure) -> None:
    """Close a verified ``loop`` by the Sim(3) pose graph alone on ``source``'s map: the work in flight settled
    first, so the graph starts from the map as it stands."""
    source.settle()
    source.refine(close_loop(source.state, loop))


class LoopCloser:
    """Place recognition and loop closure over one run's keyframes (module docstring).

    Args:
        seq: the sequence (keyframe images); loop: the run's ``loop`` section (``cooldown``); seed: the run's seed
            (each query's RANSAC draws ``seed + kf``).
        source: where the map is (:class:`~mutualslam_cli.backend.refine.MapTarget`): its ``state`` is the map now;
            ``settle`` / ``refine`` change it.
        ba: the run's culling + BA, ``None`` without BA: the pose graph alone.
        detector: the run's place recognition (:func:`place_detector`).

    Attributes:
        loops: one record per loop closed (``manifest.json``'s ``loops``).
        skipped: ``{kf: why}`` of the keyframes kept but not queried (loop recall's reasons).
    """

    def __init__(self, seq: Sequence, loop: LoopConfig, seed: int, source: MapTarget, ba: MapBA | None,
                 detector: LoopDetector) -> None:
        self.seq, self.settings, self.seed, self.source, self.ba = seq, loop, seed, source, ba
        self.detector = detector
        self.loops: list[LoopRecord] = []
        self.skipped: dict[int, str] = {}
        self._last = -(10 ** 9)  # the query keyframe of the last loop closed
        self.ba_seconds = 0.0  # of the closing BAs (booked to BA, not to the loop)

    def after_keyframe(self, kf: int, depth_of: Callable[[int], np.ndarray],
                       val_loss: Callable[[list[int]], Mapping[int, float]]) -> float:
        """Keep keyframe ``kf`` and close a loop from it when there is one; returns the seconds spent.

        Args:
            depth_of: ``kf_id → (h, w)`` the adapted network's depth now; val_loss: L_val of keyframe ids now.
        """
        t = time.perf_counter()
        state = self.source.state
        gray = self.seq.load_gray(state.frame_of(kf))
        self.detector.add(kf, gray)
        if kf - self._last < self.settings.cooldown:
            self.skipped[kf] = (f"not queried: within loop.cooldown ({self.settings.cooldown}) keyframes of the loop "
                                f"closed at keyframe {self._last}")
            return time.perf_counter() - t
        loop = self.detector.query(state, kf, gray, depth_of(kf), seed=self.seed + kf)
        if loop is None:
            return time.perf_counter() - t
        if self.detector.already_closed(state, loop):  # e.g. the front end relocalised there: nothing to correct
            return time.perf_counter() - t
        self.loops.append(self.close(loop, depth_of, val_loss))
        log.info("loop closed: keyframe %d sees keyframe %d again (scale %.3f, %d inliers)", kf, loop.match,
                 loop.scale, loop.inliers)
        return time.perf_counter() - t

    def close(self, loop: LoopClosure, depth_of: Callable[[int], np.ndarray],
              val_loss: Callable[[list[int]], Mapping[int, float]]) -> LoopRecord:
        """Close a verified ``loop`` on the map as it stands: the pose graph, then (with a BA stage) culling + the
        robust BA; returns its record. Also a merge's way within one map unit (:mod:`~mutualslam_cli.backend.merge`)."""
        kf, state = loop.query, self.source.state
        self._last = kf  # whoever asked (a loop, a merge): no other loop within loop.cooldown keyframes of it
        close_on_graph(self.source, loop)
        nearby = None
        if self.ba is not None:  # the robust BA over the closed map: the loop's two ends now tie by nearby targets
            t_ba = time.perf_counter()
            r = refine_map(self.source, kf, self.ba, depth_of, val_loss)
            nearby = int(r.stats.n_nearby_targets)
            self.ba_seconds += time.perf_counter() - t_ba
        return LoopRecord(loop, int(state.frame_of(kf)), float(state.time_of(kf)), float(state.time_of(loop.match)),
                          nearby)

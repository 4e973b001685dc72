"""Refining the map as it stands: culling + global BA of a snapshot, and the refinement handed back.

:class:`MapBA` culls with the adapted network and runs the global photometric BA
(:func:`~mutualslam_cli.backend.ba.global_ba.run_global_ba`) on a map snapshot, each run recorded in a
:class:`BALog`. :func:`refine_map` is the one way to refine the map of a run while it runs — at Algorithm 1's
requests (the mutual loop) and after a loop closure's pose graph: the map settled, a snapshot of it, the BA of
its newest ``ba.window`` keyframes (:func:`~mutualslam_cli.backend.ba.global_ba.window_start`), and the
change handed back to the map (:class:`~mutualslam_cli.map.refinement.MapRefinement`) — to the front end's
event source or, under the realtime schedule, to the copy the work runs on (:class:`MapTarget`). The final BA
of a run refines a finished map with the same :meth:`MapBA.run_ba` (:mod:`~mutualslam_cli.stages.ba`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from mutualslam_cli.adapt.inputs import frame_lookup
from mutualslam_cli.backend.ba.global_ba import GlobalBAResult, run_global_ba, window_start
from mutualslam_cli.backend.records import BARun
from mutualslam_cli.config import BAConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.refinement import MapRefinement
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.sim3 import Sim3
from mutualslam_cli.map.state import MapState
from mutualslam_cli.types import FrameRef, Intrinsics
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)


class MapTarget(Protocol):
    """Where the back end's changes to a run's map go: the front end's event source
    (:class:`~mutualslam_cli.vo.source.FrontEndSource`), or under the realtime schedule the copy of the
    map a piece of work runs on until its changes are due (:class:`~mutualslam_cli.online.realtime.DeferredMap`)."""

    @property
    def state(self) -> MapState:
        """The map as it stands now."""
        ...

    def settle(self) -> None:
        """Make the map whole (the front end's pending windowed BA) before it is read for a change."""
        ...

    def transform_segment(self, segment: int, S: Sim3, onto: int) -> None:
        """Join ``segment`` to segment ``onto`` by the similarity ``S`` (a bridge, a merge)."""
        ...

    def refine(self, r: MapRefinement) -> None:
        """Take a global BA's or a pose graph's refinement."""
        ...


def ba_images(seq: Sequence, keyframes: VOResult | Callable[[int], int], scale: float = 1.0,
              keep: int = 0, camera: Intrinsics | None = None) -> Callable[[int], np.ndarray]:
    """``kf_id → (H, W)`` float32 grey in [0, 1] of the keyframes (of a map, or ``kf_id → frame index``),
    undistorted, at ``scale`` × the pinhole camera (area resampling; cached for the run, at most the
    ``keep`` newest ids when ``keep > 0``)."""
    und = Undistorter(seq.intrinsics)
    cam = camera or (keyframes.intrinsics if isinstance(keyframes, VOResult) else seq.intrinsics)
    size = (round(cam.width * scale), round(cam.height * scale))
    frame_of = frame_lookup(keyframes)
    cache: dict[int, np.ndarray] = {}

    def load(kf_id: int) -> np.ndarray:
        if kf_id not in cache:
            grey = cv2.cvtColor(und.image(seq.load_rgb(frame_of(kf_id))), cv2.COLOR_RGB2GRAY)
            cache[kf_id] = cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
            if keep and len(cache) > keep:  # a windowed BA (ba.window) asks for newer keyframes only
                del cache[next(iter(cache))]  # the oldest read
        return cache[kf_id]

    return load


@dataclass
class BALog:
    """What the culling + BA runs of one run did: each run's ``stats`` (Algorithm 1's requests, loop closures,
    then the final one), the ids of every culled map point and of every point dropped as an outlier."""

    runs: list[BARun] = field(default_factory=list)
    culled: set[int] = field(default_factory=set)
    dropped: set[int] = field(default_factory=set)

    def culled_mask(self, ids: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: which of the map-point ``ids`` were culled."""
        return np.isin(ids, np.fromiter(self.culled, np.int64, len(self.culled)))

    def dropped_mask(self, ids: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: which of the map-point ``ids`` the BA dropped as outliers."""
        return np.isin(ids, np.fromiter(self.dropped, np.int64, len(self.dropped)))


class MapBA:
    """Culling + global BA of one run's map snapshots, every run recorded.

    Args:
        seq: the sequence (keyframe images at the BA's scale, cached for the run); cfg: the run's ``ba``.
        cull: cull with the adapted network before the BA (``False``: ``ba.culling=false`` or scheme ``none``).

    Attributes:
        record: what each culling + BA did (:class:`BALog`).
    """

    def __init__(self, seq: Sequence, cfg: BAConfig, cull: bool) -> None:
        self.seq, self.cfg, self.cull = seq, cfg, cull
        self.record = BALog()
        self._frame_of: dict[int, int] = {}  # keyframe → frame, of the maps BA has seen (the map grows)
        self.images = ba_images(seq, self._frame_of.__getitem__, cfg.image_scale, keep=cfg.window,
                                camera=seq.intrinsics)

    @property
    def frames(self) -> list[FrameRef]:
        """The sequence's frames (what a snapshot of the map is made over)."""
        return self.seq.frames

    @property
    def window(self) -> int:
        """``ba.window``: the newest keyframes a BA refines (0: all)."""
        return self.cfg.window

    def run_ba(self, vo: VOResult, kf_id: int, depth_of: Callable[[int], np.ndarray],
               val_loss: Mapping[int, float]) -> GlobalBAResult:
        """Culling (unless :attr:`cull` is off) + global BA of ``vo``'s keyframes ≤ ``kf_id`` (the segments a bridge
        or a merge joined as one map: :attr:`~mutualslam_cli.map.result.VOResult.units`), recorded into
        :attr:`record`."""
        self._frame_of.update((k.id, k.frame_index) for k in vo.keyframes)
        units = vo.unit_of_segment()  # the map's own answer: bridges and merges
        r = run_global_ba(vo, self.images, depth_of, val_loss, self.cfg, cull=self.cull, upto=kf_id, units=units)
        self.record.culled.update(vo.points.ids[~r.keep].tolist())
        self.record.dropped.update(vo.points.ids[r.dropped].tolist())
        self.record.runs.append(BARun(kf_id, r.stats))
        st = r.stats
        log.info("global BA after keyframe %d: %d culled, %d dropped, %d refined (%d unrefined), cost %.4g -> %.4g, "
                 "%.2f s", kf_id, st.n_culled, st.n_dropped, st.n_refined, st.n_unrefined, st.cost0, st.cost,
                 st.seconds)
        return r


def refine_map(target: MapTarget, kf: int, ba: MapBA, depth_of: Callable[[int], np.ndarray],
               val_loss: Callable[[list[int]], Mapping[int, float]]) -> GlobalBAResult:
    """Culling + global BA of the map as it stands in ``target``, keyframes ≤ ``kf`` (the newest ``ba.window``),
    the refinement handed back to ``target`` (module docstring); returns the BA's result.

    Args:
        depth_of: ``kf_id → (h, w)`` the adapted network's depth now; val_loss: L_val of keyframe ids now (the
            window's).
    """
    target.settle()
    snap = target.state.snapshot(ba.frames, covisibility=False)
    first = window_start(kf, ba.window)
    r = ba.run_ba(snap, kf, depth_of, val_loss([k.id for k in snap.keyframes[first:kf + 1]]))
    target.refine(MapRefinement.between(snap, r.vo, snap.points.ids[~r.keep | r.dropped]))
    return r

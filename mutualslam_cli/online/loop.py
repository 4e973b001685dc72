"""Algorithm 1 on one clock, the front end's frames (DESIGN §1, §5): :class:`OnlineLoop`, the engine the
adaptation stage (:mod:`mutualslam_cli.stages.adaptation`) drives.

After each frame's events (:class:`~mutualslam_cli.vo.source.FrontEndSource`) the map —
:attr:`~mutualslam_cli.vo.source.FrontEndSource.state`, the one object that holds it — is the
map as it stood then, and for each keyframe the frame created:

1. the previous keyframe's optimiser steps, when the realtime schedule waited for this arrival to know them;
2. the online scores of the frames up to it, its own included, with the model of their time (before it trains on
   the keyframe);
3. a new tracking segment is joined to the map before it by the network as adapted up to now (a bridge);
4. Algorithm 1's tick: a validation keyframe's L_val (the FSM may request global BA), or a training
   keyframe's batch — the newest keyframe plus the scheme's replay — with every label (poses, sparse
   depths) read from the map now (:class:`~mutualslam_cli.online.labels.MapLabels`);
5. a requested global BA culls with the network of now, refines the map, and hands the refinement to the
   front end, which tracks and maps from it (the mutual loop, paper §III-A, §III-C).

With causal labels (``adapt.labels: causal``, the default) bridges and BAs reach the live front end; with
``hindsight`` (a diagnostic) the front end ran to the end first, labels are the final map's and the changes
are made to that map only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import torch

from mutualslam_cli.adapt.buffer import KeyframeSample
from mutualslam_cli.adapt.depthnet import DepthNet, predict_depth, prepare
from mutualslam_cli.adapt.inputs import keyframe_images
from mutualslam_cli.adapt.online import OnlineAdapter, StepInfo
from mutualslam_cli.backend.bridges import Bridge, plan_bridge
from mutualslam_cli.backend.loop_closer import LoopCloser, place_detector
from mutualslam_cli.backend.merge import SegmentMerger
from mutualslam_cli.backend.refine import MapBA, MapTarget, refine_map
from mutualslam_cli.online.credit import WeightsAt
from mutualslam_cli.online.labels import DepthOf, MapLabels, depth_predictor
from mutualslam_cli.online.realtime import DeferredMap, RealtimeClock, RealtimeSchedule
from mutualslam_cli.online.rows import KeyframeRow
from mutualslam_cli.online.run import OnlineRun
from mutualslam_cli.online.scores import OnlineScorer
from mutualslam_cli.vo.source import FrontEndSource


class OnlineLoop:
    """Algorithm 1 over the front end's events, for one run (module docstring).

    Args:
        run: the run (sequence, config, device, progress).
        source: the front end's events; its ``state`` is the map at the loop's time.
        net: the network to adapt (a copy of the pre-trained one).
        fast: bf16 autocast for the network.
        ba: the run's culling + global BA (:class:`~mutualslam_cli.backend.refine.MapBA`), ``None`` without BA.
        scorer: scores evaluated frames with the model of their time (``None``: not scored).

    Attributes:
        rows: one ``keyframes.csv`` row per keyframe; bridges: one record per bridge made; refused: one per
            bridge refused (its segment stays apart, and the network is not trained on it: one unit).
    """

    def __init__(self, run: OnlineRun, source: FrontEndSource, net: DepthNet, fast: bool,
                 ba: MapBA | None = None, scorer: OnlineScorer | None = None) -> None:
        cfg = run.cfg
        self.run, self.source, self.state, self.cfg, self.fast = run, source, source.state, cfg, fast
        self.ba, self.scorer = ba, scorer
        w, h = cfg.net.width, cfg.net.height
        self.net = prepare(net, fast, device=run.device, bf16_encoder=cfg.net.fast_train == "all")
        self.load = keyframe_images(run.seq, lambda k: self.state.frame_of(k), w, h)
        self.adapter: OnlineAdapter | None = None
        if cfg.adapt.scheme != "none":
            K_net = torch.from_numpy(self.state.intr.scaled(w, h).K()).float()
            self.adapter = OnlineAdapter(self.net, cfg.adapt, K_net, seed=cfg.seed, fast=fast,
                                         val_scope=cfg.adapt.val_scope, reg_mode=cfg.adapt.reg_mode,
                                         labels=MapLabels(self.state, w, h), device=run.device)
        self.clock: RealtimeClock | None = None
        self.writer: MapTarget = source  # where the loop's map changes go: the source now, or when their work ends
        if cfg.adapt.schedule == "realtime" and self.adapter is not None:
            cost = cfg.adapt.step_cost_ms
            self.clock = RealtimeClock(None if cost == "measured" else float(cost), cfg.adapt.max_steps)
            self.writer = DeferredMap(source)
        places = place_detector(run.seq, cfg.vo, cfg.loop, self.writer)  # one keyframe index for closer and merger
        self.closer = (LoopCloser(run.seq, cfg.loop, cfg.seed, self.writer, ba, places) if cfg.loop.enabled
                       else None)
        self.merger = (SegmentMerger(run.seq, cfg.seed, self.writer,
                                     places if self.closer is None else places.sharing(), self.closer)
                       if cfg.vo.merge_segments and cfg.vo.mode == "svo" else None)
        if cfg.vo.depth_seeds or cfg.vo.scale_prior:  # the front end asks the network of now at its keyframes
            frame_image = keyframe_images(run.seq, lambda f: f, w, h)  # by frame: not in the map yet when asked
            source.use_network(lambda f: predict_depth(self.net, frame_image(f)[None], fast)[0])
        self.rows: list[KeyframeRow] = []  # the ticked keyframes' rows, in tick order
        self.bridges: list[Bridge] = []
        self.refused: list[Bridge] = []
        self.net_unit: int | None = None  # the map unit the network is trained in (its first keyframe's)
        self.other_unit: list[int] = []  # keyframes of segments kept apart: not trained on, not validated
        self.trained_kf = -1  # the keyframe whose steps made the weights now (-1: pre-trained)
        self.weights_at = WeightsAt(set())  # the weights at the frames where the credit bridges are planned
        self.row_of: dict[int, KeyframeRow] = {}
        self._segments: set[int] = set()
        if scorer is not None and self.adapter is not None:
            scorer.log = self.adapter.step_log

    # ------------------------------------------------------------------ Algorithm 1
    def run_loop(self) -> None:
        """Every frame in order, each keyframe it created through Algorithm 1 (module docstring) on the schedule of
        ``adapt.schedule``: in order (:meth:`in_order`), or on the sequence's clock
        (:class:`~mutualslam_cli.online.realtime.RealtimeSchedule`); each keyframe reported when its work ends."""
        schedule = RealtimeSchedule(self) if self.clock is not None else self.in_order
        t0 = time.perf_counter()
        for frame, keyframes in self.source.timeline():
            self._mark("frontend")
            self.weights_at.at_frame(frame, self.net)  # the weights the front end has at this frame
            for kf in schedule(frame, keyframes):
                self._report(kf, t0)

    def in_order(self, frame: int, keyframes: list[int]) -> Iterator[int]:
        """The causal schedule: each of ``frame``'s new keyframes' whole work before the next; yields each as done."""
        for kf in keyframes:
            # the frames up to and including the keyframe's own: the model of their time, before it learns
            # from this one (test-time adaptation's rule: a frame is scored before the model trains on it)
            self.score_before(self.state.created_at[kf] + 1, kf - 1)
            self.keyframe_work(kf)
            if self.adapter is not None:
                self._train(self.cfg.adapt.steps_per_keyframe)
                self.trained_kf = kf
            yield kf

    def keyframe_work(self, kf: int) -> None:
        """Keyframe ``kf``'s work before its optimiser steps, with the map and the network of now."""
        if self.clock is not None:
            self.row(kf).rt_start_ms = self.clock.now_ms
        self._join_segment(kf)                          # a new segment: the network of now bridges it
        merger, closer = self.merger, self.closer
        if merger is not None:                          # a segment found in the map before it: merged
            self._backend("merge_s", kf, lambda: merger.after_keyframe(kf, self._depth_of(), self._val_loss))
        info = self._tick(kf)                           # validate, or assemble the batch (labels of now)
        if info is not None and info.run_global_ba:
            self._global_ba(kf)                         # cull + BA; the refined map goes back to the front end
        if closer is not None:                          # a place seen before: close the loop (loop.enabled)
            self._backend("loop_s", kf, lambda: closer.after_keyframe(kf, self._depth_of(), self._val_loss))

    def _tick(self, kf: int) -> StepInfo | None:
        if self.adapter is None:
            return None
        unit = self.state.unit(self.state.segment(kf))
        self.net_unit = unit if self.net_unit is None else self.net_unit
        if unit != self.net_unit:  # a segment no bridge could join: never trained in two units
            self.other_unit.append(kf)
            return None
        t = time.perf_counter()
        info = self.adapter.begin_keyframe(KeyframeSample(
            kf_id=kf, image=self.load(kf), K=self.adapter.K_net, pose=self.state.pose(kf),
            uv=torch.zeros(0, 2, device="cpu"), depth=torch.zeros(0, device="cpu"), segment=self.state.segment(kf)))
        if self.clock is not None:  # the keyframe image's decode included
            self.clock.charge(1000.0 * (time.perf_counter() - t), "tick")
        row = self.row(kf)
        row.took(info)
        row.n_sparse = len(self.state.sparse_depth(kf)[1])
        self.rows.append(row)
        return info

    def _train(self, steps: int) -> None:
        """The pending batch's ``steps`` optimiser steps and its consolidation; its row updated."""
        if self.adapter is None or self.adapter.pending is None:
            return
        info = self.adapter.train_pending(steps)
        assert info is not None  # a batch was pending
        self.row_of[info.kf_id].took(info)

    def _join_segment(self, kf: int) -> None:
        """The first keyframe of a new segment: join it to the map before it (``vo.bridge_segments``)."""
        seg = self.state.segment(kf)
        if seg in self._segments:
            return
        first = not self._segments
        self._segments.add(seg)
        if first or not self.cfg.vo.bridge_segments:
            return
        t = time.perf_counter()
        snap = self.state.snapshot(self.run.seq.frames, covisibility=False)
        b = plan_bridge(snap, kf, self._depth_of(), self.run.seq.load_gray, self.run.seq.intrinsics)
        if b is not None and b.refused:
            self.refused.append(b)
        elif b is not None:
            self.writer.transform_segment(b.segment, b.sim3(), b.onto)
            self.bridges.append(b)
        self._busy("bridge_s", kf, time.perf_counter() - t)

    def _global_ba(self, kf: int) -> None:
        """Culling + global BA of keyframes ≤ ``kf`` with the network of now; the refinement back to the map."""
        if self.ba is None:
            return
        t = time.perf_counter()
        refine_map(self.writer, kf, self.ba, self._depth_of(), self._val_loss)
        self._busy("ba_s", kf, time.perf_counter() - t)

    def row(self, kf: int) -> KeyframeRow:
        """Keyframe ``kf``'s row, made on first use (work on it may come before its tick: a merge, a bridge)."""
        if kf not in self.row_of:
            self.row_of[kf] = KeyframeRow(kf)
        return self.row_of[kf]

    def keyframe_rows(self) -> list[KeyframeRow]:
        """``keyframes.csv``: a row per keyframe — Algorithm 1's, and for keyframes it did not tick (scheme
        ``none``, a segment kept apart) the work done on them (bridge, merge, loop seconds)."""
        why = "a segment no bridge joined" if self.adapter is not None else "scheme none"
        rows = [self.row_of.get(k) or KeyframeRow(k) for k in range(self.state.n_keyframes)]
        for r in rows:
            if r.info is None:
                r.not_ticked = why
        return rows

    # ------------------------------------------------------------------ helpers
    def _val_loss(self, ids: list[int]) -> dict[int, float]:
        return self.adapter.per_keyframe_val_loss(ids) if self.adapter is not None else {}

    def _depth_of(self) -> DepthOf:
        return depth_predictor(self.net, self.load, self.fast, self.adapter.buffer if self.adapter else None)

    def _busy(self, key: str, kf: int, seconds: float) -> None:
        """``seconds`` of work on keyframe ``kf`` (a bridge, a BA): into its row and onto the clock, where the
        map changes it made take hold when it ends."""
        self.row(kf).add_seconds(key, seconds)
        self._mark(key[:-2])
        if self.clock is not None:
            self.clock.charge(1000.0 * seconds, key[:-2])
            assert isinstance(self.writer, DeferredMap)  # the realtime schedule's
            self.writer.finish(self.clock.now_ms)

    def _backend(self, key: str, kf: int, work: Callable[[], float]) -> None:
        """A merge's or loop closure's work on keyframe ``kf``: its BA's seconds booked as BA, the rest as ``key``."""
        ba0 = self.closer.ba_seconds if self.closer is not None else 0.0
        seconds = work()
        ba = (self.closer.ba_seconds if self.closer is not None else 0.0) - ba0
        self._busy(key, kf, seconds - ba)
        if ba:
            self._busy("ba_s", kf, ba)

    def score_before(self, frame: int, kf: int) -> None:
        """Online scores of the frames before ``frame`` not scored yet, with the weights now (after ``kf``'s steps)."""
        if self.scorer is not None:
            done = self.scorer.seconds
            self.scorer.score_until(self.net, frame, kf)
            if self.scorer.seconds > done:  # it scored frames (and may have refreshed its weights)
                self._mark("score")

    def _mark(self, kind: str) -> None:
        if self.adapter is not None:
            self.adapter.step_log.mark(kind)

    def _report(self, kf: int, t0: float) -> None:
        if self.run.progress is not None:
            row = self.row_of[kf].to_row() if kf in self.row_of else {"kf_id": kf}
            self.run.progress("adapt", {"done": kf + 1, "total": None, **row, "elapsed_s": time.perf_counter() - t0})

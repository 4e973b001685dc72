"""The front end's events, frame by frame, into the map the adaptation loop reads (DESIGN §5, §9).

:class:`FrontEndSource` owns the loop's :class:`~mutualslam_cli.map.state.MapState` (:attr:`~FrontEndSource.state`)
and advances it one frame at a time: from the per-sequence journal (:mod:`~mutualslam_cli.vo.journal_cache`)
while there is one, else from the live front end. A change from the network's side — a segment joined
to the map (a bridge), a global BA's refinement — is made, with ``live_feedback``, in the live front end,
which goes on from it (its events reach the state like any other); a source that reads a cached journal
first resumes the front end at that frame (:mod:`~mutualslam_cli.vo.checkpoint`: the latest resumption
point, then the frames after it again, checked event by event against the journal). Without
``live_feedback`` (hindsight labels, the oracles) the front end has finished first and the change is
made in the state only.

The journal up to the first change does not depend on the network: :meth:`FrontEndSource.close`
stores it (with the resumption points) when it is longer than the cached one, for the next run.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Generator, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence, grey_frames
from mutualslam_cli.errors import CacheMismatch, DatasetError
from mutualslam_cli.geometry import pinhole
from mutualslam_cli.map.journal import Event
from mutualslam_cli.map.refinement import MapRefinement, apply_refinement
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.sim3 import Sim3
from mutualslam_cli.map.state import MapState, events_from_result
from mutualslam_cli.types import Progress
from mutualslam_cli.vo import checkpoint
from mutualslam_cli.vo.depth_oracle import run_oracle
from mutualslam_cli.vo.faults import corrupt_depths
from mutualslam_cli.vo.frontend import FrontEnd
from mutualslam_cli.vo.journal_cache import CHECKPOINT_EVERY, JournalEntry, cache_path, load_entry, save_entry
from mutualslam_cli.vo.pose_oracle import run_pose_oracle
from mutualslam_cli.vo.scale_check import DepthHint

log = logging.getLogger(__name__)


class FrontEndSource:
    """The front end of one run, frame by frame (module docstring).

    Args:
        seq: the sequence.
        cfg: the run's config: ``vo`` and ``seed`` run the front end; its journal is keyed by those, ``data`` and
            ``threads`` as well (:func:`~mutualslam_cli.vo.journal_cache.vo_cache_key`), so the whole config, not a
            section.
        cache_dir: where journals are kept (``None``: no cache).
        progress: ``progress("vo", info)`` after each frame.
        live_feedback: changes reach the live front end (causal labels, our VO); else the state only.

    Attributes:
        state: the map as it stands after the last frame advanced (and the changes made since).
        frame: the last frame advanced (−1 before the first).
        replayed: frames taken from the cached journal.
        changed_at: the frame of the first change (``None``: none yet).
        seconds: wall time spent advancing the front end (decoding, tracking, replay).
    """

    def __init__(self, seq: Sequence, cfg: RunConfig, cache_dir: Path | None = None,
                 progress: Progress | None = None, live_feedback: bool = False) -> None:
        if len(seq) == 0:
            raise DatasetError(f"{seq.root}: sequence has no frames")
        self.seq, self.cfg, self.n = seq, cfg, len(seq)
        self.progress = progress
        self.state = MapState(pinhole(seq.intrinsics), self.n)
        self.path = cache_path(cache_dir, seq, cfg) if cache_dir is not None else None
        self.live_feedback = live_feedback and cfg.vo.mode == "svo"
        self.entry = load_entry(self.path) if self.path is not None else None
        if self.entry is not None and self.entry.n_frames != self.n:
            self.entry = None
        if cfg.vo.mode != "svo" and (self.entry is None or not self.entry.complete):
            self.entry = self._oracle_entry()
        self._bounds = np.zeros(0, np.int64)
        if self.entry is not None:
            frames = np.array([e.frame for e in self.entry.events], np.int64)
            self._bounds = np.searchsorted(frames, np.arange(self.n + 1), side="left")
        self.live: FrontEnd | None = None
        self._frames: Generator[tuple[int, np.ndarray], None, None] | None = None
        self._live_pos = 0
        self.pure: list[Event] = []
        self.pure_ckpts: dict[int, dict[str, np.ndarray]] = {}
        self._ck_keyframes = 0
        self.changed_at: int | None = None
        self.frame = -1
        self.replayed = 0
        self.seconds = 0.0
        self._kf_seen = 0
        self._meta: dict | None = None
        self._hint: DepthHint | None = None

    def use_network(self, hint: DepthHint) -> None:
        """The live front end asks the network at each keyframe from now on (``vo.depth_seeds`` /
        ``vo.scale_prior``, live feedback only: :mod:`~mutualslam_cli.vo.depth_prior`). Its output then depends
        on the network from the first keyframe that asked: no frame is replayed from the journal (it holds the
        front end without the network) and the journal is stored up to the frame before that keyframe."""
        vo = self.cfg.vo
        if not (self.live_feedback and (vo.depth_seeds or vo.scale_prior)):
            return
        if self.frame >= 0:
            raise RuntimeError("use_network() of a source advanced part of the way")
        self.entry, self._bounds = None, np.zeros(0, np.int64)

        def asked(frame: int) -> np.ndarray:
            if self.changed_at is None:  # this frame's events are the network's doing: not the cache's
                self.changed_at = frame - 1
                log.info("front end: the network's depth first asked at frame %d", frame)
            return hint(frame)

        self._hint = asked

    # ------------------------------------------------------------------ advancing
    def advance(self) -> int:
        """Advance the state by the next frame's events; returns the frame's index."""
        t0 = time.perf_counter()
        i = self.frame + 1
        e = self.entry
        if self.live is None and e is not None and i <= e.until:
            for ev in e.events[self._bounds[i]:self._bounds[i + 1]]:
                self._apply(ev)
            if i in e.checkpoints and self.changed_at is None:
                self.pure_ckpts[i] = e.checkpoints[i]
            self.replayed += 1
        else:
            fe = self._ensure_live()
            self._step(fe, i)
            self._drain()
            self._maybe_checkpoint(fe)
        self.frame = i
        self.seconds += time.perf_counter() - t0
        if self.progress is not None:
            self.progress("vo", self._progress_info())
        return i

    def frames(self) -> Iterator[int]:
        """Advance frame by frame to the end, yielding each frame's index after its events."""
        while self.frame < self.n - 1:
            yield self.advance()

    def run_all(self) -> None:
        """Advance to the end (the front end on its own)."""
        for _ in self.frames():
            pass

    def timeline(self) -> Iterator[tuple[int, list[int]]]:
        """``(frame, keyframes created at it)`` in frame order. A source not advanced yet advances frame by
        frame (the state is the map as it stood at each frame); one already at the end (hindsight) yields the
        keyframes by their creation frame over its final state."""
        if self.frame < self.n - 1:
            if self.frame >= 0:
                raise RuntimeError("timeline() of a source advanced part of the way")
            for i in self.frames():
                yield i, self.new_keyframes()
            return
        by_frame: dict[int, list[int]] = {}
        for k, f in enumerate(self.state.created_at):
            by_frame.setdefault(f, []).append(k)
        self._kf_seen = self.state.n_keyframes
        for i in range(self.n):
            yield i, by_frame.get(i, [])

    def new_keyframes(self) -> list[int]:
        """Ids of the keyframes created since the last call, in order."""
        n = self.state.n_keyframes
        out = list(range(self._kf_seen, n))
        self._kf_seen = n
        return out

    # ------------------------------------------------------------------ changes from the network's side
    def settle(self) -> None:
        """Before the map is read for a change: the live front end applies its pending windowed BA now."""
        if self.live_feedback:
            self._change().settle()
            self._drain()

    def transform_segment(self, segment: int, S: Sim3, onto: int) -> None:
        """Join ``segment`` to segment ``onto`` by the similarity ``S`` (a bridge, a merge), now."""
        if self.live_feedback:
            fe = self._change()
            fe.transform_segment(segment, S, onto)
            self._drain()
        else:
            self.state.transform_segment(segment, S, onto)

    def refine(self, r: MapRefinement) -> None:
        """A global BA's refinement of the map, now."""
        if self.live_feedback:
            fe = self._change()
            fe.refine(r)
            self._drain()
        else:
            apply_refinement(self.state, r)

    def inject_outliers(self, fraction: float, seed: int) -> np.ndarray:
        """The ``vo.inject_outliers`` test knob on the finished map: gross depth errors in ``round(fraction · P)``
        points (:func:`~mutualslam_cli.vo.faults.inject_outliers`); returns their ids. Hindsight only: a live
        front end would never see them."""
        if self.live_feedback:
            raise RuntimeError("inject_outliers(): the live front end would not see the faults (hindsight only)")
        return corrupt_depths(self.state, self.result(), fraction, seed)

    # ------------------------------------------------------------------ results
    def result(self) -> VOResult:
        """The map now as a :class:`~mutualslam_cli.map.result.VOResult`, with the front end's counters."""
        if self.live is not None:
            return self.state.snapshot(self.seq.frames, self.live.stats())
        vo = self.state.snapshot(self.seq.frames)
        return replace(vo, meta=dict(self.entry.meta)) if self.entry is not None and self.entry.meta else vo

    @property
    def from_cache(self) -> bool:
        """Whether any frame came from the cached journal."""
        return self.replayed > 0

    def close(self) -> None:
        """Stop the live front end and store the journal up to the first change, when longer than the cache's."""
        if self.live is not None and self.live.mapper.pool is not None:
            self.live.mapper.close()
        if self._frames is not None:
            self._frames.close()
        if self.path is None or self.cfg.vo.mode != "svo":
            return
        until = self.frame if self.changed_at is None else self.changed_at
        if until < 0 or (self.entry is not None and self.entry.until >= until):
            return
        complete = until >= self.n - 1
        meta = self.result().meta if complete and self.changed_at is None else {}
        save_entry(self.path, JournalEntry(self.pure, until, self.n,
                                           {f: c for f, c in self.pure_ckpts.items() if f <= until}, meta))

    # ------------------------------------------------------------------ internals
    def _apply(self, ev: Event) -> None:
        self.state.apply(ev)
        if self.changed_at is None:
            self.pure.append(ev)

    def _step(self, fe: FrontEnd, i: int) -> None:
        assert self._frames is not None
        j, gray = next(self._frames)
        assert j == i
        fe.process(i, gray)
        if i == self.n - 1:
            fe.finish()

    def _drain(self) -> None:
        fe = self.live
        assert fe is not None
        new = fe.journal.events[self._live_pos:]
        for ev in new:
            self._apply(ev)
        if self.changed_at is not None:  # nothing more to cache: the journal need not grow
            fe.journal.events.clear()
            self._live_pos = 0
        else:
            self._live_pos = len(fe.journal.events)

    def _maybe_checkpoint(self, fe: FrontEnd) -> None:
        if self.changed_at is not None or self.path is None:
            return
        if self.state.n_keyframes - self._ck_keyframes >= CHECKPOINT_EVERY and checkpoint.resumable(fe):
            self.pure_ckpts[fe.st.frame] = checkpoint.capture(fe)
            self._ck_keyframes = self.state.n_keyframes

    def _change(self) -> FrontEnd:
        fe = self._ensure_live()
        if self.changed_at is None:
            self.changed_at = self.frame
            log.info("front end: first change from the network's side at frame %d", self.frame)
        return fe

    def _ensure_live(self) -> FrontEnd:
        """The live front end, in the state after :attr:`frame` (resumed from the journal when needed)."""
        if self.live is not None:
            return self.live
        upto, e = self.frame, self.entry
        cks = [f for f in (e.checkpoints if e is not None else {}) if f <= upto]
        if cks:
            c = max(cks)
            assert e is not None  # the checkpoints are the entry's
            fe = checkpoint.restore(self.seq, self.cfg.vo, self.cfg.seed, e.events[:self._bounds[c + 1]],
                                    e.checkpoints[c])
            start = c + 1
        else:
            fe = FrontEnd(self.seq, self.cfg.vo, self.cfg.seed)
            start = 0
        if self._hint is not None:
            fe.use_network(self._hint)
        self.live = fe
        self._frames = grey_frames(self.seq, start)
        for i in range(start, upto + 1):  # again, silently: the state has these events already
            assert e is not None  # without a live front end the frames so far were replayed from the entry
            self._step(fe, i)
            got = fe.journal.events[self._live_pos:]
            want = e.events[self._bounds[i]:self._bounds[i + 1]]
            if len(got) != len(want) or not all(a.same(b) for a, b in zip(got, want)):
                raise CacheMismatch(f"{self.path}: the cached front end differs from the front end run again at "
                                    f"frame {i}; delete the file and run again")
            self._live_pos = len(fe.journal.events)
        if upto >= start:
            log.info("front end resumed at frame %d (from %s)", upto, f"frame {start - 1}" if start else "the start")
        return fe

    def _oracle_entry(self) -> JournalEntry:
        """The oracle front end's whole result as a journal (cached like ours)."""
        seq, cfg, progress = self.seq, self.cfg, self.progress
        cb = (lambda info: progress("vo", info)) if progress else None
        if cfg.vo.mode == "gt":  # pose oracle: our VO's tracks (cached like any svo run) re-triangulated with GT poses
            ours = FrontEndSource(seq, replace(cfg, vo=replace(cfg.vo, mode="svo")),
                                  self.path.parent if self.path is not None else None, self.progress)
            ours.run_all()
            svo = ours.result()
            ours.close()
            vo = run_pose_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb, vo=svo)
        else:
            vo = run_oracle(seq, cfg.vo, seed=cfg.seed, progress=cb)
        entry = JournalEntry(events_from_result(vo, self.n), self.n - 1, self.n, {}, dict(vo.meta))
        if self.path is not None:
            save_entry(self.path, entry)
        return entry

    def _progress_info(self) -> dict:
        if self.live is not None:
            return self.live.progress_info()
        return {"frame": self.frame, "n_frames": self.n, "keyframes": self.state.n_keyframes, "tracked": 0,
                "fps": 0.0, "state": "cached"}

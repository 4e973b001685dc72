"""The map and frame records at one time: what the front end's events build (DESIGN §5).

:class:`MapState` is the map's one writer: every change to the keyframes, points and frame records is one of
its methods (the store's own mutators are private). It is one object for two roles. The front end owns one
and changes it through those methods, each change journaled (:mod:`~mutualslam_cli.map.journal`). The
adaptation loop owns a *replica* and :meth:`MapState.apply`\\ s the same events in the same order, frame by frame, so at
the loop's time t its replica is the front end's map as it stood at t: the labels of a training
step (:meth:`sparse_depth`, :meth:`pose`), the map a bridge or a global BA starts from
(:meth:`snapshot`) — never a later state. Replayed from a cached journal it is the same, bit for bit.
"""

from __future__ import annotations

import copy
from collections.abc import Container

import numpy as np

from mutualslam_cli.geometry import project
from mutualslam_cli.map.assemble import RunStats, build_result
from mutualslam_cli.map.journal import Event, Journal
from mutualslam_cli.map.records import Relocalised
from mutualslam_cli.map.result import Keyframe, VOResult
from mutualslam_cli.map.sim3 import Sim3, rescaled
from mutualslam_cli.map.store import Map
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import FrameRef, Intrinsics


class MapState:
    """Keyframes, map points and frame records (which frame was tracked, relative to which keyframe).

    Args:
        intr: the pinhole camera of poses and pixels (``VOResult.intrinsics``).
        n_frames: frames of the sequence.
        journal: where changes are recorded (the front end's state); ``None`` for a replica.

    Attributes:
        map: keyframes and points (:class:`~mutualslam_cli.map.store.Map`).
        frame_rel: tracked frame → ``(reference keyframe, T_kf,c)``; a frame follows its keyframe.
        frame_seg: ``(N,)`` segment of each frame, −1 = not tracked.
        init_methods: how each segment was initialised, in order.
        relocalisations: one :class:`~mutualslam_cli.map.records.Relocalised` per accepted relocalisation.
        losses: ``(frame, reason, why)`` of each tracking loss (``reason`` one of
            :data:`~mutualslam_cli.map.assemble.LOSS_REASONS`).
        created_at: the front end's frame when each keyframe was created (replicas only: the clock of
            its :class:`~mutualslam_cli.map.journal.Event`).
        joined: ``{segment: onto}``: the segments a bridge joined to another (one map unit, :meth:`unit`).
    """

    def __init__(self, intr: Intrinsics, n_frames: int, journal: Journal | None = None) -> None:
        self.intr, self.K = intr, intr.K()
        self._journal = journal
        self.map = Map(journal=journal)
        self.frame_rel: dict[int, tuple[int, np.ndarray]] = {}
        self.frame_seg = -np.ones(n_frames, np.int64)
        self.init_methods: list[str] = []
        self.relocalisations: list[Relocalised] = []
        self.losses: list[tuple[int, str, str]] = []
        self.created_at: list[int] = []
        self.joined: dict[int, int] = {}

    @property
    def journal(self) -> Journal | None:
        """Where changes are recorded (``None``: not journaled, e.g. while a checkpoint replays the past)."""
        return self._journal

    @journal.setter
    def journal(self, journal: Journal | None) -> None:
        self._journal = self.map.journal = journal

    def _emit(self, kind: str, **data: object) -> None:
        if self._journal is not None:
            self._journal.emit(kind, **data)

    def fork(self) -> MapState:
        """A deep copy to change on the side (the map of a delayed change,
        :class:`~mutualslam_cli.online.realtime.DeferredMap`); its journal copied too (the original untouched)."""
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ the map's changes (the store's writers)
    def add_keyframe(self, frame: int, t: float, T_wc: np.ndarray, segment: int) -> int:
        """A keyframe made from ``frame`` (timestamp ``t`` s) at ``T_wc`` ``(4, 4)`` in ``segment``; returns its id."""
        return self.map._add_keyframe(frame, t, T_wc, segment)

    def set_poses(self, kfs: np.ndarray, T_wc: np.ndarray) -> None:
        """Keyframes ``kfs`` ``(n,)`` take the poses ``T_wc`` ``(n, 4, 4)`` (their points' ``Xw``: :meth:`refresh`)."""
        self.map._set_poses(kfs, T_wc)

    def add_points(self, host: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray, rho: np.ndarray,
                   sigma: np.ndarray, obs: list[dict[int, np.ndarray]]) -> np.ndarray:
        """New map points ``(n,)``: host keyframes, host pixels ``(n, 2)`` (undistorted) and normalised ``(n, 2)``,
        inverse depths (1/map units) and their σ, observations ``{kf: (2,) px}`` (the host's included); returns
        their ids."""
        return self.map._add_points(host, px_h, xn_h, rho, sigma, obs)

    def refresh(self, pids: np.ndarray) -> None:
        """Recompute the world positions of points ``pids`` from their hosts' poses and their inverse depths."""
        self.map._refresh(pids)

    def observe(self, kf: int, pids: np.ndarray, px: np.ndarray) -> None:
        """Keyframe ``kf`` observes points ``pids`` at undistorted pixels ``px`` ``(n, 2)``."""
        self.map._observe(kf, pids, px)

    def set_depths(self, pids: np.ndarray, rho: np.ndarray) -> None:
        """Points ``pids`` take the inverse depths ``rho`` (1/map units; ``Xw``: :meth:`refresh`)."""
        self.map._set_depths(pids, rho)

    def remove_observations(self, pids: np.ndarray, kfs: np.ndarray) -> None:
        """Keyframe ``kfs[j]`` no longer observes point ``pids[j]``."""
        self.map._remove_observations(pids, kfs)

    def remove_points(self, pids: np.ndarray) -> None:
        """Points ``pids`` leave the map (no observation, NaN depth; their ids stay taken)."""
        self.map._remove_points(pids)

    def fuse_points(self, young: np.ndarray, old: np.ndarray) -> None:
        """Point ``young[j]`` is point ``old[j]`` seen again: its observations go to ``old[j]``, it leaves the map."""
        self.map._fuse_points(young, old)

    def set_host_pixels(self, pids: np.ndarray, px_h: np.ndarray, xn_h: np.ndarray) -> None:
        """Points ``pids`` move to host pixels ``px_h`` (undistorted) and ``xn_h`` (normalised), ``(n, 2)`` each."""
        self.map._set_host_pixels(pids, px_h, xn_h)

    # ------------------------------------------------------------------ the front end's changes
    def track_frame(self, i: int, segment: int, ref: int, T_rel: np.ndarray) -> None:
        """Frame ``i`` was tracked in ``segment`` at ``T_ref,c = T_rel`` from keyframe ``ref``."""
        self.frame_rel[i] = (ref, np.array(T_rel, np.float64))
        self.frame_seg[i] = segment
        self._emit("frame", index=i, segment=segment, ref=ref, T_rel=T_rel)

    def start_segment(self, segment: int, frame: int, method: str) -> None:
        """A new tracking segment initialised at ``frame`` by ``method``."""
        self.init_methods.append(method)
        self._emit("segment", segment=segment, index=frame, method=method)

    def lose(self, frame: int, reason: str, why: str) -> None:
        """Tracking was lost at ``frame``: ``reason`` a short code, ``why`` the detail."""
        self.losses.append((frame, reason, why))
        self._emit("lost", index=frame, reason=reason, why=why)

    def relocalise(self, r: Relocalised) -> None:
        """A relocalisation was accepted."""
        self.relocalisations.append(r)
        self._emit("reloc", index=r.frame, t=r.timestamp, keyframe=r.keyframe, inliers=r.inliers,
                   frames_lost=r.frames_lost, candidates_tried=r.candidates_tried)

    def transform_segment(self, segment: int, S: Sim3, onto: int) -> np.ndarray:
        """Move ``segment`` by the similarity ``S`` (``x ↦ s·R·x + t``: keyframes, hosted points, its frames' relative
        translations ×s) into the frame and unit of segment ``onto`` (a bridge); returns the hosted points' ids."""
        hosted = self.map._transform_segment(segment, S.as_float64())
        for i, (ref, T) in self.frame_rel.items():
            if self.frame_seg[i] == segment:
                self.frame_rel[i] = (ref, rescaled(T, S.s))
        self.joined[segment] = onto
        self._emit("similarity", segment=segment, onto=onto, s=S.s, R=S.R, t=S.t)
        return hosted

    def rescale_frames(self, kfs: np.ndarray, scales: np.ndarray) -> None:
        """Frames tracked from keyframe ``kfs[j]`` keep their place relative to it in a unit ``scales[j]`` times
        larger (a pose graph's Sim(3) correction of that keyframe)."""
        by_kf = dict(zip(np.asarray(kfs).tolist(), np.asarray(scales, float).tolist()))
        for i, (ref, T) in self.frame_rel.items():
            if ref in by_kf:
                self.frame_rel[i] = (ref, rescaled(T, by_kf[ref]))
        self._emit("rescale", kfs=kfs, scales=scales)

    def unit(self, segment: int) -> int:
        """The map unit (frame and scale) of ``segment``: the first segment of the chain of bridges it was
        joined by; its own when no bridge joined it."""
        seen = set()
        while segment in self.joined and segment not in seen:
            seen.add(segment)
            segment = self.joined[segment]
        return segment

    # ------------------------------------------------------------------ a replica
    def apply(self, e: Event) -> None:
        """Replay one event of the front end's journal (the same change, the same order)."""
        m, k = self.map, e.kind
        if k == "keyframe":
            kf = self.add_keyframe(e["frame"], e["t"], e["T_wc"][0], e["segment"])
            if kf != e["kf"]:
                raise ValueError(f"journal out of order: keyframe {e['kf']} replayed as {kf}")
            self.created_at.append(e.frame)
        elif k == "pose":
            self.set_poses(e["kfs"], e["T_wc"])
        elif k == "points":
            if e["first"] != len(m.host):
                raise ValueError(f"journal out of order: point {e['first']} replayed as {len(m.host)}")
            cut = np.cumsum(e["obs_n"])[:-1]
            obs = [dict(zip(ks.tolist(), px)) for ks, px in zip(np.split(e["obs_kf"], cut), np.split(e["obs_px"], cut))]
            self.add_points(e["host"], e["px_h"], e["xn_h"], e["rho"], e["sigma"], obs)
        elif k == "observe":
            self.observe(e["kf"], e["pids"], e["px"])
        elif k == "depth":
            self.set_depths(e["pids"], e["rho"])
        elif k == "unobserve":
            self.remove_observations(e["pids"], e["kfs"])
        elif k == "refresh":
            self.refresh(e["pids"])
        elif k == "remove":
            self.remove_points(e["pids"])
        elif k == "pixel":
            self.set_host_pixels(e["pids"], e["px_h"], e["xn_h"])
        elif k == "similarity":
            self.transform_segment(e["segment"], Sim3(e["R"], e["t"], e["s"]), e["onto"])
        elif k == "rescale":
            self.rescale_frames(e["kfs"], e["scales"])
        elif k == "frame":
            self.track_frame(e["index"], e["segment"], e["ref"], e["T_rel"][0])
        elif k == "segment":
            self.start_segment(e["segment"], e["index"], e["method"])
        elif k == "lost":
            self.lose(e["index"], e["reason"], e["why"])
        elif k == "reloc":
            self.relocalise(Relocalised(e["index"], e["t"], e["keyframe"], e["inliers"], e["frames_lost"],
                                        e["candidates_tried"]))
        else:  # pragma: no cover - SCHEMA and this dispatch list the same kinds
            raise ValueError(f"unknown event kind {k!r}")

    # ------------------------------------------------------------------ what the loop and the back end read
    @property
    def n_keyframes(self) -> int:
        return len(self.map.kf_frame)

    def frame_of(self, kf: int) -> int:
        """The sequence frame keyframe ``kf`` was made from."""
        return self.map.kf_frame[kf]

    def time_of(self, kf: int) -> float:
        """The timestamp of keyframe ``kf``'s frame (seconds)."""
        return self.map.kf_time[kf]

    def pose(self, kf: int) -> np.ndarray:
        """``(4, 4)`` ``T_wc`` of keyframe ``kf`` now (a copy)."""
        return self.map.kf_T_wc[kf].copy()

    def pose_cw(self, kf: int) -> np.ndarray:
        """``(4, 4)`` ``T_cw`` (world to camera) of keyframe ``kf`` now (a copy)."""
        return self.map.T_cw(kf)

    def segment(self, kf: int) -> int:
        """The tracking segment of keyframe ``kf``."""
        return self.map.kf_segment[kf]

    def unit_of(self, kf: int) -> int:
        """The map unit of keyframe ``kf`` (:meth:`unit` of its segment)."""
        return self.unit(self.map.kf_segment[kf])

    def first_keyframe(self, segment: int) -> int:
        """The first keyframe of tracking segment ``segment``."""
        return min(k for k, sg in enumerate(self.map.kf_segment) if sg == segment)

    def n_shared(self, a: int, b: int) -> int:
        """How many map points keyframes ``a`` and ``b`` both observe now."""
        return len(self.map.kf_points[a] & self.map.kf_points[b])

    def points_world(self, pids: np.ndarray) -> np.ndarray:
        """``(n, 3)`` world positions of map points ``pids`` now (a copy)."""
        return self.map.Xw[pids]

    def hosted_points(self, kfs: Container[int]) -> np.ndarray:
        """``(n,)`` int64 ids, ascending, of the map points hosted by keyframes in ``kfs`` with a finite depth."""
        m = self.map
        return np.array([p for p, h in enumerate(m.host) if h in kfs and np.isfinite(m.rho[p])], np.int64)

    def host_of(self, pid: int) -> int:
        """The host keyframe of map point ``pid``."""
        return self.map.host[pid]

    def inv_depth(self, pid: int) -> float:
        """The inverse depth of map point ``pid`` along its host ray (1/map units; NaN once removed)."""
        return self.map.rho[pid]

    def host_pixel(self, pid: int) -> np.ndarray:
        """``(2,)`` the host pixel of map point ``pid`` (undistorted pinhole; a copy)."""
        return self.map.px_h[pid].copy()

    def sparse_depth(self, kf: int) -> tuple[np.ndarray, np.ndarray]:
        """The map points keyframe ``kf`` observes now, projected into it with its pose now: pixels
        ``(M, 2)`` (VO camera) and depths ``(M,)`` (map units, > 0, inside the image) — D_sparse of Eq. 6."""
        m = self.map
        pids = np.fromiter(sorted(m.kf_points[kf]), np.int64, len(m.kf_points[kf]))
        if not len(pids):
            return np.zeros((0, 2)), np.zeros(0)
        rho = np.array([m.rho[p] for p in pids.tolist()])
        pids = pids[np.isfinite(rho) & (rho > 0)]
        T = m.poses_cw()[kf]
        pix, z = project(m.Xw[pids] @ T[:3, :3].T + T[:3, 3], self.K)
        ok = (z > 1e-6) & in_image(pix, self.intr.width, self.intr.height)
        return pix[ok], z[ok]

    def snapshot(self, frames: list[FrameRef], stats: RunStats | None = None, covisibility: bool = True) -> VOResult:
        """The map now as a :class:`~mutualslam_cli.map.result.VOResult` (point ids = map ids; removed and
        non-positive-depth points left out); ``stats``: the front end's counters (default: what the events say);
        ``covisibility=False`` skips the keyframe graph (a mid-run snapshot)."""
        if stats is None:
            stats = RunStats(segment=len(self.init_methods) - 1, init_methods=list(self.init_methods), timing={},
                             total_s=0.0, reprojected=0, ba_stats=(), ba_threaded=False,
                             relocalisations=list(self.relocalisations), losses=list(self.losses))
        units = {sg: self.unit(sg) for sg in set(self.map.kf_segment) if self.unit(sg) != sg}
        return build_result(self.map, frames, self.frame_rel, self.frame_seg, self.intr, stats, covisibility, units)


def events_from_result(vo: VOResult, n_frames: int) -> list[Event]:
    """A finished front end's result as a journal in frame order, for the oracle front ends, which make
    their whole map at once: at each keyframe's frame the keyframe, the points it hosts (with their
    observations by it and earlier keyframes) and its observations of earlier points; each tracked frame
    relative to the latest keyframe of its segment at or before it (at the segment's first keyframe's
    frame when it comes before that). A replica of it ends as ``vo`` (point ids renumbered in host order)."""
    journal = Journal()
    state = MapState(vo.intrinsics, n_frames, journal)
    K = vo.intrinsics.K()
    pts = vo.points
    kfs = sorted(vo.keyframes, key=lambda k: (k.frame_index, k.id))
    hosted_by = {k.id: np.flatnonzero(pts.host == k.id) for k in kfs}
    seen_by: dict[int, list[tuple[int, np.ndarray]]] = {}
    for p, (ks, pxs) in enumerate(zip(pts.observations, pts.obs_pixels)):
        for k, px in zip(ks.tolist(), pxs):
            if k != pts.host[p]:
                seen_by.setdefault(k, []).append((p, px))
    tracked = np.flatnonzero(vo.frame_segment >= 0)
    frames_at: dict[int, list[tuple[int, Keyframe, np.ndarray]]] = {}
    if len(tracked) == len(vo.traj_all.poses):
        for f, T in zip(tracked.tolist(), vo.traj_all.poses):
            cands = [k for k in kfs if k.segment == vo.frame_segment[f]]
            if cands:
                ref = ([k for k in cands if k.frame_index <= f] or cands[:1])[-1]
                frames_at.setdefault(max(f, ref.frame_index), []).append((f, ref, T))
    kf_at: dict[int, list[Keyframe]] = {}
    for k in kfs:
        kf_at.setdefault(k.frame_index, []).append(k)
    local: dict[int, int] = {}
    new_id = np.full(len(pts), -1, np.int64)
    segments: set[int] = set()
    for f in range(n_frames):
        journal.frame = f
        for kf in kf_at.get(f, []):
            if kf.segment not in segments:
                segments.add(kf.segment)
                state.start_segment(kf.segment, f, str(vo.meta.get("mode", "oracle")))
            local[kf.id] = state.add_keyframe(f, kf.timestamp, kf.pose, kf.segment)
            known = [(p, px) for p, px in seen_by.get(kf.id, []) if new_id[p] >= 0]
            if known:
                state.observe(local[kf.id], new_id[[p for p, _ in known]], np.array([px for _, px in known]))
            hosted = hosted_by[kf.id]
            if len(hosted):
                obs = [{local[o]: px for o, px in zip(pts.observations[p].tolist(), pts.obs_pixels[p]) if o in local}
                       for p in hosted]
                new_id[hosted] = state.add_points(np.full(len(hosted), local[kf.id]), pts.pixel[hosted],
                                              (pts.pixel[hosted] - K[:2, 2]) / np.diag(K)[:2], pts.inv_depth[hosted],
                                              pts.sigma[hosted], obs)
        for g, ref, T in frames_at.get(f, []):
            state.track_frame(g, int(vo.frame_segment[g]), local[ref.id], np.linalg.inv(ref.pose) @ T)
    return journal.events

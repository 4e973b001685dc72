"""The map and frame records at one time: what the front end's events build (DESIGN §5).

:class:`MapState` is one object for two roles. The front end owns one and changes it through its
methods, each change journaled (:mod:`~mutualslam_cli.vo.journal`). The adaptation loop owns a
*replica* and :meth:`MapState.apply`\\ s the same events in the same order, frame by frame, so at
the loop's time t its replica is the front end's map as it stood at t: the labels of a training
step (:meth:`sparse_depth`, :meth:`pose`), the map a bridge or a global BA starts from
(:meth:`snapshot`) — never a later state. Replayed from a cached journal it is the same, bit for bit.
"""

from __future__ import annotations

from collections.abc import Container
from typing import TYPE_CHECKING, Any

import numpy as np

from mutualslam_cli.geometry import project
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import FrameRef, Intrinsics
from mutualslam_cli.vo.assemble import RunStats, build_result
from mutualslam_cli.vo.journal import Event, Journal
from mutualslam_cli.vo.result import VOResult
from mutualslam_cli.vo.state import Map

if TYPE_CHECKING:
    from mutualslam_cli.vo.relocalise import RelocIndex, Relocalisation


class MapState:
    """Keyframes, map points and frame records (which frame was tracked, relative to which keyframe).

    Args:
        intr: the pinhole camera of poses and pixels (``VOResult.intrinsics``).
        n_frames: frames of the sequence.
        journal: where changes are recorded (the front end's state); ``None`` for a replica.

    Attributes:
        map: keyframes and points (:class:`~mutualslam_cli.vo.state.Map`).
        frame_rel: tracked frame → ``(reference keyframe, T_kf,c)``; a frame follows its keyframe.
        frame_seg: ``(N,)`` segment of each frame, −1 = not tracked.
        init_methods: how each segment was initialised, in order.
        relocalisations: one dict per accepted relocalisation.
        losses: ``(frame, why)`` of each tracking loss.
        created_at: the front end's frame when each keyframe was created (replicas only: the clock of
            its :class:`~mutualslam_cli.vo.journal.Event`).
        joined: ``{segment: onto}``: the segments a bridge joined to another (one map unit, :meth:`unit`).
    """

    def __init__(self, intr: Intrinsics, n_frames: int, journal: Journal | None = None) -> None:
        self.intr, self.K = intr, intr.K()
        self.journal = journal
        self.map = Map(journal=journal)
        self.frame_rel: dict[int, tuple[int, np.ndarray]] = {}
        self.frame_seg = -np.ones(n_frames, np.int64)
        self.init_methods: list[str] = []
        self.relocalisations: list[dict[str, Any]] = []
        self.losses: list[tuple[int, str]] = []
        self.created_at: list[int] = []
        self.joined: dict[int, int] = {}

    def _emit(self, kind: str, **data: Any) -> None:
        if self.journal is not None:
            self.journal.emit(kind, **data)

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

    def lose(self, frame: int, why: str) -> None:
        """Tracking was lost at ``frame``."""
        self.losses.append((frame, why))
        self._emit("lost", index=frame, why=why)

    def relocalise(self, info: dict[str, Any]) -> None:
        """A relocalisation was accepted (``frame``, ``timestamp``, ``keyframe``, ``inliers``, …)."""
        self.relocalisations.append(dict(info))
        self._emit("reloc", index=info["frame"], t=info["timestamp"], keyframe=info["keyframe"],
                   inliers=info["inliers"], frames_lost=info["frames_lost"], candidates_tried=info["candidates_tried"])

    def transform_segment(self, segment: int, R: np.ndarray, t: np.ndarray, s: float, onto: int) -> np.ndarray:
        """Move ``segment`` by ``x ↦ s·R·x + t`` (keyframes, hosted points, its frames' relative
        translations ×s) into the frame and unit of segment ``onto`` (a bridge); returns the hosted points' ids."""
        hosted = self.map.transform_segment(segment, R, t, s)
        for i, (ref, T) in self.frame_rel.items():
            if self.frame_seg[i] == segment:
                T = T.copy()
                T[:3, 3] *= s
                self.frame_rel[i] = (ref, T)
        self.joined[segment] = onto
        self._emit("similarity", segment=segment, onto=onto, s=s, R=R, t=t)
        return hosted

    def rescale_frames(self, kfs: np.ndarray, scales: np.ndarray) -> None:
        """Frames tracked from keyframe ``kfs[j]`` keep their place relative to it in a unit ``scales[j]`` times
        larger (a pose graph's Sim(3) correction of that keyframe)."""
        by_kf = dict(zip(np.asarray(kfs).tolist(), np.asarray(scales, float).tolist()))
        for i, (ref, T) in self.frame_rel.items():
            if ref in by_kf:
                T = T.copy()
                T[:3, 3] *= by_kf[ref]
                self.frame_rel[i] = (ref, T)
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
            kf = m.add_keyframe(e["frame"], e["t"], e["T_wc"][0], e["segment"])
            if kf != e["kf"]:
                raise ValueError(f"journal out of order: keyframe {e['kf']} replayed as {kf}")
            self.created_at.append(e.frame)
        elif k == "pose":
            m.set_poses(e["kfs"], e["T_wc"])
        elif k == "points":
            if e["first"] != len(m.host):
                raise ValueError(f"journal out of order: point {e['first']} replayed as {len(m.host)}")
            cut = np.cumsum(e["obs_n"])[:-1]
            obs = [dict(zip(ks.tolist(), px)) for ks, px in zip(np.split(e["obs_kf"], cut), np.split(e["obs_px"], cut))]
            m.add_points(e["host"], e["px_h"], e["xn_h"], e["rho"], e["sigma"], obs)
        elif k == "observe":
            m.observe(e["kf"], e["pids"], e["px"])
        elif k == "depth":
            m.set_depths(e["pids"], e["rho"])
        elif k == "unobserve":
            m.remove_observations(e["pids"], e["kfs"])
        elif k == "refresh":
            m.refresh(e["pids"])
        elif k == "remove":
            m.remove_points(e["pids"])
        elif k == "pixel":
            m.set_host_pixels(e["pids"], e["px_h"], e["xn_h"])
        elif k == "similarity":
            self.transform_segment(e["segment"], e["R"], e["t"], e["s"], e["onto"])
        elif k == "rescale":
            self.rescale_frames(e["kfs"], e["scales"])
        elif k == "frame":
            self.track_frame(e["index"], e["segment"], e["ref"], e["T_rel"][0])
        elif k == "segment":
            self.start_segment(e["segment"], e["index"], e["method"])
        elif k == "lost":
            self.lose(e["index"], e["why"])
        elif k == "reloc":
            self.relocalise({"frame": e["index"], "timestamp": e["t"], "keyframe": e["keyframe"],
                             "inliers": e["inliers"], "frames_lost": e["frames_lost"],
                             "candidates_tried": e["candidates_tried"]})
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

    def locate(self, index: RelocIndex, gray: np.ndarray, thr: float, seed: int = 0,
               keyframes: list[int] | None = None, newest: int = 2,
               witnesses: list[int] | None = None) -> Relocalisation | None:
        """The pose of the grey image ``gray`` in this map now, by the relocaliser's keyframe ``index``
        (:meth:`~mutualslam_cli.vo.relocalise.RelocIndex.query`: its arguments)."""
        return index.query(gray, self.map, thr, seed=seed, keyframes=keyframes, newest=newest, witnesses=witnesses)

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
        """The map now as a :class:`~mutualslam_cli.vo.result.VOResult` (point ids = map ids; removed and
        non-positive-depth points left out); ``stats``: the front end's counters (default: what the events say);
        ``covisibility=False`` skips the keyframe graph (a mid-run snapshot)."""
        if stats is None:
            stats = RunStats(segment=len(self.init_methods) - 1, init_methods=list(self.init_methods), timing={},
                             total_s=0.0, reprojected=0, ba_stats=(), ba_threaded=False,
                             relocalisations=list(self.relocalisations))
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
    m, K = state.map, vo.intrinsics.K()
    pts = vo.points
    kfs = sorted(vo.keyframes, key=lambda k: (k.frame_index, k.id))
    hosted_by = {k.id: np.flatnonzero(pts.host == k.id) for k in kfs}
    seen_by: dict[int, list[tuple[int, np.ndarray]]] = {}
    for p, (ks, pxs) in enumerate(zip(pts.observations, pts.obs_pixels)):
        for k, px in zip(ks.tolist(), pxs):
            if k != pts.host[p]:
                seen_by.setdefault(k, []).append((p, px))
    tracked = np.flatnonzero(vo.frame_segment >= 0)
    frames_at: dict[int, list[tuple[int, Any, np.ndarray]]] = {}
    if len(tracked) == len(vo.traj_all.poses):
        for f, T in zip(tracked.tolist(), vo.traj_all.poses):
            cands = [k for k in kfs if k.segment == vo.frame_segment[f]]
            if cands:
                ref = ([k for k in cands if k.frame_index <= f] or cands[:1])[-1]
                frames_at.setdefault(max(f, ref.frame_index), []).append((f, ref, T))
    kf_at: dict[int, list[Any]] = {}
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
            local[kf.id] = m.add_keyframe(f, kf.timestamp, kf.pose, kf.segment)
            known = [(p, px) for p, px in seen_by.get(kf.id, []) if new_id[p] >= 0]
            if known:
                m.observe(local[kf.id], new_id[[p for p, _ in known]], np.array([px for _, px in known]))
            hosted = hosted_by[kf.id]
            if len(hosted):
                obs = [{local[o]: px for o, px in zip(pts.observations[p].tolist(), pts.obs_pixels[p]) if o in local}
                       for p in hosted]
                new_id[hosted] = m.add_points(np.full(len(hosted), local[kf.id]), pts.pixel[hosted],
                                              (pts.pixel[hosted] - K[:2, 2]) / np.diag(K)[:2], pts.inv_depth[hosted],
                                              pts.sigma[hosted], obs)
        for g, ref, T in frames_at.get(f, []):
            state.track_frame(g, int(vo.frame_segment[g]), local[ref.id], np.linalg.inv(ref.pose) @ T)
    return journal.events

"""Initialisation part of the front end: reference frame, two-view bootstrap of a segment.

Features detected in a reference frame are tracked with KLT until their median displacement
reaches ``kf_min_parallax_px``; then :func:`~mutualslam_cli.vo.initialization.initialize`
(homography or essential matrix, median depth 1) is tried every frame. On success the
reference becomes keyframe 0 of a new segment, the current frame keyframe 1; the frames in
between get poses from PnP on the stored track positions, so they count as tracked.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from mutualslam_cli.geometry import se3_inv, to_normalized
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.features import detect_grid
from mutualslam_cli.vo.frontend_base import FrontEndBase
from mutualslam_cli.vo.initialization import InitResult, initialize
from mutualslam_cli.vo.state import InitReference, Tracks
from mutualslam_cli.vo.tracking import Pyramid, estimate_pose, klt_track

log = logging.getLogger("mutualslam_cli.vo.frontend")

INIT_POINT_PARALLAX_DEG = 1.0
"""Two-view correspondences triangulated under a smaller angle start as seeds, not map points."""


MAX_INIT_FRAMES = 150
"""A reference frame that has not initialised after this many frames is replaced (bounded memory)."""


class InitMixin(FrontEndBase):
    """Methods of the front end (``_Frontend``) that bring up a new tracking segment."""

    def _start_ref(self, i: int, gray: np.ndarray) -> None:
        pts = detect_grid(gray, self.cfg.grid_size, self.cfg.max_fts)
        self.st.ref = InitReference(i, gray, pts, pts, np.arange(len(pts)))

    def _init_step(self, i: int, gray: np.ndarray, pyr: Pyramid, prev_pyr: Pyramid | None) -> None:
        cfg = self.cfg
        if self._relocalise(i, gray):
            return
        ref = self.st.ref
        stale = ref is None or len(ref.raw) < cfg.min_tracked or len(ref.hist) >= MAX_INIT_FRAMES
        if stale or prev_pyr is None:
            self._start_ref(i, gray)
            return
        assert ref is not None  # not stale
        t0 = time.perf_counter()
        raw, ok = klt_track(prev_pyr, pyr, ref.raw, cfg.klt_window, cfg.klt_levels, cfg.fb_threshold_px)
        self.st.timing["track"] += time.perf_counter() - t0
        ref.raw, ref.alive = raw[ok], ref.alive[ok]
        ref.hist.append((i, ref.alive.copy(), ref.raw.copy()))
        if len(ref.raw) < cfg.min_tracked:
            self._start_ref(i, gray)
            return
        px0, x0 = self._undist(ref.raw0[ref.alive])
        px1, x1 = self._undist(ref.raw)
        if np.median(np.linalg.norm(px1 - px0, axis=1)) < cfg.kf_min_parallax_px:
            return
        if self.reloc is not None and self.st.lost_at >= 0 and i - self.st.lost_at < cfg.reloc_frames:
            return  # the map may still be found again: no new segment yet
        res = initialize(x0, x1, self.thr, min_points=cfg.min_tracked, seed=self.seed + i)
        if res is None:
            return
        self._bootstrap(i, gray, res, px0, px1, x1)

    def _bootstrap(self, i: int, gray: np.ndarray, res: InitResult, px0: np.ndarray, px1: np.ndarray,
                   x1: np.ndarray) -> None:
        """Create the two first keyframes and the initial map of a new segment."""
        ref = self.st.ref
        assert ref is not None  # called by _init_step with its reference
        self.st.segment += 1
        self.state_map.start_segment(self.st.segment, ref.frame, res.method)
        sm = self.state_map
        m = sm.map
        k0 = sm.add_keyframe(ref.frame, self.seq.frames[ref.frame].timestamp, np.eye(4), self.st.segment)
        k1 = sm.add_keyframe(i, self.seq.frames[i].timestamp, se3_inv(res.T_10), self.st.segment)
        # well-triangulated correspondences become map points; the rest become seeds of kf0
        # initialised from their two-view depth (ORB-SLAM keeps only parallax > ~0.4°; the
        # filter decides about ours)
        strong = res.parallax_deg >= INIT_POINT_PARALLAX_DEG
        idx = res.index[strong]
        X0 = res.points0[strong]
        T_hc = np.repeat(se3_inv(res.T_10)[None], len(res.index), 0)
        f0 = res.points0 / np.linalg.norm(res.points0, axis=1, keepdims=True)
        dist = np.linalg.norm(res.points0, axis=1)
        tau = dfl.compute_tau(T_hc, f0, dist, self.px_err_angle)
        sig_rho = 0.5 * (1 / np.maximum(dist - tau, 1e-7) - 1 / (dist + tau)) * f0[:, 2] ** -1
        obs = [{k0: px0[j], k1: px1[j]} for j in idx]
        pids = self.state_map.add_points(np.full(len(idx), k0), px0[idx], to_normalized(px0[idx], self.K),
                            1.0 / X0[:, 2], np.nan_to_num(sig_rho[strong], nan=1.0), obs)
        # poses of the frames between the two keyframes: PnP on the stored track positions
        self.st.last_kf = k0
        alive_ref = ref.alive[idx]
        for fi, alive, raw in ref.hist[:-1]:
            sel = np.isin(alive, alive_ref)
            if sel.sum() < self.cfg.min_tracked:
                continue
            pos = np.searchsorted(alive_ref, alive[sel])
            _, xn = self._undist(raw[sel])
            T, inl = estimate_pose(m.Xw[pids[pos]], xn, [np.eye(4), self.st.T_cw], self.thr, seed=self.seed + fi)
            if T is not None and inl.sum() >= self.cfg.min_tracked:
                self.st.T_cw = T
                self._record(fi)
        self.state_map.track_frame(ref.frame, self.st.segment, k0, np.eye(4))
        t = Tracks.empty()
        n = len(idx)
        raw = ref.raw[idx]
        t.raw, t.px, t.xn = raw.astype(np.float32), px1[idx], x1[idx]
        t.pid = pids.astype(np.int64)
        t.host = np.full(n, k0)
        t.f_h, t.px_h = np.zeros((n, 3)), px0[idx]
        t.seed = dfl.new_seeds(n, dfl.SeedInit(1.0, 0.5))
        t.kf_px, t.at_kf, t.obs = t.px.copy(), np.ones(n, bool), [[] for _ in range(n)]
        weak = np.flatnonzero(~strong)
        if len(weak):
            jw = res.index[weak]
            zmin = float(np.min(res.points0[:, 2]))
            w = Tracks.empty()
            w.raw, w.px, w.xn = ref.raw[jw].astype(np.float32), px1[jw], x1[jw]
            w.pid = -np.ones(len(jw), np.int64)
            w.host = np.full(len(jw), k0)
            w.f_h, w.px_h = f0[weak], px0[jw]
            w.seed = dfl.new_seeds(len(jw), dfl.SeedInit(1.0, max(zmin, 1e-2)))
            w.seed["mu"] = 1.0 / dist[weak]
            tau_inv = 0.5 * (1 / np.maximum(dist[weak] - tau[weak], 1e-7) - 1 / (dist[weak] + tau[weak]))
            w.seed["sigma2"] = np.minimum(np.nan_to_num(tau_inv, nan=np.inf) ** 2, w.seed["sigma2"])
            w.kf_px, w.at_kf, w.obs = w.px.copy(), np.ones(len(jw), bool), [[(k1, px1[j])] for j in jw]
            t = t.extend(w)
        self.st.tracks = t
        self.mapper.run(k1, self.st.segment)
        self.st.T_cw = m.T_cw(k1)
        self.st.vel, self.st.vel_dt, self.st.t_prev = np.eye(4), 0.0, self.seq.frames[i].timestamp
        self.st.last_kf = k1
        self._new_seeds(k1, gray)
        self.st.kf_imgs = {k0: ref.gray, k1: gray}
        if self.reloc is not None:
            self.reloc.add_keyframe(k0, ref.gray)
            self.reloc.add_keyframe(k1, gray)
        self._record(i)
        self.st.mode = "tracking"
        self.st.ref = None
        log.info("segment %d initialised at frame %d (%s, %d points)", self.st.segment, i, res.method, n)

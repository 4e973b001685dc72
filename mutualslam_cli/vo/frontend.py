"""The monocular VO front end (the paper's SVO role, DESIGN §4): ``run_vo``.

Per frame: decode → KLT (forward–backward checked) → PnP-RANSAC + robust refinement on the
map-point tracks → depth-filter update of the seed tracks → promotion of converged seeds.
Per keyframe (parallax / overlap policy): re-projection of lost window points, observations,
grid detection of new seeds, windowed BA (solved on a worker thread, applied ``BA_LAG`` frames
later). Decoding of the next frame runs on a second thread. After a tracking loss the frame is
looked for among the keyframes (:mod:`~mutualslam_cli.vo.recovery`); failing that, a new segment
starts with its own scale (:mod:`~mutualslam_cli.vo.bootstrap`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from mutualslam_cli.allocator import retain_freed_memory
from mutualslam_cli.config import VOConfig
from mutualslam_cli.config.checks import check_vo
from mutualslam_cli.datasets.sequence import Sequence, grey_frames
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import pinhole, scale_motion, se3_inv, to_normalized
from mutualslam_cli.map.assemble import RunStats
from mutualslam_cli.map.journal import Journal
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.state import MapState
from mutualslam_cli.pixels import in_image
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.bootstrap import InitMixin
from mutualslam_cli.vo.camera import distort_points, focal_px, undistort_points
from mutualslam_cli.vo.depth_prior import NetworkMixin
from mutualslam_cli.vo.features import detect_grid
from mutualslam_cli.vo.feedback import FeedbackMixin
from mutualslam_cli.vo.keyframe_images import KeyframeImages
from mutualslam_cli.vo.local_map import OLD_AGE, LocalMapMixin
from mutualslam_cli.vo.mapper import Mapper
from mutualslam_cli.vo.recovery import RecoveryMixin
from mutualslam_cli.vo.relocalise import RelocIndex
from mutualslam_cli.vo.rescue import KEEP_FACTOR, WEAK_FACTOR, judge, loss_reason, rescue_pose, seed_points
from mutualslam_cli.vo.scale_check import KeyframeRatio, ScaleCheck
from mutualslam_cli.vo.state import TrackerState, Tracks
from mutualslam_cli.vo.tracking import Pyramid, build_pyramid, estimate_pose, klt_track

log = logging.getLogger(__name__)

FRONTEND_VERSION = 6
"""Bumped whenever the front end's output changes for the same config (invalidates VO caches)."""

BA_LAG = 4
"""Frames after a keyframe at which its windowed BA (solved on a worker thread) is applied:
enough for the worker to finish on a 2-core machine, so the tracker rarely waits for it."""

MAX_STEP_RATIO = 4.0
"""The motion prior stretches the last motion by at most this factor (or shrinks it by its inverse)."""

SEED_PREDICT_SIGMA = 0.05
"""Seeds with σ below this fraction of their inverse-depth range are predicted from their mean depth."""

STAGES = ("decode", "track", "pose", "filter", "keyframe", "local_ba")


class FrontEnd(InitMixin, RecoveryMixin, FeedbackMixin, LocalMapMixin, NetworkMixin):
    """State machine ``init`` → ``tracking`` → (loss) → ``init`` … over one sequence, one frame per
    :meth:`process`. Every change to the map and the frame records is journaled in :attr:`journal`
    (:mod:`~mutualslam_cli.map.journal`); between frames the adaptation loop may join a new segment to
    the map (:meth:`transform_segment`) or hand it a global BA's refinement (:meth:`refine`).

    Its state from frame to frame is two declared objects its mixins share: :attr:`state_map` (the map and
    frame records, :class:`~mutualslam_cli.map.state.MapState`) and :attr:`st` (:class:`TrackerState`);
    besides them: the camera and settings, the BA worker (:attr:`mapper`), the relocalisation index."""

    def __init__(self, seq: Sequence, cfg: VOConfig, seed: int, journal: Journal | None = None) -> None:
        check_vo(cfg)
        self.seq, self.cfg, self.seed = seq, cfg, seed
        self.intr = seq.intrinsics
        self.K = self.intr.K()
        self.f = focal_px(self.intr)
        self.thr = cfg.ransac_threshold_px / self.f
        self.px_err_angle = 2.0 * np.arctan(0.5 / self.f)  # SVO: one-pixel bearing error
        self.journal = journal if journal is not None else Journal()
        self.state_map = MapState(pinhole(self.intr), len(seq), self.journal)
        self.mapper = Mapper(self.state_map, self.K, cfg.core_kfs, self.thr)
        self.reloc = (RelocIndex(self.intr, load=lambda kf: seq.load_gray(self.state_map.map.kf_frame[kf]))
                      if cfg.relocalise else None)  # keyframe images decoded again when needed: memory flat
        self.st = TrackerState(timing={k: 0.0 for k in STAGES})
        self.old_images = KeyframeImages(seq.load_gray)
        self.scale: ScaleCheck | None = None

    # ---------------------------------------------------------------- helpers
    def _undist(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px = undistort_points(raw, self.intr)
        return px, to_normalized(px, self.K)

    def _record(self, i: int) -> None:
        """Store frame ``i``'s pose relative to the current reference keyframe."""
        T_wc = se3_inv(self.st.T_cw)
        sm = self.state_map
        sm.track_frame(i, self.st.segment, self.st.last_kf, sm.map.poses_cw()[self.st.last_kf] @ T_wc)

    # ---------------------------------------------------------------- tracking
    def _track_step(self, i: int, gray: np.ndarray, pyr: Pyramid, prev_pyr: Pyramid | None) -> None:
        cfg, m = self.cfg, self.state_map.map
        if self.mapper.pending is not None and i >= self.st.ba_due:
            self._collect_ba()
        t0 = time.perf_counter()
        T_prior = self._motion_prior(i) @ self.st.T_cw
        pred = self._predict(self.st.tracks, T_prior)
        assert prev_pyr is not None, "tracking follows a frame"
        raw, ok = klt_track(prev_pyr, pyr, self.st.tracks.raw, cfg.klt_window, cfg.klt_levels, cfg.fb_threshold_px,
                            pred=pred)
        tr = self.st.tracks.select(ok)
        tr.raw = raw[ok]
        tr.px, tr.xn = self._undist(tr.raw)
        t1 = time.perf_counter()
        self.st.timing["track"] += t1 - t0
        pm = np.flatnonzero(tr.pid >= 0)
        priors = [T_prior, self.st.T_cw]
        T, inl = estimate_pose(m.Xw[tr.pid[pm]], tr.xn[pm], priors, self.thr, seed=self.seed + i)
        if T is None or inl.sum() < WEAK_FACTOR * cfg.min_tracked:
            # weak tracking: look for the window's lost map points before giving up
            tr = self._reproject(tr, gray, T_prior if T is None else T)
            pm = np.flatnonzero(tr.pid >= 0)
            T, inl = estimate_pose(m.Xw[tr.pid[pm]], tr.xn[pm], priors, self.thr, seed=self.seed + i)
        pose = judge(T, inl, m.Xw[tr.pid[pm]], tr.xn[pm], self.thr)
        n_usable = len(pm)
        if pose.T is None or inl.sum() < WEAK_FACTOR * cfg.min_tracked:
            Xs, rows = seed_points(tr, m.poses_wc())
            n_usable += len(rows)
            pose = rescue_pose(pose, m.Xw[tr.pid[pm]], tr.xn[pm], Xs, tr.xn[rows], priors, self.thr,
                               cfg.min_tracked, self.seed + i)
        t2 = time.perf_counter()
        self.st.timing["pose"] += t2 - t1
        # tracks a few pixels off (rolling shutter, blur, a young map point) stay alive and
        # simply weigh less in the Huber refinement; only gross outliers are dropped, and
        # tracking is lost when too few tracks are within that looser bound
        if pose.T is None or pose.support < cfg.min_tracked:
            self._lost(i, gray, loss_reason(n_usable, cfg.min_tracked),
                       f"{pose.support} tracks within {KEEP_FACTOR * cfg.ransac_threshold_px:g} px "
                       f"({n_usable} map points and settled seeds tracked)")
            return
        if pose.how != "points":
            self.st.rescued[pose.how] = self.st.rescued.get(pose.how, 0) + 1
        T, inl = pose.T, pose.inl
        keep = np.ones(len(tr), bool)
        keep[pm[~pose.near]] = False
        tr = tr.select(keep)
        is_pt = tr.pid >= 0
        if is_pt.any():  # map reuse as a share: tracked points first seen long before
            self.st.old_share_sum += float(np.mean(tr.host[is_pt] < self.st.last_kf - OLD_AGE))
            self.st.old_share_frames += 1
        self.st.vel = T @ se3_inv(self.st.T_cw)
        t_i = self.seq.frames[i].timestamp
        self.st.vel_dt, self.st.t_prev = t_i - self.st.t_prev, t_i
        self.st.T_cw = T
        self.st.n_tracked = int(inl.sum())
        # depth filter on the seed tracks
        sm = np.flatnonzero(tr.pid < 0)
        if len(sm):
            T_wc = se3_inv(T)
            T_hw = m.poses_cw()
            T_hc = T_hw[tr.host[sm]] @ T_wc
            f_c = np.c_[tr.xn[sm], np.ones(len(sm))]
            f_c /= np.linalg.norm(f_c, axis=1, keepdims=True)
            x, tau2, good = dfl.measure(tr.f_h[sm], f_c, T_hc, self.px_err_angle)
            dfl.update_seeds(tr.seed, sm[good], x[good], tau2[good])
            conv = sm[dfl.converged({k: v[sm] for k, v in tr.seed.items()})]
            if len(conv):
                self._promote(tr, conv)
        self.st.tracks = tr
        t3 = time.perf_counter()
        self.st.timing["filter"] += t3 - t2
        # keyframe policy: parallax since the last keyframe or lost overlap
        at = tr.at_kf
        ratio = at.sum() / max(self.st.n_at_kf, 1)
        par = float(np.median(np.linalg.norm(tr.px[at] - tr.kf_px[at], axis=1))) if at.any() else 0.0
        if par > cfg.kf_min_parallax_px or ratio < cfg.kf_min_tracked_ratio:
            self._keyframe(i, gray)
        self._record(i)

    def _motion_prior(self, i: int) -> np.ndarray:
        """The constant-velocity guess of frame ``i``'s motion since the last tracked frame: the last
        motion stretched to this frame's time step. A camera drops frames (TUM fr1: 64–68 ms gaps in a
        30 Hz stream, often during fast motion), and a prior that assumes equal steps then misses by
        the whole last motion."""
        dt = self.seq.frames[i].timestamp - self.st.t_prev
        if self.st.vel_dt <= 0 or dt <= 0:
            return self.st.vel
        return scale_motion(self.st.vel, float(np.clip(dt / self.st.vel_dt, 1.0 / MAX_STEP_RATIO, MAX_STEP_RATIO)))

    def _predict(self, tr: Tracks, T_cw: np.ndarray) -> np.ndarray:
        """Raw pixels where the tracks should appear under the motion prior ``T_cw``.

        Map points are projected from their world position, seeds from their current
        depth-filter mean; guesses that fall behind the camera or off the image keep the
        previous position (KLT's default start).
        """
        m = self.state_map.map
        n = len(tr)
        X = np.empty((n, 3))
        pm = tr.pid >= 0
        X[pm] = m.Xw[tr.pid[pm]]
        sm = ~pm
        if sm.any():
            T_wh = m.poses_wc()[tr.host[sm]]
            Xh = tr.f_h[sm] / tr.seed["mu"][sm, None]
            X[sm] = np.einsum("nij,nj->ni", T_wh[:, :3, :3], Xh) + T_wh[:, :3, 3]
        pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        good = (pc[:, 2] > 1e-6) & (pm | (np.sqrt(tr.seed["sigma2"]) < SEED_PREDICT_SIGMA * tr.seed["z_range"]))
        pred = tr.raw.astype(np.float64).copy()
        if good.any():
            px = pc[good, :2] / pc[good, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
            pred[good] = distort_points(px, self.intr)
        w, h = self.intr.width, self.intr.height
        bad = ~np.isfinite(pred).all(1) | ~in_image(pred, w, h)
        pred[bad] = tr.raw[bad]
        shift = pred[good & ~bad] - tr.raw[good & ~bad]
        if len(shift):  # uncertain seeds move with the median predicted flow
            pred[~good] = tr.raw[~good] + np.median(shift, axis=0)
        return pred.astype(np.float32)

    def _promote(self, tr: Tracks, conv: np.ndarray) -> None:
        """Converged seeds become map points (host observation + keyframes seen since)."""
        f_h = tr.f_h[conv]
        mu = tr.seed["mu"][conv]
        rho_z = mu / f_h[:, 2]  # inverse distance along the bearing → inverse z-depth
        sig_z = np.sqrt(tr.seed["sigma2"][conv]) / f_h[:, 2]
        obs = []
        for j in conv:
            o = {int(tr.host[j]): tr.px_h[j]}
            o.update({k: p for k, p in tr.obs[j]})
            obs.append(o)
        pids = self.state_map.add_points(tr.host[conv], tr.px_h[conv], f_h[:, :2] / f_h[:, 2:3], rho_z, sig_z, obs)
        tr.pid[conv] = pids

    def _new_seeds(self, kf: int, gray: np.ndarray, ratio: KeyframeRatio | None = None) -> None:
        """Detect features in empty grid cells of keyframe ``kf`` and start seeds for them (with
        ``vo.depth_seeds`` and the keyframe's scale check ``ratio``: at the network's depth)."""
        m, tr = self.state_map.map, self.st.tracks
        pts = detect_grid(gray, self.cfg.grid_size, self.cfg.max_fts, occupied_px=tr.raw)
        pm = tr.pid >= 0
        if pm.any():
            Xc = m.Xw[tr.pid[pm]] @ self.st.T_cw[:3, :3].T + self.st.T_cw[:3, 3]
            z = Xc[:, 2][Xc[:, 2] > 0]
        else:
            z = np.array([1.0])
        prior = dfl.SeedInit(float(np.median(z)), float(np.min(z)) if len(z) else 0.5)
        n = len(pts)
        if n:
            new = Tracks.empty()
            new.raw = pts.astype(np.float32)
            new.px, new.xn = self._undist(pts)
            new.pid = -np.ones(n, np.int64)
            new.host = np.full(n, kf)
            fh = np.c_[new.xn, np.ones(n)]
            new.f_h = fh / np.linalg.norm(fh, axis=1, keepdims=True)
            new.px_h = new.px.copy()
            new.seed = dfl.new_seeds(n, prior)
            if self.cfg.depth_seeds and ratio is not None:
                assert self.scale is not None  # a ratio comes from _check_scale, which needs it
                mu, sigma2 = self.scale.seeds(ratio, new.px, new.f_h[:, 2])
                ok = np.isfinite(mu) & (mu > 0)
                new.seed["mu"][ok], new.seed["sigma2"][ok] = mu[ok], sigma2[ok]
            new.kf_px, new.at_kf, new.obs = new.px.copy(), np.ones(n, bool), [[] for _ in range(n)]
            tr = tr.extend(new)
        tr.kf_px = tr.px.copy()
        tr.at_kf = np.ones(len(tr), bool)
        self.st.tracks = tr
        self.st.n_at_kf = len(tr)

    def _store_image(self, kf: int, gray: np.ndarray) -> None:
        """Keep the grey images of the last ``core_kfs`` keyframes (reprojection sources)."""
        self.st.kf_imgs[kf] = gray
        for k in sorted(self.st.kf_imgs)[:-self.cfg.core_kfs]:
            del self.st.kf_imgs[k]

    def _collect_ba(self) -> None:
        """Apply the pending windowed BA (waiting for the worker if needed)."""
        t0 = time.perf_counter()
        bad = self.mapper.collect()
        if len(bad) and len(self.st.tracks):
            self.st.tracks = self.st.tracks.select(~np.isin(self.st.tracks.pid, bad))
        self.st.timing["local_ba"] += time.perf_counter() - t0

    def _keyframe(self, i: int, gray: np.ndarray) -> None:
        self._collect_ba()
        t0 = time.perf_counter()
        self.st.tracks = self._reproject(self.st.tracks, gray, self.st.T_cw, fuse=True)
        tr = self.st.tracks
        kf = self.state_map.add_keyframe(i, self.seq.frames[i].timestamp, se3_inv(self.st.T_cw), self.st.segment)
        seen = np.flatnonzero(tr.pid >= 0)
        self.state_map.observe(kf, tr.pid[seen], tr.px[seen])
        for j in np.flatnonzero(tr.pid < 0):
            tr.obs[j] = tr.obs[j] + [(kf, tr.px[j])]
        if self.reloc is not None:
            self.reloc.add_keyframe(kf, gray)
        ratio = self._check_scale(kf, i)
        t1 = time.perf_counter()
        self.mapper.submit(kf, self.st.segment)  # solved on the worker, applied BA_LAG frames later
        self.st.ba_due = i + BA_LAG
        t2 = time.perf_counter()
        self.st.last_kf = kf
        self._new_seeds(kf, gray, ratio)
        self._store_image(kf, gray)
        self.st.timing["keyframe"] += (t1 - t0) + (time.perf_counter() - t2)
        self.st.timing["local_ba"] += t2 - t1

    # ---------------------------------------------------------------- main loop
    def process(self, i: int, gray: np.ndarray) -> None:
        """Track frame ``i`` (the next one: frames come in order) from its ``(H, W)`` uint8 grey image."""
        t0 = time.perf_counter()
        self.journal.frame = i
        pyr = build_pyramid(gray, self.cfg.klt_window, self.cfg.klt_levels)
        self.st.timing["decode"] += time.perf_counter() - t0
        if self.st.mode == "init":
            self._init_step(i, gray, pyr, self.st.prev_pyr)
        else:
            self._track_step(i, gray, pyr, self.st.prev_pyr)
        self.st.prev_pyr = pyr
        self.st.frame = i
        self.st.wall_s += time.perf_counter() - t0

    def finish(self) -> None:
        """The end of the sequence: apply the pending windowed BA, stop the worker."""
        self.journal.frame = self.st.frame
        self._collect_ba()
        self.mapper.close()

    def progress_info(self) -> dict:
        """What a progress bar shows after a frame."""
        i, n = self.st.frame, len(self.seq)
        return {"frame": i, "n_frames": n, "keyframes": len(self.state_map.map.kf_frame),
                "tracked": self.st.n_tracked if self.st.mode == "tracking" else 0,
                "fps": (i + 1) / self.st.wall_s if self.st.wall_s > 0 else 0.0, "state": self.st.mode}

    def stats(self) -> RunStats:
        """Counters and timings so far (the :class:`VOResult`'s ``meta``)."""
        return RunStats(segment=self.st.segment, init_methods=list(self.state_map.init_methods), timing=self.st.timing,
                        total_s=self.st.wall_s, reprojected=self.st.n_reprojected, ba_stats=self.mapper.stats,
                        ba_threaded=self.mapper.pool is not None,
                        relocalisations=list(self.state_map.relocalisations), losses=list(self.state_map.losses),
                        init_wait=self.cfg.reloc_frames if self.reloc is not None else 0, rescued=dict(self.st.rescued),
                        reloc_rejected=self.reloc.rejected if self.reloc is not None else 0,
                        reused=self.st.n_reused, fused=self.st.n_fused,
                        old_share=(self.st.old_share_sum / self.st.old_share_frames
                                   if self.st.old_share_frames else None),
                        scale_check=self.scale.summary() if self.scale is not None else None)

    def result(self) -> VOResult:
        """The map and trajectories now (see :func:`~mutualslam_cli.map.assemble.build_result`)."""
        return self.state_map.snapshot(self.seq.frames, self.stats())


def run_vo(seq: Sequence, cfg: VOConfig, seed: int = 0,
           progress: Callable[[dict], None] | None = None) -> VOResult:
    """Run the monocular front end over a sequence, on its own (no network: nothing joins its segments).

    Args:
        seq: the sequence (frames are decoded one at a time).
        cfg: VO options (grid, KLT, thresholds, keyframe policy, ``core_kfs``).
        seed: seeds every RANSAC (OpenCV's RNG is reset per call): same seed → same output.
        progress: called after every frame with ``{"frame", "n_frames", "keyframes",
            "tracked", "fps", "state"}``.

    Returns:
        :class:`VOResult` in undistorted pinhole pixels; ``meta`` has ``n_reinit``, ``gaps``,
        ``init_methods``, ``timing`` (ms per stage) and ``fps``.
    """
    if len(seq) == 0:
        raise DatasetError(f"{seq.root}: sequence has no frames")
    retain_freed_memory()  # per-frame buffers reuse mapped pages instead of faulting new ones
    # numpy's OpenBLAS would spin up its own threads for the BA's products and busy-wait on
    # both cores, starving the tracker and the decoder (measured: ~40 % more CPU per frame)
    with threadpool_limits(limits=1, user_api="blas"):
        fe = FrontEnd(seq, cfg, seed)
        try:
            for i, gray in grey_frames(seq):
                fe.process(i, gray)
                if progress is not None:
                    progress(fe.progress_info())
        finally:
            fe.finish()
        return fe.result()

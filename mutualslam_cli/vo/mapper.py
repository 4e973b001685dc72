"""Keyframe-time map maintenance: the windowed BA over ``core_kfs`` keyframes, run off the
tracking path, and the rejection of observations it finds inconsistent.

A BA job is *prepared* on the tracking thread (a snapshot of the window as a
:class:`~mutualslam_cli.vo.local_ba.BAProblem`), *solved* on a worker thread (numpy and
OpenCV release the GIL, so tracking continues on the other core) and *applied* on the
tracking thread at a fixed point (a given number of frames later, at the next keyframe, at a
tracking loss or at the end). Because the join point depends only on frame indices, the
output is the same as with a synchronous BA at that point: deterministic for a given seed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np

from mutualslam_cli.geometry import se3_inv, to_normalized
from mutualslam_cli.map.state import MapState
from mutualslam_cli.vo.local_ba import BAProblem, WindowStats, residuals, solve

log = logging.getLogger(__name__)

OUTLIER_FACTOR = 3.0
"""Observations with reprojection error above ``OUTLIER_FACTOR × threshold`` after BA are removed."""

#: A windowed BA's result: new ``T_cw`` ``(K, 4, 4)``, new ``rho`` ``(P,)`` and its figures.
_Solved: TypeAlias = tuple[np.ndarray, np.ndarray, WindowStats]


@dataclass
class _Job:
    kf: int
    kfs: list[int]
    free: np.ndarray
    pids: list[int]
    o_id: list[tuple[int, int]]
    prob: BAProblem
    result: Future[_Solved] | _Solved  # in flight on the worker thread, or solved


class Mapper:
    """Windowed BA of the newest keyframe's window on a map (written through its
    :class:`~mutualslam_cli.map.state.MapState`), optionally threaded."""

    def __init__(self, state: MapState, K: np.ndarray, core_kfs: int, thr: float, iters: int = 6,
                 threaded: bool = True) -> None:
        self.state, self.K, self.core_kfs, self.thr, self.iters = state, K, core_kfs, thr, iters
        self.pool = ThreadPoolExecutor(max_workers=1) if threaded else None
        self.job: _Job | None = None
        self.stats: list[WindowStats] = []
        self.prior_of: Callable[[np.ndarray], np.ndarray] | None = None  # vo.scale_prior: points' prior ρ (NaN: none)
        self.prior_w = 0.0

    @property
    def pending(self) -> int | None:
        """Keyframe id of the BA job not applied yet, or ``None``."""
        return None if self.job is None else self.job.kf

    def run(self, kf: int, segment: int) -> np.ndarray:
        """Synchronous BA of the window ending at ``kf`` (see :meth:`collect` for the return)."""
        self.submit(kf, segment, threaded=False)
        return self.collect()

    def submit(self, kf: int, segment: int, threaded: bool = True) -> None:
        """Snapshot the window ending at keyframe ``kf`` and start solving it.

        At most one job is in flight: callers :meth:`collect` the previous one first. Nothing
        is submitted when the window has fewer than two keyframes or no multi-view point.
        """
        assert self.job is None, "collect() the pending BA before submitting another"
        m = self.state.map
        seg = [k for k in range(kf + 1) if m.kf_segment[k] == segment]
        window = seg[-self.core_kfs:]
        pids = sorted(set().union(*(m.kf_points[k] for k in window)))
        pids = [p for p in pids if len(m.obs[p]) >= 2]
        if not pids or len(window) < 2:
            return
        kfs = sorted(set(window) | {k for p in pids for k in m.obs[p]} | {m.host[p] for p in pids})
        kidx = {k: j for j, k in enumerate(kfs)}
        free = np.array([k in window and k != window[0] for k in kfs])
        host = np.array([kidx[m.host[p]] for p in pids])
        ray = np.c_[np.array([m.xn_h[p] for p in pids]), np.ones(len(pids))]
        rho = np.array([m.rho[p] for p in pids])
        o_pt, o_kf, o_px, o_id = [], [], [], []
        for j, p in enumerate(pids):
            for k, px in m.obs[p].items():
                if k != m.host[p]:
                    o_pt.append(j)
                    o_kf.append(kidx[k])
                    o_px.append(px)
                    o_id.append((p, k))
        prob = BAProblem(m.poses_cw()[kfs].copy(), free, host, ray, rho, np.array(o_pt), np.array(o_kf),
                         to_normalized(np.array(o_px), self.K))
        if self.prior_of is not None:  # the scale prior on the points the window's free keyframes host
            prob.prior_rho = np.where(free[host], self.prior_of(np.array(pids, np.int64)), np.nan)
            # a keyframe's n priors weigh as one measurement of its scale: each 1/√n of the keyframe's weight
            n_h = np.bincount(host[np.isfinite(prob.prior_rho)], minlength=len(kfs))
            prob.prior_w = self.prior_w / np.sqrt(np.maximum(n_h[host], 1))
        result = self.pool.submit(self._solve, prob) if threaded and self.pool is not None else self._solve(prob)
        self.job = _Job(kf, kfs, free, pids, o_id, prob, result)

    def resume(self, kf: int, kfs: list[int], free: np.ndarray, pids: list[int], o_id: list[tuple[int, int]],
               prob: BAProblem) -> None:
        """Put back a job a checkpoint captured in flight (:mod:`~mutualslam_cli.vo.checkpoint`): solved again
        from its problem, so its result is the one the captured front end would have applied."""
        assert self.job is None, "collect() the pending BA before resuming another"
        result = self.pool.submit(self._solve, prob) if self.pool is not None else self._solve(prob)
        self.job = _Job(kf, kfs, free, pids, o_id, prob, result)

    def _solve(self, prob: BAProblem) -> _Solved:
        t0 = time.perf_counter()
        T_new, rho_new, ba_stats = solve(prob, self.thr, iters=self.iters)
        ba_stats["solve_ms"] = 1000.0 * (time.perf_counter() - t0)
        return T_new, rho_new, ba_stats

    def collect(self) -> np.ndarray:
        """Wait for the pending job (if any) and write its result into the map.

        Returns:
            ids of points whose observation in the job's keyframe was rejected (their tracks
            should be dropped); empty when nothing was pending.
        """
        job, st = self.job, self.state
        m = st.map
        if job is None:
            return np.zeros(0, np.int64)
        self.job = None
        res = job.result.result() if isinstance(job.result, Future) else job.result
        T_new, rho_new, ba_stats = res
        ba_stats["kf"], ba_stats["points"], ba_stats["obs"] = job.kf, len(job.pids), len(job.o_id)
        self.stats.append(ba_stats)
        free = np.flatnonzero(job.free)
        st.set_poses(np.array(job.kfs, np.int64)[free], np.array([se3_inv(T) for T in T_new[free]]).reshape(-1, 4, 4))
        st.set_depths(np.array(job.pids, np.int64), rho_new)
        # reject observations the optimised window cannot explain
        r, front = residuals(job.prob, T_new, rho_new)
        err = np.where(front, np.linalg.norm(r, axis=1), np.inf)
        bad = [(p, k) for e, (p, k) in zip(err, job.o_id) if not np.isfinite(e) or e > OUTLIER_FACTOR * self.thr]
        st.remove_observations(np.array([p for p, _ in bad], np.int64), np.array([k for _, k in bad], np.int64))
        bad_kf = [p for p, k in bad if k == job.kf]
        all_pids = sorted(set().union(*(m.kf_points[k] for k in job.kfs)))
        st.refresh(np.array(all_pids, dtype=np.int64))
        return np.array(bad_kf, np.int64)

    def close(self) -> None:
        """Stop the worker thread (after :meth:`collect`)."""
        if self.pool is not None:
            self.pool.shutdown(wait=True)

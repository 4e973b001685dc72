"""Loop closure: a keyframe that sees a place the map saw long before (the paper's future work, §V).

A visual odometry drifts; when the camera returns, the map holds the place twice, apart by the drift.
For each new keyframe (:class:`LoopDetector`):

1. **Place recognition**: the keyframes at least ``min_gap`` keyframes older, ranked by the appearance of
   their thumbnails (zero-mean NCC) — the global descriptor the relocalisation keeps — the best
   ``n_candidates`` tried in that order.
2. **Geometric verification**, the relocalisation's (:mod:`~mutualslam_cli.vo.relocalise`): a homography
   from ORB matches brings the candidate's map points near the new keyframe's image, KLT from the
   candidate's own image finds them, PnP-RANSAC places the keyframe in the candidate's map, enough
   inliers of the matches, halves of the inliers agreeing, and other old keyframes' own images finding
   their points where the pose projects them.
3. **Scale** (a monocular map drifts in scale too): the adapted network's depth of the new keyframe relates
   the depths of its own map points (the drifted unit) to those of the candidate's inlying points under the
   loop pose (the old unit). Each old point is paired with the new points within :data:`PAIR_RADIUS` of the
   image width, ``s = (z_old / d_old) / (z_new / d_new)`` per pair — the network only bridges a few pixels,
   so its error across the image (a wall nearer or farther than it thinks) cancels — and ``s`` is the median
   over the old points (each its pairs' median), refused when uncertain by more than ``max_scale_error``
   and when too few old points have a new one near: the medians over each whole set (the bridge's rule,
   :func:`~mutualslam_cli.backend.bridges.depth_ratio`) were off by 20 % on a rendered room, where the old and
   the new points lay in different parts of the image. **The adapted depth must agree**: the old points' depths
   under the loop pose, divided by the network's, must be nearly one number (relative spread ≤
   ``max_depth_spread``, or ≤ :data:`DEPTH_SPREAD_FACTOR` × the spread of the keyframe's own points, the
   network's own noise on the image); the depths of a wrong pose do not follow the picture the network sees.

The accepted loop is a Sim(3) measurement between the two keyframes; :mod:`~mutualslam_cli.backend.pose_graph`
spreads it over the keyframes between them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mutualslam_cli.backend.bridges import MIN_RATIO_POINTS
from mutualslam_cli.config import LoopConfig
from mutualslam_cli.map.state import MapState
from mutualslam_cli.metrics.loop_recall import LoopQuery
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import focal_px, undistort_points
from mutualslam_cli.vo.relocalise import OLD_PLACE_RERANK, RelocIndex, RelocSettings

#: A loop that moves its query keyframe less than this (degrees; relative to its median point depth, and in log
#: scale) closes nothing new (:meth:`LoopDetector.already_closed`).
CLOSED_DEG, CLOSED_REL = 1.0, 0.02


@dataclass
class LoopClosure:
    """An accepted loop.

    Attributes:
        query: the new keyframe; match: the old keyframe it sees again.
        T_cw: ``(4, 4)`` the new keyframe's pose in the old map's frame (the loop pose).
        scale: ``s``, old units per unit of the new keyframe's (drifted) map.
        inliers: PnP inliers of the match; spread: the depth agreement's relative spread.
        n_new, n_old: points behind each scale ratio; scale_error: the scale's relative standard error.
        T_match_cw: ``(4, 4)`` the match keyframe's pose when the loop was found (the loop's relative pose is
            ``T_cw @ inv(T_match_cw)``; evaluation compares it with GT).
    """

    query: int
    match: int
    T_cw: np.ndarray
    scale: float
    inliers: int
    spread: float
    n_new: int
    n_old: int
    scale_error: float = 0.0
    T_match_cw: np.ndarray | None = None

    def record(self) -> dict:
        """A JSON-ready record (``manifest.json``'s ``loops``)."""
        return {"query": self.query, "match": self.match, "scale": self.scale, "inliers": self.inliers,
                "spread": self.spread, "n_new": self.n_new, "n_old": self.n_old,
                "scale_error": self.scale_error}


def _ratios(z: np.ndarray, d: np.ndarray) -> tuple[float, float, float, int]:
    """``(median(z / d), relative spread, relative standard error of the median, n)`` over positive pairs."""
    ok = np.isfinite(d) & (d > 0) & np.isfinite(z) & (z > 0)
    n = int(ok.sum())
    if n < MIN_RATIO_POINTS:
        return float("nan"), float("nan"), float("nan"), n
    r = z[ok] / d[ok]
    med = float(np.median(r))
    spread = 1.4826 * float(np.median(np.abs(r - med))) / med
    return med, spread, 1.2533 * spread / np.sqrt(n), n


#: The old points' depth spread against the network may exceed ``max_depth_spread`` up to this many times the
#: spread of the keyframe's own points (the network's own noise on this image, with a pose known to be right).
DEPTH_SPREAD_FACTOR = 1.5

def depth_agrees(spread_old: float, spread_new: float, max_spread: float) -> bool:
    """Whether the old points' depths under the loop pose follow the network's: their relative spread (depth over
    the network's) within ``max_spread``, or within :data:`DEPTH_SPREAD_FACTOR` times the spread of the keyframe's
    own points — the network's own noise on this image (a pre-trained network on real images spreads by 0.15–0.77
    on RedKitchen's keyframes, and the absolute bound alone refused 46 of 56 true revisits there)."""
    return spread_old <= max(max_spread, DEPTH_SPREAD_FACTOR * spread_new)


#: Pairs of an old and a new point nearer than this share of the image width measure the loop's scale locally.
PAIR_RADIUS = 0.05


def _local_scale(px_old: np.ndarray, z_old: np.ndarray, uv_new: np.ndarray, z_new: np.ndarray, depth: np.ndarray,
                 size: tuple[int, int]) -> tuple[float, float] | None:
    """The loop's scale and its relative standard error from nearby pairs (module docstring, 3), ``None`` with
    fewer than ``MIN_RATIO_POINTS`` old points paired.

    Args:
        px_old, z_old: ``(n, 2)`` pixels and depths (old unit, under the loop pose) of the matched old points.
        uv_new, z_new: ``(m, 2)`` pixels and depths (the drifted unit) of the new keyframe's own points.
        depth: ``(h, w)`` the adapted network's depth of the new keyframe; size: the image's ``(width, height)``.
    """
    d_old, d_new = lookup_nearest(depth, px_old, size), lookup_nearest(depth, uv_new, size)
    q_old, q_new = z_old / d_old, z_new / d_new
    ok_o = np.isfinite(q_old) & (q_old > 0)
    ok_n = np.isfinite(q_new) & (q_new > 0)
    if ok_o.sum() < MIN_RATIO_POINTS or ok_n.sum() < MIN_RATIO_POINTS:
        return None
    a, qa, b, qb = px_old[ok_o], q_old[ok_o], uv_new[ok_n], q_new[ok_n]
    near = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2) < PAIR_RADIUS * size[0]
    per = [np.median(qa[i] / qb[near[i]]) for i in range(len(a)) if near[i].any()]
    if len(per) < MIN_RATIO_POINTS:
        return None
    lr = np.log(per)
    med = float(np.median(lr))
    spread = 1.4826 * float(np.median(np.abs(lr - med)))
    return float(np.exp(med)), 1.2533 * spread / np.sqrt(len(per))


#: An old and a new point nearer than this in the query image (pixels) are taken for one point of the scene.
SAME_POINT_PX = 3.0
#: Same-point pairs a map-measured loop scale needs.
MIN_SAME_POINTS = 10


def paired_scale(px_old: np.ndarray, z_old: np.ndarray, uv_new: np.ndarray,
                 z_new: np.ndarray) -> tuple[float, float] | None:
    """The loop's scale from 3D–3D pairs of the two maps and its relative standard error; ``None`` with fewer than
    :data:`MIN_SAME_POINTS` pairs.

    The old points under the loop pose and the query keyframe's own points are both in the query camera; an old
    point within :data:`SAME_POINT_PX` of a new one lies on the same ray, so the Sim(3) between the two maps' points
    (Umeyama 1991) is a pure scale along the rays — ``s = median(z_old / z_new)`` over the pairs (old units per
    new unit), robust to a share of wrong pairs, its standard error ``1.2533 · 1.4826 · MAD(log r) / √n``. No network:
    the maps measure it themselves (ORB-SLAM's loop Sim(3) from matched map points, Mur-Artal & Tardós 2017).

    Args:
        px_old, z_old: ``(n, 2)`` pinhole pixels and depths (old unit, loop pose) of the matched old points.
        uv_new, z_new: ``(m, 2)`` pixels and depths (the drifted unit) of the query keyframe's own points.
    """
    ok = np.isfinite(z_old) & (z_old > 0)
    a, za = px_old[ok], z_old[ok]
    if not len(a) or not len(uv_new):
        return None
    d = np.linalg.norm(a[:, None, :] - uv_new[None, :, :], axis=2)
    j = d.argmin(axis=1)
    same = (d[np.arange(len(a)), j] < SAME_POINT_PX) & (z_new[j] > 0)
    if same.sum() < MIN_SAME_POINTS:
        return None
    lr = np.log(za[same] / z_new[j[same]])
    med = float(np.median(lr))
    spread = 1.4826 * float(np.median(np.abs(lr - med)))
    return float(np.exp(med)), 1.2533 * spread / np.sqrt(int(same.sum()))


class LoopDetector:
    """Finds and verifies loops over a growing map (module docstring).

    Args:
        intr: the camera of the raw images (distortion included).
        thr: PnP inlier threshold in normalised units (the front end's RANSAC threshold / focal length).
        settings: the thresholds, the run's ``loop`` section (:class:`~mutualslam_cli.config.LoopConfig`, whose
            ``enabled`` is the caller's business); default: its defaults.
        load: keyframe id → its grey image decoded again (the index then holds no image:
            :class:`~mutualslam_cli.vo.relocalise.HeldImages`).
        index: a keyframe index to share (:meth:`sharing`), built with these thresholds; default: one of its own.

    Attributes:
        index: per keyframe its grey image, thumbnail and ORB features (:class:`RelocIndex`).
        tried, rejected: candidates verified, and refuted with their reason counts (``{reason: n}``).
        queries: one record per :meth:`query`, what it saw and decided (read by the evaluation only, e.g. loop recall
            against GT): ``kf``; ``pool`` ``(P,)`` the old keyframes of its map unit it could match; ``candidates`` the
            best ``n_candidates`` of them by appearance; ``geometry`` ``{candidate: outcome}`` of those verified, in
            order (:data:`~mutualslam_cli.vo.relocalise.PASSED` …); ``verified`` the candidate that passed, or
            ``None``; ``outcome`` ``"loop"`` or why not.
    """

    def __init__(self, intr: Intrinsics, thr: float, settings: LoopConfig | None = None,
                 load: Callable[[int], np.ndarray] | None = None, index: RelocIndex | None = None) -> None:
        self.intr, self.K, self.thr = intr, intr.K(), thr
        self.settings = settings or LoopConfig()
        factor = self.settings.inlier_px / focal_px(intr) / thr  # the loop's inlier threshold over the front end's
        self.index = index if index is not None else RelocIndex(
            intr, RelocSettings(n_candidates=self.settings.n_candidates, inlier_factor=factor,
                                witness_ratio=self.settings.witness_ratio, rerank=OLD_PLACE_RERANK), load)
        self.tried = 0
        self.rejected: dict[str, int] = {}
        self.queries: list[LoopQuery] = []

    def sharing(self) -> LoopDetector:
        """A detector of the same camera and thresholds over this one's keyframe index (one ORB extraction per
        keyframe for all), with records of its own (``tried``, ``rejected``, ``queries``)."""
        return LoopDetector(self.intr, self.thr, self.settings, index=self.index)

    def add(self, kf: int, gray: np.ndarray) -> None:
        """Keep keyframe ``kf``'s ``(H, W)`` uint8 grey image for later queries (once: the index may be shared)."""
        if kf not in self.index.images:
            self.index.add_keyframe(kf, gray)

    def _reject(self, why: str) -> None:
        self.rejected[why] = self.rejected.get(why, 0) + 1
        if self.queries:  # the last query's record (already_closed follows its query)
            self.queries[-1]["outcome"] = why

    def already_closed(self, state: MapState, loop: LoopClosure) -> bool:
        """Whether ``loop`` agrees with the map as it stands — the place is closed already (the front end
        relocalised there, or an earlier loop closed it): nothing to correct, no pose graph or BA. Counted among
        the rejections as ``already closed``. Agreement: the query keyframe's pose now and the loop pose within
        :data:`CLOSED_DEG` and :data:`CLOSED_REL` of the keyframe's median point depth, the scale within
        :data:`CLOSED_REL` of one."""
        T_now, T_loop = state.pose(loop.query), np.linalg.inv(loop.T_cw)
        cos = (np.trace(T_now[:3, :3].T @ T_loop[:3, :3]) - 1.0) / 2.0
        _, z = state.sparse_depth(loop.query)
        shift = float(np.linalg.norm(T_now[:3, 3] - T_loop[:3, 3])) / (float(np.median(z)) if len(z) else 1.0)
        closed = (np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) < CLOSED_DEG and shift < CLOSED_REL
                  and abs(np.log(loop.scale)) < CLOSED_REL)
        if closed:
            self._reject("already closed")
        return closed

    def query(self, state: MapState, kf: int, gray: np.ndarray, depth: np.ndarray, seed: int = 0,
              pool: list[int] | None = None, newest: int = 0) -> LoopClosure | None:
        """A loop from keyframe ``kf`` to an old keyframe of its map unit, verified (module docstring).

        Args:
            state: the map now; gray: ``(H, W)`` uint8 raw grey image of ``kf``; depth: ``(h, w)`` the adapted
                network's depth of ``kf`` (any unit; looked up at the nearest pixel).
            pool: the old keyframes that may match (default: those of its map unit ``min_gap`` or more keyframes
                older; a merge, :mod:`~mutualslam_cli.backend.merge`, gives the other segments').
            newest: the pool's newest keyframes tried first, before the appearance ranking (a merge: where the camera
                was when tracking was lost; a loop: 0, by appearance only).
        """
        s = self.settings
        unit = state.unit_of(kf)
        if pool is None:
            pool = [k for k in sorted(self.index.images) if k <= kf - s.min_gap and state.unit_of(k) == unit]
        rec: LoopQuery = {"kf": kf, "pool": np.array(pool, np.int64), "candidates": [], "geometry": {},
                          "verified": None, "outcome": "no old keyframe in its map unit"}
        self.queries.append(rec)
        if not pool:
            return None
        rec["candidates"] = self.index.candidates(gray, pool, newest)
        rejected0 = self.index.rejected
        r = self.index.query(gray, state.map, self.thr, seed=seed, keyframes=pool, newest=newest, witnesses=pool)
        self.tried += min(len(pool), s.n_candidates) if r is None else r.candidates_tried
        rec["geometry"], rec["outcome"] = dict(self.index.outcomes), "geometry: no candidate passed"
        if self.index.rejected > rejected0:
            self._reject("geometry (inliers, halves or witnesses)")
        if r is None:
            return None
        rec["verified"] = r.keyframe
        size = (self.intr.width, self.intr.height)
        # the new keyframe's own points, in its (drifted) unit
        uv_new, z_new = state.sparse_depth(kf)
        r_new, spread_new, _, n_new = _ratios(z_new, lookup_nearest(np.asarray(depth, float), uv_new, size))
        # the old points it matched, under the loop pose (the old unit)
        Xc = state.points_world(r.pids) @ r.T_cw[:3, :3].T + r.T_cw[:3, 3]
        px = undistort_points(r.raw, self.intr)
        r_old, spread, _, n_old = _ratios(Xc[:, 2], lookup_nearest(np.asarray(depth, float), px, size))
        rec["spread_old"], rec["spread_new"] = spread, spread_new
        if not (np.isfinite(r_new) and np.isfinite(r_old)):
            self._reject("too few points with a predicted depth")
            return None
        # the scale from the two maps themselves: an old and a new point on one pixel are one point (3D–3D pairs);
        # too few such pairs: nearby pairs through the network's depth, whose bias across the image cancels
        local = paired_scale(px, Xc[:, 2], uv_new, z_new)
        rec["scale_from"] = "map"
        if local is None:
            local = _local_scale(px, Xc[:, 2], uv_new, z_new, np.asarray(depth, float), size)
            rec["scale_from"] = "network"
        if local is None:
            self._reject("scale not measurable (too few nearby old and new points)")
            return None
        scale, scale_error = local
        if scale_error > s.max_scale_error:
            self._reject("scale uncertain")
            return None
        if not depth_agrees(spread, spread_new, s.max_depth_spread):
            self._reject("depth disagrees with the network")
            return None
        rec["outcome"] = "loop"
        return LoopClosure(kf, r.keyframe, r.T_cw, scale, r.inliers, spread, n_new, n_old, scale_error,
                           np.linalg.inv(state.pose(r.keyframe)))

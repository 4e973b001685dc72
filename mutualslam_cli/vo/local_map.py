"""The current frame's local map: the map points it should see, however old (map reuse, ``vo.reuse_map``).

A front end that re-attaches only the points of its last few keyframes forgets what it mapped beyond them:
a camera that comes back to a place mapped hundreds of frames ago makes new points there at today's drifted
scale instead of observing the old ones. SVO 2.0 (Forster et al., T-RO 2017, §V-A) projects the points of the
keyframes that overlap the new frame; ORB-SLAM's local map is the covisible keyframes' points. Here:

* every live point of the current map unit that projects into the frame (in front of it, inside the image)
  and is not tracked already is a candidate;
* it is matched (KLT, :func:`~mutualslam_cli.vo.reproject.match_points`) from the image of the observing
  keyframe whose viewpoint is closest: the angle at the point between the two rays at most
  :data:`MAX_VIEW_ANGLE_DEG`, the distance ratio within :data:`MAX_SCALE_CHANGE`; an old point's patch is first
  warped into the current view by the relative pose (SVO 2.0's affine warp,
  :func:`~mutualslam_cli.vo.reproject.warped_klt`: on RedKitchen's 1000 frames the front end's ATE went 8.25 →
  6.78 cm against unwarped KLT at the same gate) and kept within :data:`REUSE_GATE_PX` of its prediction;
  points of the newest keyframes are matched from the newest image holding them, as before;
* one old candidate per grid cell that no track and no newest keyframe's point holds (the best observed point
  of the cell), so the recovered points take the cells where new seeds would otherwise start, and at most
  :data:`MAX_SOURCES` old keyframe images are decoded per call (:class:`KeyframeImages`: an LRU over the
  sequence's files, memory flat in the sequence's length).

At a keyframe, young tracked points that are old points seen again — made while the old ones projected a drift
away, until a loop or the windowed BA brought the two maps together — are fused into them (:func:`duplicates`,
ORB-SLAM's point fusion): a point found again is observed, not made again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mutualslam_cli.map.store import Map
from mutualslam_cli.pixels import in_image
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.camera import distort_points
from mutualslam_cli.vo.frontend_base import FrontEndBase
from mutualslam_cli.vo.reproject import match_points, reproject_points
from mutualslam_cli.vo.state import Tracks

OLD_AGE = 15
"""A point hosted more than this many keyframes before the newest is *old*: the share of them among a frame's
tracked points measures map reuse (``vo.old_share``); a younger one may be fused into an old one
(:func:`duplicates`)."""

MAX_VIEW_ANGLE_DEG = 30.0
"""Largest angle at a point between an old keyframe's ray and the current one for KLT to match its patch."""

MAX_SCALE_CHANGE = 1.4
"""Largest ratio of the point's distances from the two cameras (KLT has no scale invariance)."""

MAX_SOURCES = 4
"""Old keyframes (outside the held images) matched from per call: bounds the decoding per keyframe."""

BORDER_PX = 8
"""Candidates this close to the image border are not matched (KLT's window would leave the image)."""

REUSE_GATE_PX = 10.0
"""An old point found (warped KLT, :func:`~mutualslam_cli.vo.reproject.warped_klt`) within this many pixels of its
prediction is observed again. The newest keyframes' points are held to the RANSAC threshold; an old point's depth
was made from other viewpoints and the map has drifted since: on RedKitchen's 1000 real frames the warped matches of
old points landed a median 8.4 px from their predictions (under 2 px: none) while the same matcher lands within
0.1 px on a render, so a 2 px gate kept nothing. The windowed BA then refines the old point's depth and pulls the
window to the old map (its keyframes fixed)."""

FUSE_PX = 6.0
"""An old point projecting this close to a young tracked point (pixels) is a candidate duplicate of it."""

SAME_PX = 2.0
"""… and is its duplicate when KLT from the old point's own keyframe image lands this close to the track."""

FUSE_DEPTH = 0.15
"""… with depths in the frame within this relative difference."""


@dataclass
class LocalMap:
    """Points to look for in the current frame and the keyframe each is matched from.

    Attributes:
        pids: ``(R,)`` point ids; source: ``(R,)`` keyframe id whose image and observation KLT starts from.
        old: ``(R,)`` bool, the point is outside the newest keyframes' points (map reuse proper).
    """

    pids: np.ndarray
    source: np.ndarray
    old: np.ndarray


def _closest_view(m: Map, pids: np.ndarray, C: np.ndarray) -> np.ndarray:
    """For each point the observing keyframe whose viewpoint is closest to a camera at ``C`` ``(3,)``, or −1
    when none is within :data:`MAX_VIEW_ANGLE_DEG` and :data:`MAX_SCALE_CHANGE`."""
    pt, kf = [], []
    for j, p in enumerate(pids.tolist()):
        for k in m.obs[p]:
            pt.append(j)
            kf.append(k)
    out = -np.ones(len(pids), np.int64)
    if not pt:
        return out
    pt_a, kf_a = np.array(pt), np.array(kf)
    X = m.Xw[pids[pt_a]]
    v_k = X - m.poses_wc()[kf_a, :3, 3]
    v_c = X - C
    n_k, n_c = np.linalg.norm(v_k, axis=1), np.linalg.norm(v_c, axis=1)
    cos = np.sum(v_k * v_c, 1) / np.maximum(n_k * n_c, 1e-12)
    ratio = n_c / np.maximum(n_k, 1e-12)
    ok = (cos >= np.cos(np.radians(MAX_VIEW_ANGLE_DEG))) & (ratio <= MAX_SCALE_CHANGE) & (ratio >= 1 / MAX_SCALE_CHANGE)
    score = np.where(ok, cos, -np.inf)
    order = np.lexsort((-kf_a, -score, pt_a))  # per point: best cosine first, then the newest keyframe
    first = np.r_[True, pt_a[order][1:] != pt_a[order][:-1]]
    best = order[first]
    good = np.isfinite(score[best])
    out[pt_a[best][good]] = kf_a[best][good]
    return out


def local_map(m: Map, T_cw: np.ndarray, K: np.ndarray, size: tuple[int, int], kfs: np.ndarray,
              recent: list[int], held: set[int], tracked: np.ndarray, occupied_px: np.ndarray,
              to_raw: Callable[[np.ndarray], np.ndarray], grid: int) -> LocalMap:
    """The points the frame at ``T_cw`` should see (module docstring).

    Args:
        m: the map; T_cw: ``(4, 4)`` the frame's pose; K: ``(3, 3)`` pinhole (undistorted pixels);
        size: ``(W, H)`` image size.
        kfs: keyframe ids of the map unit the frame tracks in.
        recent: the newest keyframes (their points are matched as the window's always were).
        held: keyframes whose grey images are held (the newest ones).
        tracked: ids of points tracked already; occupied_px: ``(T, 2)`` raw pixels of the frame's tracks.
        to_raw: undistorted → raw (distorted) pixels; grid: grid cell size in pixels.

    Returns:
        :class:`LocalMap` (possibly empty).
    """
    empty = LocalMap(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool))
    recent_pts = set().union(*(m.kf_points[k] for k in recent)) if recent else set()
    host = np.asarray(m.host, np.int64)
    if not len(host):
        return empty
    in_unit = np.zeros(len(m.kf_frame), bool)
    in_unit[kfs] = True
    live = np.isfinite(m.Xw[:, 0]) & in_unit[host]
    live[tracked] = False
    pids = np.flatnonzero(live)
    if not len(pids):
        return empty
    Xc = m.Xw[pids] @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = Xc[:, 2] > 1e-6
    pids, Xc = pids[front], Xc[front]
    px = Xc[:, :2] / Xc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    w, h = size
    inside = in_image(px, w, h, BORDER_PX)
    pids, px = pids[inside], px[inside]
    if not len(pids):
        return empty
    raw = to_raw(px)
    inside = in_image(raw, w, h, BORDER_PX)
    pids, raw = pids[inside], raw[inside]
    is_recent = np.array([p in recent_pts for p in pids.tolist()], bool)
    # the cell rule for old points: a cell a track or a newest keyframe's point holds gets none; else its
    # best-observed old point (the newest keyframes' points are all tried, as the window's always were)
    cell = lambda r: (r[:, 1] // grid).astype(np.int64) * 100000 + (r[:, 0] // grid).astype(np.int64)  # noqa: E731
    c = cell(raw)
    taken = np.r_[cell(occupied_px) if len(occupied_px) else np.zeros(0, np.int64), c[is_recent]]
    free = is_recent | ~np.isin(c, taken)
    pids, c, is_recent = pids[free], c[free], is_recent[free]
    n_obs = np.array([len(m.obs[p]) for p in pids.tolist()], np.int64)
    order = np.lexsort((pids, -n_obs, c))
    first = np.r_[True, c[order][1:] != c[order][:-1]] if len(order) else np.zeros(0, bool)
    keep = np.sort(np.r_[order[first & ~is_recent[order]], np.flatnonzero(is_recent)])
    pids, is_recent = pids[keep], is_recent[keep]
    source = -np.ones(len(pids), np.int64)
    if is_recent.any():
        source[is_recent] = [max((k for k in m.obs[p] if k in held), default=-1) for p in pids[is_recent].tolist()]
    old = ~is_recent
    if old.any():
        source[old] = _closest_view(m, pids[old], -T_cw[:3, :3].T @ T_cw[:3, 3])
        srcs, counts = np.unique(source[old & (source >= 0) & ~np.isin(source, list(held))], return_counts=True)
        if len(srcs) > MAX_SOURCES:  # the old keyframes with the most points, newest first on ties
            top = srcs[np.lexsort((-srcs, -counts))[:MAX_SOURCES]]
            drop = old & ~np.isin(source, top) & ~np.isin(source, list(held))
            source[drop] = -1
    ok = source >= 0
    return LocalMap(pids[ok], source[ok], old[ok])


def duplicates(m: Map, T_cw: np.ndarray, K: np.ndarray, kfs: np.ndarray, young_before: int, track_pids: np.ndarray,
               track_raw: np.ndarray, to_raw: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Old points that may be young tracked points seen again: candidate pairs for :func:`fuse_duplicates`.

    A camera back in a place it mapped long ago makes new points there before its map reuse finds the old ones
    (the old ones project a drift away, or every grid cell is held by a track); once a loop or the windowed BA has
    brought the two maps together, the same corner is two points. A young point (hosted at or after keyframe
    ``young_before``) and an old one of the same map unit (hosted before it) are a candidate pair when the old
    point projects within :data:`FUSE_PX` of the young one's track and their depths in the frame agree within
    :data:`FUSE_DEPTH`; the nearest old point per track.

    Args:
        m: the map; T_cw: ``(4, 4)`` the frame's pose; K: ``(3, 3)`` pinhole; kfs: keyframes of the map unit.
        track_pids, track_raw: ``(T,)`` point ids and ``(T, 2)`` raw pixels of the frame's map-point tracks.
        to_raw: undistorted → raw pixels.

    Returns:
        ``(young, old)`` point ids ``(P,)`` each.
    """
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    host = np.asarray(m.host, np.int64)
    if not len(track_pids) or not len(host):
        return none
    in_unit = np.zeros(len(m.kf_frame), bool)
    in_unit[kfs] = True
    old = np.flatnonzero(np.isfinite(m.Xw[:, 0]) & in_unit[host] & (host < young_before))
    young = host[track_pids] >= young_before
    if not len(old) or not young.any():
        return none
    yp, yraw = track_pids[young], track_raw[young]
    Xc = m.Xw[old] @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = Xc[:, 2] > 1e-6
    old, Xc = old[front], Xc[front]
    if not len(old):
        return none
    raw = to_raw(Xc[:, :2] / Xc[:, 2:3] @ K[:2, :2].T + K[:2, 2])
    # nearest old projection per young track, on a grid of FUSE_PX cells (no quadratic search)
    cell = np.floor(raw / FUSE_PX).astype(np.int64)
    table: dict[tuple[int, int], list[int]] = {}
    for j, (cx, cy) in enumerate(cell.tolist()):
        table.setdefault((cx, cy), []).append(j)
    z_young = (m.Xw[yp] @ T_cw[2, :3] + T_cw[2, 3])
    pair_y, pair_o = [], []
    for i, (x, y) in enumerate(yraw.tolist()):
        cx, cy = int(np.floor(x / FUSE_PX)), int(np.floor(y / FUSE_PX))
        near = [j for dx in (-1, 0, 1) for dy in (-1, 0, 1) for j in table.get((cx + dx, cy + dy), ())]
        if not near:
            continue
        near_a = np.array(near)
        d = np.linalg.norm(raw[near_a] - (x, y), axis=1)
        ok = (d < FUSE_PX) & (np.abs(Xc[near_a, 2] / max(z_young[i], 1e-9) - 1.0) < FUSE_DEPTH)
        if ok.any():
            pair_y.append(int(yp[i]))
            pair_o.append(int(old[near_a[ok][np.argmin(d[ok])]]))
    if not pair_y:
        return none
    return np.array(pair_y, np.int64), np.array(pair_o, np.int64)


class LocalMapMixin(FrontEndBase):
    """Methods of the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) that re-attach lost map points:
    the newest keyframes' always, with ``vo.reuse_map`` the whole map unit's in view (:func:`local_map`)."""

    def _image_of(self, kf: int) -> np.ndarray:
        """The grey image of keyframe ``kf``: held when among the newest, else decoded again (an LRU)."""
        img = self.st.kf_imgs.get(kf)
        return img if img is not None else self.old_images.get(self.state_map.map.kf_frame[kf])

    def _fuse_duplicates(self, tr: Tracks, gray: np.ndarray, T_cw: np.ndarray, kfs: np.ndarray) -> Tracks:
        """Young tracked points that are old points seen again (:func:`duplicates`, confirmed by KLT from the old
        point's own keyframe image landing within :data:`SAME_PX` of the track) are fused into the old ones: the
        track goes on as the old point, which takes the young one's observations (:meth:`Map.fuse_points`)."""
        m = self.state_map.map
        pm = np.flatnonzero(tr.pid >= 0)
        young_before = max(0, self.st.last_kf - OLD_AGE) + 1
        y, o = duplicates(m, T_cw, self.K, kfs, young_before, tr.pid[pm], tr.raw[pm],
                          lambda px: distort_points(px, self.intr))
        if not len(y):
            return tr
        src = _closest_view(m, o, -T_cw[:3, :3].T @ T_cw[:3, 3])
        has = src >= 0
        y, o, src = y[has], o[has], src[has]
        if len(src) and len(np.unique(src)) > MAX_SOURCES:  # bound the decoding: the sources with most candidates
            srcs, counts = np.unique(src, return_counts=True)
            top = srcs[np.lexsort((-srcs, -counts))[:MAX_SOURCES]]
            keep = np.isin(src, top)
            y, o, src = y[keep], o[keep], src[keep]
        if not len(y):
            return tr
        cfg = self.cfg
        found, raw = match_points(m, self._image_of, gray, T_cw, o, src, self.intr, cfg.klt_window, cfg.klt_levels,
                                  cfg.fb_threshold_px, FUSE_PX / self.f, warp=True)
        at = {int(p): r for p, r in zip(found.tolist(), raw)}
        row = {int(p): j for j, p in enumerate(tr.pid.tolist()) if p >= 0}
        fy, fo = [], []
        used: set[int] = set()
        for a, b in zip(y.tolist(), o.tolist()):
            r = at.get(b)
            if r is None or b in used or b in row:  # not found, taken, or tracked already on its own
                continue
            if np.linalg.norm(r - tr.raw[row[a]]) < SAME_PX:
                fy.append(a)
                fo.append(b)
                used.add(b)
        if not fy:
            return tr
        self.state_map.fuse_points(np.array(fy, np.int64), np.array(fo, np.int64))
        for a, b in zip(fy, fo):
            tr.pid[row[a]] = b
            tr.host[row[a]] = m.host[b]
        self.st.n_fused += len(fy)
        return tr

    def _reproject(self, tr: Tracks, gray: np.ndarray, T_cw: np.ndarray, fuse: bool = False) -> Tracks:
        """Re-attach lost map points to the current frame: the newest keyframes' (see :mod:`reproject`), and with
        ``vo.reuse_map`` every point of the map unit the frame sees (:mod:`~mutualslam_cli.vo.local_map`); with
        ``fuse`` (at a keyframe, no windowed BA in flight) young tracked points that are old ones seen again are
        fused into them first (:meth:`_fuse_duplicates`)."""
        m = self.state_map.map
        seg = [k for k in range(len(m.kf_frame)) if m.kf_segment[k] == self.st.segment]
        window = seg[-self.cfg.core_kfs:]
        cfg = self.cfg
        if cfg.reuse_map:
            unit = self.state_map.unit(self.st.segment)
            kfs = np.array([k for k in range(len(m.kf_frame)) if self.state_map.unit(m.kf_segment[k]) == unit],
                           np.int64)
            if fuse:
                tr = self._fuse_duplicates(tr, gray, T_cw, kfs)
            lm = local_map(m, T_cw, self.K, (self.intr.width, self.intr.height), kfs, window, set(self.st.kf_imgs),
                           tr.pid[tr.pid >= 0], tr.raw, lambda px: distort_points(px, self.intr), cfg.grid_size)
            recent = ~lm.old
            pids, raw = match_points(m, self._image_of, gray, T_cw, lm.pids[recent], lm.source[recent], self.intr,
                                     cfg.klt_window, cfg.klt_levels, cfg.fb_threshold_px, self.thr)
            if lm.old.any():  # old points: their depth, made from other viewpoints, misses by more (REUSE_GATE_PX)
                p_old, r_old = match_points(m, self._image_of, gray, T_cw, lm.pids[lm.old], lm.source[lm.old],
                                            self.intr, cfg.klt_window, cfg.klt_levels, cfg.fb_threshold_px,
                                            REUSE_GATE_PX / self.f, warp=True)
                pids, raw = np.concatenate([pids, p_old]), np.concatenate([raw, r_old]).astype(np.float32)
                self.st.n_reused += len(p_old)
        else:
            pids, raw = reproject_points(m, self.st.kf_imgs, gray, T_cw, tr.pid[tr.pid >= 0], window, self.intr,
                                         cfg.klt_window, cfg.klt_levels, cfg.fb_threshold_px, self.thr)
        if len(pids) == 0:
            return tr
        # do not double-book grid cells: drop seeds sharing a cell with a recovered point
        g = self.cfg.grid_size
        cell = lambda r: (r[:, 1] // g).astype(int) * 10000 + (r[:, 0] // g).astype(int)  # noqa: E731
        rc = set(cell(raw).tolist())
        keep = (tr.pid >= 0) | ~np.isin(cell(tr.raw), list(rc))
        tr = tr.select(keep)
        n = len(pids)
        new = Tracks.empty()
        new.raw = raw
        new.px, new.xn = self._undist(raw)
        new.pid = pids
        new.host = np.array([m.host[p] for p in pids], np.int64)
        new.f_h, new.px_h = np.zeros((n, 3)), np.zeros((n, 2))
        new.seed = dfl.new_seeds(n, dfl.SeedInit(1.0, 0.5))
        new.kf_px, new.at_kf, new.obs = new.px.copy(), np.zeros(n, bool), [[] for _ in range(n)]
        self.st.n_reprojected += n
        return tr.extend(new)

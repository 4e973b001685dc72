"""Map-point culling + global photometric BA as one stage (paper §III-C, DESIGN §6).

:func:`run_global_ba` takes a front-end map (a :class:`~mutualslam_cli.map.result.VOResult`),
keyframe images at the BA resolution, the adapted network's depth and per-keyframe L_val, and
returns a refined copy. It is the only module that reads :class:`~mutualslam_cli.config.BAConfig`.

Choices the paper leaves open (written down here):

- **Host**: Eq. 10 judges each point in its best-validated observing keyframe (lowest L_val, Fig. 3,
  :func:`~mutualslam_cli.backend.culling.choose_hosts`), comparing the point's depth there with the CNN's.
  The BA keeps the front end's host (the keyframe where the feature was detected: its patch is the
  detected corner). Re-hosting the BA parameters in the best-validated keyframe (pixel = the point's
  projection there, exact at the time) was tried: on ``redkitchen_7scenes`` with GT depth as the
  "CNN", a mid-run BA and the final BA with re-hosting took keyframe ATE from 25.1 to 40–49 mm (two
  random L_val orders), without it to 34 mm; in the real run (adapted CNN, one Algorithm 1
  request) to 64 mm and map e_si from 0.176 to 0.238. A projected host pixel is off the tracked
  feature by the reprojection error, so each re-hosting moves the patch off its corner.
  ``n_judged_elsewhere`` counts the points judged in another keyframe than their host.
- **Targets** (≤ ``max_targets`` per point, paper §III-C: "re-projections to the nearby keyframes,
  including the existing 3D-2D constraints"): the point's existing observations first (nearest
  keyframe index first, at most ``max_targets − nearby_slots``), then the keyframes of its map unit
  nearest to its host *in space* (camera centres), where it projects inside the image in front of
  the camera, not more than :data:`~mutualslam_cli.backend.ba.targets.MAX_DEPTH_RATIO` farther or nearer
  than in its host, and where its block passes the robust test at the start
  (:func:`~mutualslam_cli.backend.ba.residuals.classify`) (:mod:`~mutualslam_cli.backend.ba.targets`).
  Keyframes far apart in time that see the same place are what pulls drift out of a sequence that
  returns; an occluded or mismatched target is kept out by that test and again at every round of the solver. The slots
  kept for them matter: a tracked point has its five neighbours in time as observations, and with
  all five taken first a synthetic 1,600-frame room sequence that returns to its start got 244
  nearby targets of 23,055 and keyframe ATE 5.5 → 7.5 mm; with two slots kept, 2.75 mm.
- **Host pixels** sit on integer positions of the BA images (rounded; the refined point keeps the
  rounded pixel): the host intensities of the residual pattern are samples, not interpolations.
- **Dropped points**: a point whose blocks are mostly outliers at the end (the solver's
  ``dropped``) leaves the map like a culled one; ``n_dropped`` counts them (culling: ``n_culled``).
- **Unrefined points**: a kept point with no valid target (or whose host patch leaves the image)
  is not in the BA and is kept *as it is* (host, pixel, inverse depth unchanged; it moves with its
  host keyframe's pose). Counted in ``n_unrefined``. So is a point whose inverse depth the BA
  changed by more than :data:`MAX_CHANGE` (``n_diverged``): on ``tum_fr1_xyz`` two points seen by
  two close keyframes only went to ×0.49 and to infinity (the solver's ρ floor), which alone took
  the map's e_si from 0.11 to 0.62; the other 648 moved by 9 % (median).
- **Segments and units**: a re-initialised front end has one map frame and scale per segment; a bridge joins
  a segment into the unit of the one before it (``units``). Each map unit is one BA — its first keyframe
  fixed, the scale held by the solver's prior on the extent of its keyframe trajectory — so a bridge's
  placement and scale are refined with the rest: no observation crosses a gap, but a point's nearby
  targets may lie in another segment of its unit where it projects with a matching patch. Segments no
  bridge joined are BAs of their own. Keyframes without any residual stay fixed.
- **Partial BA** (``upto``): only keyframes ``≤ upto`` and the points they host exist yet
  (Algorithm 1 triggers mid-run). Everything else follows the correction of its nearest refined
  keyframe, ``T_new = T_ref_new · T_ref_old⁻¹ · T``: later keyframes that of the last refined
  keyframe of their segment, frames of ``traj_all`` that of the latest keyframe at or before them
  (the first one of their segment before it). Points are host-relative, so they follow their host.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace

import numpy as np

from mutualslam_cli.backend.ba.photometric import solve
from mutualslam_cli.backend.ba.targets import (
    MARGIN,
    UnitScene,
    connected_parts,
    existing_targets,
    nearby_targets,
    pattern_of,
)
from mutualslam_cli.backend.culling import cull_map_points
from mutualslam_cli.config import BAConfig
from mutualslam_cli.errors import ShapeError
from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.sim3 import follow
from mutualslam_cli.pixels import in_image, lookup_nearest
from mutualslam_cli.types import Trajectory

#: Largest factor by which the BA may change a point's inverse depth; beyond it the point keeps
#: its value before BA (an under-constrained depth, e.g. one short-baseline target). The same
#: factor as a gross outlier of Eq. 10 with γ = 0.5.
MAX_CHANGE = 2.0


@dataclass
class BAStats:
    """What one culling + global BA did (:func:`run_global_ba`), in the order the manifest's ``ba_runs`` lists it.

    Attributes:
        n_points: points of the map; n_culled: of them culled by Eq. 10; n_judged: those Eq. 10 could judge;
            n_judged_elsewhere: judged in another host than the front end's (``val_loss``).
        n_targets: photometric targets; n_nearby_targets: of them in keyframes beyond the existing observations.
        n_diverged: kept points not refined because they moved by more than :data:`MAX_CHANGE`.
        n_blocks, n_outlier_blocks: residual blocks, and those the robust cost found to be outliers.
        iterations, accepted: LM iterations and accepted steps; cost0, cost: the robust cost before and after
            (each summed over the solved problems, ``n_parts`` of them).
        n_refined, n_unrefined, n_dropped: points refined, kept but not refined, dropped as outliers.
        keyframes: keyframes taking part; costs: per problem, the last round's cost sequence; seconds: wall time.
    """

    n_points: int = 0
    n_culled: int = 0
    n_judged: int = 0
    n_judged_elsewhere: int = 0
    n_targets: int = 0
    n_nearby_targets: int = 0
    n_diverged: int = 0
    n_blocks: int = 0
    n_outlier_blocks: int = 0
    iterations: int = 0
    accepted: int = 0
    cost0: float = 0
    cost: float = 0
    n_parts: int = 0
    n_refined: int = 0
    n_unrefined: int = 0
    n_dropped: int = 0
    keyframes: int = 0
    costs: list = field(default_factory=list)
    seconds: float = 0.0

    def record(self) -> dict[str, int | float]:
        """The manifest's row of this run: every field but ``costs``, in order."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "costs"}


@dataclass
class GlobalBAResult:
    """Output of :func:`run_global_ba`.

    Attributes:
        vo: refined copy of the input: keyframe poses ≤ ``upto``, and the inverse depths and (integer)
            host pixels of refined points replaced (hosts stay), the rest following (module
            docstring). Culled and dropped points are still in it, unchanged; :meth:`kept` drops them.
        keep: ``(P,)`` bool over the input's points, False = culled by Eq. 10.
        dropped: ``(P,)`` bool, points the BA found to be outliers (mostly outlier blocks).
        stats: what the run did (:class:`BAStats`).
    """

    vo: VOResult
    keep: np.ndarray
    dropped: np.ndarray
    stats: BAStats = field(default_factory=BAStats)

    def kept(self) -> VOResult:
        """The refined map without the culled and the dropped points."""
        return replace(self.vo, points=self.vo.points.subset(self.keep & ~self.dropped))


def _follow(poses: np.ndarray, times: np.ndarray, segs: np.ndarray, ref_times: np.ndarray,
            ref_segs: np.ndarray, ref_old: np.ndarray, ref_new: np.ndarray) -> np.ndarray:
    """``T_new = T_ref_new · T_ref_old⁻¹ · T`` with ref = latest reference of the same segment at or
    before each pose's time (the segment's first reference before it); no reference → unchanged."""
    out = poses.copy()
    for s in np.unique(segs):
        r = np.flatnonzero(ref_segs == s)
        m = np.flatnonzero(segs == s)
        if not len(r) or not len(m):
            continue
        j = r[np.clip(np.searchsorted(ref_times[r], times[m], side="right") - 1, 0, len(r) - 1)]
        out[m] = follow(poses[m], np.linalg.inv(ref_old[j]), ref_new[j])
    return out


def window_start(last: int, window: int) -> int:
    """The first keyframe of a BA of the keyframes up to ``last`` with ``ba.window = window``: the newest
    ``window`` of them (0: every keyframe, from the first)."""
    return max(0, last - window + 1) if window else 0


def run_global_ba(vo: VOResult, images: Callable[[int], np.ndarray],
                  depth_of: Callable[[int], np.ndarray] | None, val_loss: Mapping[int, float] | None,
                  cfg: BAConfig, *, cull: bool, upto: int | None = None,
                  units: Mapping[int, int] | None = None) -> GlobalBAResult:
    """Cull the map with the CNN depth (Eq. 10), then photometric BA (Eq. 11–12) of every keyframe.

    Args:
        vo: the map (poses ``T_wc``, points host-relative, pinhole camera ``vo.intrinsics``).
        images: ``kf_id → (H, W)`` float grey in [0, 1], undistorted, at the BA resolution (any
            size; the camera is ``vo.intrinsics`` scaled to it).
        depth_of: ``kf_id → (h, w)`` CNN depth in map units at any resolution (looked up at the
            nearest pixel); ``None`` = no culling.
        val_loss: ``{kf_id: L_val}`` of the current network (host choice); ``None`` = front-end hosts.
        cfg: γ, d_max, pattern, max_targets, iterations, levels, rounds, robust thresholds.
        cull: apply Eq. 10 (and re-host by L_val).
        upto: last keyframe that exists yet (default: the last one).
        units: ``{segment: map unit}``: segments a bridge joined solve as one map (default: each its own).

    With ``cfg.window = W > 0`` only the newest ``W`` keyframes up to ``upto`` and the points they host
    are culled and refined; the window's first keyframe is held fixed (the gauge) and older keyframes
    and points are left as they are, so a trigger's cost does not grow with the map.

    Returns:
        :class:`GlobalBAResult`. Within each segment and round of the solver the robust cost never
        increases.
    """
    t0 = time.perf_counter()
    nk = len(vo.keyframes)
    upto = nk - 1 if upto is None else int(upto)
    first = window_start(upto, cfg.window)  # the keyframes [first, upto] take part
    pts = vo.points
    inside = (pts.host <= upto) & (pts.host >= first)
    sub_idx = np.flatnonzero(inside)  # the points that exist at keyframe ``upto`` (hosted in the window)
    seen = [(pts.observations[i] <= upto) & (pts.observations[i] >= first) for i in sub_idx]
    sub_obs = [pts.observations[i][m] for i, m in zip(sub_idx, seen)]
    sub_pix = [pts.obs_pixels[i][m] for i, m in zip(sub_idx, seen)]
    sub = replace(vo, keyframes=vo.keyframes[:upto + 1],
                  points=replace(pts.subset(inside), observations=sub_obs, obs_pixels=sub_pix))
    keep = np.ones(len(pts), bool)
    culled = (0, 0, 0)  # culled, judged, judged elsewhere
    if cull and depth_of is not None and len(sub_idx):
        keep[sub_idx], culled = _cull(sub, vo, depth_of, val_loss, cfg)
    stack_all = {k: np.asarray(images(k), np.float32) for k in range(first, upto + 1)} if len(sub_idx) else {}
    H, W = next(iter(stack_all.values())).shape if stack_all else (vo.intrinsics.height, vo.intrinsics.width)
    if any(im.shape != (H, W) for im in stack_all.values()):
        raise ShapeError("run_global_ba: keyframe images must all have one size")
    s = np.array([W / vo.intrinsics.width, H / vo.intrinsics.height])
    pix_ba = np.rint((sub.points.pixel + 0.5) * s - 0.5)  # host pixels on the BA images' pixel grid
    T_wc = np.stack([k.pose for k in vo.keyframes])
    groups = np.array([(units or {}).get(k.segment, k.segment) for k in sub.keyframes])
    sv = _solve_units(sub, sub_obs, keep[sub_idx], stack_all, vo.intrinsics.scaled(W, H).K(), T_wc, pix_ba,
                      first, cfg, groups)
    dropped = np.zeros(len(pts), bool)
    dropped[sub_idx] = sv.dropped
    out = _assemble(vo, upto, T_wc, sv, sub_idx, (pix_ba + 0.5) / s - 0.5)
    stats = replace(sv.totals, n_points=len(pts), n_culled=culled[0], n_judged=culled[1], n_judged_elsewhere=culled[2],
                    n_refined=int(sv.refined.sum()), n_unrefined=int((keep[sub_idx] & ~sv.refined & ~sv.dropped).sum()),
                    n_dropped=int(dropped.sum()), keyframes=upto + 1 - first, costs=sv.costs,
                    seconds=time.perf_counter() - t0)
    return GlobalBAResult(out, keep, dropped, stats)


def _cull(sub: VOResult, vo: VOResult, depth_of: Callable[[int], np.ndarray], val_loss: Mapping[int, float] | None,
          cfg: BAConfig) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Eq. 10 on the points of ``sub``: their keep mask and the counts (culled, judged, judged in another host)."""
    cache: dict[int, np.ndarray] = {}

    def depth_at(k: int, uv: np.ndarray) -> np.ndarray:
        d = cache.setdefault(k, np.asarray(depth_of(k), float))
        if d.ndim != 2:
            raise ShapeError(f"depth_of({k}): expected an (h, w) depth map, got shape {d.shape}")
        return lookup_nearest(d, uv, (vo.intrinsics.width, vo.intrinsics.height))

    cr = cull_map_points(sub, val_loss or {}, depth_at, cfg.gamma, cfg.d_max)
    return cr.keep, (int((~cr.keep).sum()), int(cr.judged.sum()), int(np.sum(cr.host != sub.points.host)))


@dataclass
class _Solved:
    """What the BAs of the units did to the points of the sub-map (module docstring).

    Attributes:
        T_wc: ``(K, 4, 4)`` every keyframe's pose after (the fixed and untouched ones bit for bit).
        rho: ``(P,)`` inverse depths after; refined, dropped: ``(P,)`` bool.
        totals: the counts summed over the problems (the :class:`BAStats` fields of the solver); costs: each
            problem's last round's cost sequence.
    """

    T_wc: np.ndarray
    rho: np.ndarray
    refined: np.ndarray
    dropped: np.ndarray
    totals: BAStats = field(default_factory=BAStats)
    costs: list = field(default_factory=list)


def _solve_units(sub: VOResult, sub_obs: list[np.ndarray], keep: np.ndarray, stack_all: dict[int, np.ndarray],
                 K: np.ndarray, T_wc: np.ndarray, pix: np.ndarray, first: int, cfg: BAConfig,
                 units: np.ndarray) -> _Solved:
    """The photometric BAs of the points of ``sub`` that ``keep`` over the keyframes from ``first`` on: per map
    unit (``units``: per keyframe, its segment or the unit bridges joined it into), per part of the unit its
    blocks tie together (:func:`~mutualslam_cli.backend.ba.targets.connected_parts`), each part's first keyframe fixed
    and one scale prior on its extent (module docstring)."""
    host, rho = sub.points.host, sub.points.inv_depth
    out = _Solved(T_wc.copy(), rho.copy(), np.zeros(len(host), bool), np.zeros(len(host), bool))
    H, W = next(iter(stack_all.values())).shape if stack_all else (1, 1)
    for u in np.unique(units):
        ks = np.flatnonzero((units == u) & (np.arange(len(units)) >= first))
        loc = np.full(len(T_wc), -1)
        loc[ks] = np.arange(len(ks))
        cand = np.flatnonzero(keep & (loc[host] >= 0) & in_image(pix, W, H, MARGIN + 2))
        if len(ks) < 2 or not len(cand):
            continue
        scene = UnitScene(np.stack([stack_all[int(k)] for k in ks]), K, np.stack([se3_inv(T_wc[k]) for k in ks]),
                          np.zeros((len(ks), 2)), loc[host[cand]], pix[cand], rho[cand],
                          [loc[sub_obs[i]][loc[sub_obs[i]] >= 0] for i in cand],
                          np.array([sub.keyframes[k].segment for k in ks]))
        obs_pt, obs_kf = existing_targets(scene, cfg.max_targets - (cfg.nearby_slots if cfg.nearby_targets else 0))
        n_near = 0
        if cfg.nearby_targets:
            near_pt, near_kf = nearby_targets(scene, obs_pt, obs_kf, cfg)
            obs_pt, obs_kf, n_near = np.r_[obs_pt, near_pt], np.r_[obs_kf, near_kf], len(near_pt)
        out.totals.n_targets += len(obs_pt)
        out.totals.n_nearby_targets += n_near
        for part in connected_parts(len(ks), scene.host[obs_pt], obs_kf):  # one gauge per connected map
            _solve_part(scene, obs_pt, obs_kf, part, ks, cand, cfg, (H, W), out)
    return out


def _solve_part(scene: UnitScene, obs_pt: np.ndarray, obs_kf: np.ndarray, part: np.ndarray, ks: np.ndarray,
                cand: np.ndarray, cfg: BAConfig, hw: tuple[int, int], out: _Solved) -> None:
    """The BA of the blocks ``(obs_pt, obs_kf)`` (each block's point and target keyframe) whose keyframes lie in
    ``part`` (local indices of ``scene``, whose keyframes are ``ks`` and points ``cand`` of the sub-map), written
    into ``out``; its first keyframe fixed, and so is any keyframe no block of the part touches."""
    if len(part) < 2:
        return
    in_part = np.isin(scene.host[obs_pt], part)
    obs_pt, obs_kf = obs_pt[in_part], obs_kf[in_part]
    used = np.unique(obs_pt)
    remap = np.full(len(scene.host), -1)
    remap[used] = np.arange(len(used))
    free = np.zeros(len(scene.T_cw), bool)
    free[np.unique(np.r_[obs_kf, scene.host[used]])] = True
    free[part[0]] = False
    # the scale: that of the part's first segment (the one the others were bridged onto), so a bridge's can move
    segment = scene.segment
    assert segment is not None  # _solve_units gives every scene its keyframes' segments
    joined = len(np.unique(segment)) > 1
    anchor = (segment == segment[part[0]]) & np.isin(np.arange(len(free)), part) if joined else None
    H, W = hw
    r = solve(scene.problem(remap[obs_pt], obs_kf, used, free, anchor), iterations=cfg.iterations,
              huber_delta=cfg.huber_grey / 255, outlier_delta=cfg.outlier_grey / 255, pattern=pattern_of(cfg),
              max_targets=cfg.max_targets, levels=max(1, min(cfg.levels, int(np.log2(min(H, W) / 32)) + 1)),
              rounds=cfg.rounds)
    out.T_wc[ks[free]] = np.stack([se3_inv(T) for T in r.T_cw[free]])  # fixed ones keep their bits
    pts, gone = cand[used], r.stats["dropped"]
    sane = ~gone & (np.abs(np.log(r.inv_depth / scene.rho[used])) < np.log(MAX_CHANGE))
    out.rho[pts[sane]] = r.inv_depth[sane]
    out.refined[pts[sane]] = True
    out.dropped[pts[gone]] = True
    out.costs.extend(x["costs"] for x in r.stats["rounds"])
    t = out.totals
    t.n_diverged += int((~sane & ~gone).sum())
    t.n_blocks += r.stats["n_blocks"]
    t.n_outlier_blocks += r.stats["n_outlier_blocks"]
    t.iterations += r.stats["iterations"]
    t.accepted += r.stats["accepted"]
    t.cost0 += r.stats["cost0"]
    t.cost += r.stats["cost"]
    t.n_parts += 1


def _assemble(vo: VOResult, upto: int, T_wc: np.ndarray, sv: _Solved, sub_idx: np.ndarray,
              new_pix: np.ndarray) -> VOResult:
    """The refined map: refined points get their new inverse depth and (integer) host pixel; keyframes
    and frames after ``upto`` follow the correction of their nearest refined keyframe (:func:`_follow`)."""
    pts, nk, refined = vo.points, len(vo.keyframes), sv.refined
    inv, pixel = pts.inv_depth.copy(), pts.pixel.copy()
    inv[sub_idx[refined]] = sv.rho[refined]
    pixel[sub_idx[refined]] = new_pix[refined]
    T_new = sv.T_wc
    times = np.array([k.timestamp for k in vo.keyframes])
    segs = np.array([k.segment for k in vo.keyframes])
    later = np.arange(nk) > upto
    T_new = T_new.copy()
    T_new[later] = _follow(T_wc[later], times[later], segs[later], times[~later], segs[~later],
                           T_wc[~later], T_new[~later])
    fs = vo.frame_segment
    known = len(fs[fs >= 0]) == len(vo.traj_all)  # else: one segment, the first keyframe's
    seg0 = segs[0] if nk else 0
    seg_rows = fs[fs >= 0] if known else np.full(len(vo.traj_all), seg0)
    kf_ref = ~later if known else ~later & (segs == seg0)
    all_new = _follow(vo.traj_all.poses, vo.traj_all.timestamps, seg_rows, times[kf_ref], segs[kf_ref],
                      T_wc[kf_ref], T_new[kf_ref])
    return replace(vo, keyframes=[replace(k, pose=T_new[k.id]) for k in vo.keyframes],
                   points=replace(pts, inv_depth=inv, pixel=pixel),
                   traj_all=Trajectory(vo.traj_all.timestamps, all_new))

"""Map-point culling + global photometric BA as one stage (paper §III-C, DESIGN §6).

:func:`run_global_ba` takes a front-end map (a :class:`~mutualslam_cli.vo.result.VOResult`),
keyframe images at the BA resolution, the adapted network's depth and per-keyframe L_val, and
returns a refined copy. It is the only module that reads :class:`~mutualslam_cli.config.BAConfig`.

Choices the paper leaves open (written down here):

- **Host**: Eq. 10 judges each point in its best-validated observing keyframe (lowest L_val, Fig. 3,
  :func:`~mutualslam_cli.ba.culling.choose_hosts`), comparing the point's depth there with the CNN's.
  The BA keeps the front end's host (the keyframe where the feature was detected: its patch is the
  detected corner). Re-hosting the BA parameters in the best-validated keyframe (pixel = the point's
  projection there, exact at the time) was tried: on ``redkitchen_7scenes`` with GT depth as the
  "CNN", a mid-run BA and the final BA with re-hosting took keyframe ATE from 25.1 to 40–49 mm (two
  random L_val orders), without it to 34 mm; in the real run (adapted CNN, one Algorithm 1
  request) to 64 mm and map e_si from 0.176 to 0.238. A projected host pixel is off the tracked
  feature by the reprojection error, so each re-hosting moves the patch off its corner.
  ``n_judged_elsewhere`` counts the points judged in another keyframe than their host.
- **Targets** (≤ ``max_targets`` per point): the point's existing observations, nearest keyframe
  index first, where the point projects inside the image (patch + 2 px margin). DESIGN §6 would
  add nearby keyframes with a good patch correlation; not done: on the plane scene of
  :mod:`~mutualslam_cli.bench.ba` a 5×5 NCC ≥ 0.95 test let occluded patches in (8 of 56 added
  targets) and 72 added targets among 5 264 took the poses from 0.2 mm to 1–8 cm; on
  ``tum_fr1_xyz`` (NCC ≥ 0.8, half resolution, one level) they gave keyframe ATE 13.3 vs 12.6 mm
  and map e_si 0.137 vs 0.146: no clear gain for that risk.
- **Unrefined points**: a kept point with no valid target (or whose host patch leaves the image)
  is not in the BA and is kept *as it is* (host, pixel, inverse depth unchanged; it moves with its
  host keyframe's pose). Counted in ``n_unrefined``. So is a point whose inverse depth the BA
  changed by more than :data:`MAX_CHANGE` (``n_diverged``): on ``tum_fr1_xyz`` two points seen by
  two close keyframes only went to ×0.49 and to infinity (the solver's ρ floor), which alone took
  the map's e_si from 0.11 to 0.62; the other 648 moved by 9 % (median).
- **Segments**: a re-initialised front end has one map frame and scale per segment and no point
  is shared between segments, so each segment is its own BA (its first keyframe fixed, the scale
  held by the solver's prior on its first free baseline). Keyframes without any residual stay fixed.
- **Partial BA** (``upto``): only keyframes ``≤ upto`` and the points they host exist yet
  (Algorithm 1 triggers mid-run). Everything else follows the correction of its nearest refined
  keyframe, ``T_new = T_ref_new · T_ref_old⁻¹ · T``: later keyframes that of the last refined
  keyframe of their segment, frames of ``traj_all`` that of the latest keyframe at or before them
  (the first one of their segment before it). Points are host-relative, so they follow their host.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping

import numpy as np

from mutualslam_cli.ba.culling import cull_map_points
from mutualslam_cli.ba.photometric import PhotoBAProblem, solve
from mutualslam_cli.config import BAConfig
from mutualslam_cli.errors import ShapeError
from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.pixels import in_image, lookup_nearest
from mutualslam_cli.types import Trajectory
from mutualslam_cli.vo.result import VOResult

#: Pixels at the border of the BA image where a projection is invalid (the solver's margin).
MARGIN = 2.0
#: Pyramid levels of the solver (coarse-to-fine; 1 when the image is under 64 px on a side). On the
#: 6-keyframe plane scene at 320×240 with 1 cm / 0.3° / 2 % noise, one level stops at 7× the cost
#: of the true state (pose errors up to 1.1 mm), two go below it (0.2 mm). On ``tum_fr1_xyz`` at
#: half resolution the two are close: map e_si after BA 0.113 vs 0.115, keyframe ATE 13.2 vs 12.6 mm.
LEVELS = 2
#: Largest factor by which the BA may change a point's inverse depth; beyond it the point keeps
#: its value before BA (an under-constrained depth, e.g. one short-baseline target). The same
#: factor as a gross outlier of Eq. 10 with γ = 0.5.
MAX_CHANGE = 2.0


@dataclass
class GlobalBAResult:
    """Output of :func:`run_global_ba`.

    Attributes:
        vo: refined copy of the input: keyframe poses ≤ ``upto`` and the inverse depths of refined
            points replaced (hosts and pixels stay), the rest following (module docstring). Culled
            points are still in it, unchanged; :meth:`kept` drops them.
        keep: ``(P,)`` bool over the input's points, False = culled by Eq. 10.
        stats: ``n_points, n_culled, n_judged, n_judged_elsewhere, n_refined, n_unrefined`` (kept, not
            refined; ``n_diverged`` of them by :data:`MAX_CHANGE`), ``n_targets, keyframes, cost0,
            cost`` (summed over segments), ``costs`` (per segment, the full-resolution sequence),
            ``iterations, accepted, seconds``.
    """

    vo: VOResult
    keep: np.ndarray
    stats: dict = field(default_factory=dict)

    def kept(self) -> VOResult:
        """The refined map without the culled points."""
        return replace(self.vo, points=self.vo.points.subset(self.keep))


def _targets(K, T_cw, host, pix, rho, obs, max_targets, shape, border):
    """``(obs_pt, obs_kf)`` of one segment (local keyframe indices): per point its observations
    ``obs[i]`` where it projects inside, nearest keyframe index first, at most ``max_targets``."""
    cand_p = np.repeat(np.arange(len(host)), [len(o) for o in obs]).astype(np.int64)
    cand_k = np.concatenate(obs).astype(np.int64) if obs else np.zeros(0, np.int64)
    h = host[cand_p]
    ray = np.c_[(pix[cand_p] - K[:2, 2]) / np.diag(K)[:2], np.ones(len(cand_p))] / rho[cand_p, None]
    T_th = T_cw[cand_k] @ np.linalg.inv(T_cw[h])
    X = np.einsum("nij,nj->ni", T_th[:, :3, :3], ray) + T_th[:, :3, 3]
    z = X[:, 2]
    uv = (X[:, :2] / np.where(z > 1e-9, z, 1.0)[:, None]) * np.diag(K)[:2] + K[:2, 2]
    sel = np.flatnonzero((z > 1e-9) & (cand_k != h) & in_image(uv, shape[1], shape[0], border))
    order = sel[np.lexsort((cand_k[sel], np.abs(cand_k[sel] - h[sel]), cand_p[sel]))]
    p = cand_p[order]
    take = order[np.arange(len(p)) - np.searchsorted(p, p) < max_targets]  # rank within the point
    return cand_p[take], cand_k[take]


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
        out[m] = ref_new[j] @ np.linalg.inv(ref_old[j]) @ poses[m]
    return out


def run_global_ba(vo: VOResult, images: Callable[[int], np.ndarray],
                  depth_of: Callable[[int], np.ndarray] | None, val_loss: Mapping[int, float] | None,
                  cfg: BAConfig, *, cull: bool, upto: int | None = None) -> GlobalBAResult:
    """Cull the map with the CNN depth (Eq. 10), then photometric BA (Eq. 11–12) of every keyframe.

    Args:
        vo: the map (poses ``T_wc``, points host-relative, pinhole camera ``vo.intrinsics``).
        images: ``kf_id → (H, W)`` float grey in [0, 1], undistorted, at the BA resolution (any
            size; the camera is ``vo.intrinsics`` scaled to it).
        depth_of: ``kf_id → (h, w)`` CNN depth in map units at any resolution (looked up at the
            nearest pixel); ``None`` = no culling.
        val_loss: ``{kf_id: L_val}`` of the current network (host choice); ``None`` = front-end hosts.
        cfg: γ, d_max, patch, max_targets, iterations, huber_delta.
        cull: apply Eq. 10 (and re-host by L_val).
        upto: last keyframe that exists yet (default: the last one).

    Returns:
        :class:`GlobalBAResult`. Within each segment the robust cost never increases.
    """
    t0 = time.perf_counter()
    nk = len(vo.keyframes)
    upto = nk - 1 if upto is None else int(upto)
    pts = vo.points
    sub_idx = np.flatnonzero(pts.host <= upto)  # the points that exist at keyframe ``upto``
    sub_obs = [pts.observations[i][pts.observations[i] <= upto] for i in sub_idx]
    sub_pix = [pts.obs_pixels[i][pts.observations[i] <= upto] for i in sub_idx]
    sub = replace(vo, keyframes=vo.keyframes[:upto + 1],
                  points=replace(pts.subset(pts.host <= upto), observations=sub_obs, obs_pixels=sub_pix))
    keep = np.ones(len(pts), bool)
    host = sub.points.host  # the BA keeps the front end's hosts (module docstring)
    stats = {"n_points": len(pts), "n_culled": 0, "n_judged": 0, "n_judged_elsewhere": 0}
    if cull and depth_of is not None and len(sub_idx):
        cache: dict[int, np.ndarray] = {}

        def depth_at(k: int, uv: np.ndarray) -> np.ndarray:
            d = cache.setdefault(k, np.asarray(depth_of(k), float))
            if d.ndim != 2:
                raise ShapeError(f"depth_of({k}): expected an (h, w) depth map, got shape {d.shape}")
            return lookup_nearest(d, uv, (vo.intrinsics.width, vo.intrinsics.height))

        cr = cull_map_points(sub, val_loss or {}, depth_at, cfg.gamma, cfg.d_max)
        keep[sub_idx] = cr.keep
        stats.update(n_culled=int((~cr.keep).sum()), n_judged=int(cr.judged.sum()),
                     n_judged_elsewhere=int(np.sum(cr.host != host)))
    pix, rho = sub.points.pixel, sub.points.inv_depth

    # BA, one problem per segment, at the resolution of the images
    T_wc = np.stack([k.pose for k in vo.keyframes])
    T_new = T_wc.copy()
    refined = np.zeros(len(sub_idx), bool)
    new_rho = rho.copy()
    stack_all = {k: np.asarray(images(k), np.float32) for k in range(upto + 1)} if len(sub_idx) else {}
    H, W = next(iter(stack_all.values())).shape if stack_all else (vo.intrinsics.height, vo.intrinsics.width)
    if any(im.shape != (H, W) for im in stack_all.values()):
        raise ShapeError("run_global_ba: keyframe images must all have one size")
    s = np.array([W / vo.intrinsics.width, H / vo.intrinsics.height])
    K_ba = vo.intrinsics.scaled(W, H).K()
    pix_ba = (pix + 0.5) * s - 0.5
    border = MARGIN + cfg.patch // 2
    segs = np.array([k.segment for k in vo.keyframes])
    kf_in = np.arange(upto + 1)
    costs, tot = [], {"n_targets": 0, "n_diverged": 0, "iterations": 0, "accepted": 0, "cost0": 0.0, "cost": 0.0}
    for sg in np.unique(segs[kf_in]):
        ks = kf_in[segs[kf_in] == sg]
        loc = np.full(nk, -1)
        loc[ks] = np.arange(len(ks))
        cand = np.flatnonzero(keep[sub_idx] & (loc[host] >= 0) & in_image(pix_ba, W, H, border))
        if len(ks) < 2 or not len(cand):
            continue
        stack = np.stack([stack_all[k] for k in ks])
        T_cw = np.stack([se3_inv(T_wc[k]) for k in ks])
        obs = [loc[sub_obs[i]][loc[sub_obs[i]] >= 0] for i in cand]
        op, ok_ = _targets(K_ba, T_cw, loc[host[cand]], pix_ba[cand], rho[cand], obs, cfg.max_targets,
                           (H, W), border)
        used = np.unique(op)
        if not len(used):
            continue
        remap = np.full(len(cand), -1)
        remap[used] = np.arange(len(used))
        pts_in = cand[used]
        free = np.zeros(len(ks), bool)
        free[np.unique(np.r_[ok_, loc[host[pts_in]]])] = True
        free[0] = False
        prob = PhotoBAProblem(stack, K_ba, T_cw, np.zeros((len(ks), 2)), loc[host[pts_in]], pix_ba[pts_in],
                              rho[pts_in], remap[op], ok_, free)
        r = solve(prob, iterations=cfg.iterations, huber_delta=cfg.huber_delta, patch=cfg.patch,
                  max_targets=cfg.max_targets, levels=LEVELS if min(H, W) >= 64 else 1)
        T_new[ks[free]] = np.stack([se3_inv(T) for T in r.T_cw[free]])  # fixed ones keep their bits
        sane = np.abs(np.log(r.inv_depth / rho[pts_in])) < np.log(MAX_CHANGE)
        new_rho[pts_in[sane]] = r.inv_depth[sane]
        refined[pts_in[sane]] = True
        costs.append(r.stats["costs"])
        for k, v in (("n_targets", len(op)), ("n_diverged", int((~sane).sum())),
                     ("iterations", r.stats["iterations"]), ("accepted", r.stats["accepted"]),
                     ("cost0", r.stats["cost0"]), ("cost", r.stats["cost"])):
            tot[k] += v

    # assemble: refined rows get their new inverse depth; the rest stay as they are
    inv = pts.inv_depth.copy()
    inv[sub_idx[refined]] = new_rho[refined]
    times = np.array([k.timestamp for k in vo.keyframes])
    later = np.arange(nk) > upto
    T_new[later] = _follow(T_wc[later], times[later], segs[later], times[~later], segs[~later],
                           T_wc[~later], T_new[~later])
    fs = vo.frame_segment
    known = len(fs[fs >= 0]) == len(vo.traj_all)  # else: one segment, the first keyframe's
    seg0 = segs[0] if nk else 0
    seg_rows = fs[fs >= 0] if known else np.full(len(vo.traj_all), seg0)
    kf_ref = ~later if known else ~later & (segs == seg0)
    all_new = _follow(vo.traj_all.poses, vo.traj_all.timestamps, seg_rows, times[kf_ref], segs[kf_ref],
                      T_wc[kf_ref], T_new[kf_ref])
    out = replace(vo, keyframes=[replace(k, pose=T_new[k.id]) for k in vo.keyframes],
                  points=replace(pts, inv_depth=inv),
                  traj_all=Trajectory(vo.traj_all.timestamps, all_new))
    stats.update(tot, n_refined=int(refined.sum()), n_unrefined=int((keep[sub_idx] & ~refined).sum()),
                 keyframes=upto + 1, costs=costs, seconds=time.perf_counter() - t0)
    return GlobalBAResult(out, keep, stats)

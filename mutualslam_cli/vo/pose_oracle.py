"""Pose oracle front end (``--vo gt``, DESIGN §4): our VO's tracks, GT poses, re-triangulated map.

It studies adaptation apart from *pose* error without leaking dense GT depth: the keyframes
and the map points' image tracks are our own VO's (same density, same KLT noise, same
points), only the keyframe poses are replaced by GT poses and every map point is
re-triangulated from its tracks with those poses held fixed, so depths are metric.

Per point: the host observation fixes the bearing; a linear DLT over all observations (in
the host camera frame) gives the starting inverse depth, refined by Gauss–Newton on the
reprojection error of the other observations (one unknown: the inverse depth in the host).
Rejected, each counted in ``meta["points"]["rejected"]``:

* ``few_obs``: fewer than 2 observing keyframes with a GT pose;
* ``behind``: not in front of every observing camera (or DLT at infinity / non-finite);
* ``parallax``: largest angle at the point between the host ray and another observing
  ray below :data:`MIN_PARALLAX_DEG` (depth along the ray not fixed by the tracks);
* ``reprojection``: RMS reprojection error of the non-host observations above the gate
  ``max(MAX_RMS_PX, RMS_GATE_FACTOR × median point RMS)``.

The gate is 2 px where the GT poses fit the images to a pixel (synthetic, ICL-NUIM: median
point RMS 0.4 px). On TUM fr1 (rolling shutter, mocap-to-camera calibration) the GT poses
miss our own tracks by a median 3–4 px, on 7-Scenes (KinectFusion poses of the depth camera,
colour camera not registered) by 5–12 px; a fixed 2 px gate would keep 12 % resp. 8 % of the
map there, so the gate scales with the sequence's median and still removes the outlier
tracks. ``meta["points"]`` records the median and the gate: a large median means the "GT"
poses are not pixel-accurate for this camera, and the triangulated depths inherit that.

Keyframes without a GT pose are dropped and the rest renumbered (``keyframes[k].id == k``);
a point whose host was dropped is re-hosted on its first remaining observing keyframe.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from itertools import combinations
from typing import cast

import numpy as np

from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import backproject, project, se3_inv
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.types import Trajectory
from mutualslam_cli.vo.frontend import run_vo

log = logging.getLogger(__name__)

MAX_RMS_PX = 2.0
"""Reprojection gate (RMS over the non-host observations, pixels) when the poses fit the tracks."""

RMS_GATE_FACTOR = 3.0
"""The gate grows to this multiple of the median point RMS when the GT poses fit worse."""

MIN_PARALLAX_DEG = 1.0
"""Smallest usable ray angle at the point (degrees). With ~1 px track noise at f ≈ 500 px a
pixel is 0.11°, so 1° bounds the depth error from one pixel of noise to roughly 10 %."""

GN_ITERS = 8
"""Gauss–Newton iterations on the inverse depth (1-D, converges in 3–4 from the DLT)."""

SIGMA_PX = 1.0
"""Nominal track noise (pixels) behind the reported ``sigma`` of the inverse depth."""

REASONS = ("few_obs", "behind", "parallax", "reprojection")


def remap_tracks(points: MapPoints, kf_map: np.ndarray) -> tuple[MapPoints, int]:
    """Renumber the keyframes of every track and drop the observations of removed keyframes.

    Args:
        points: map points of the source front end.
        kf_map: ``(K_old,)`` int, new keyframe id of each old one, −1 = dropped.
    Returns:
        ``(points, n_rehosted)``: same rows (``inv_depth``/``sigma`` copied, not yet
        re-triangulated), ``pixel`` = the host's observation; a point whose host was dropped
        gets its first remaining observation as host; one with no observation left gets host −1.
    """
    host = kf_map[points.host].astype(np.int64)
    pixel = points.pixel.copy()
    obs, obs_px, rehosted = [], [], 0
    for i, (o, px) in enumerate(zip(points.observations, points.obs_pixels)):
        new = kf_map[o]
        keep = new >= 0
        obs.append(new[keep].astype(np.int64))
        obs_px.append(px[keep].reshape(-1, 2))
        at = np.flatnonzero(obs[-1] == host[i])
        if len(at):
            pixel[i] = obs_px[-1][at[0]]
        elif len(obs[-1]):
            host[i], pixel[i] = obs[-1][0], obs_px[-1][0]
            rehosted += 1
        else:
            host[i] = -1
    out = MapPoints(points.ids.copy(), host, pixel, points.inv_depth.copy(), points.sigma.copy(), obs, obs_px)
    return out, rehosted


def retriangulate(points: MapPoints, poses_wc: np.ndarray, K: np.ndarray,
                  max_rms_px: float | None = None) -> tuple[MapPoints, dict]:
    """Re-triangulate every point from its tracks with the keyframe poses fixed.

    Args:
        points: tracks (``observations`` are indices into ``poses_wc``; ``obs_pixels`` pinhole
            pixels; the host is one of the observations).
        poses_wc: ``(K, 4, 4)`` ``T_wc`` of the keyframes, metres.
        K: ``(3, 3)`` pinhole intrinsics of the pixels (``fy`` may be negative).
        max_rms_px: reprojection gate in pixels; ``None`` → ``max(MAX_RMS_PX, RMS_GATE_FACTOR ×
            median RMS of the points passing the other tests)``.
    Returns:
        ``(kept, stats)``: the surviving points (``ids`` renumbered ``0..P-1``, ``pixel`` =
        the host observation, ``inv_depth`` in 1/m, ``sigma`` its standard deviation in 1/m
        for :data:`SIGMA_PX` of track noise) and ``{"rejected": {reason: count} over
        REASONS, "rms_median_px", "rms_gate_px"}``.
    """
    n = len(points)
    nobs = np.array([len(o) for o in points.observations], np.int64)
    bad = np.zeros(n, np.int64)  # 0 = kept, else 1 + index into REASONS
    bad[(nobs < 2) | (points.host < 0)] = 1
    if n == 0 or not np.any(bad == 0):
        return points.subset(np.zeros(n, bool)), _stats(bad, float("nan"), float("nan"))
    # one row per observation ("edge"): point p_e seen in keyframe k_e at pixel uv_e
    p_e = np.repeat(np.arange(n), nobs)
    k_e = np.concatenate(points.observations).astype(np.int64)
    uv_e = np.concatenate(points.obs_pixels).reshape(-1, 2)
    h_e = points.host[p_e]
    live = bad[p_e] == 0
    p_e, k_e, uv_e, h_e = p_e[live], k_e[live], uv_e[live], h_e[live]
    is_host = k_e == h_e
    T_kh = se3_inv(poses_wc[k_e]) @ poses_wc[h_e]  # host camera → observing camera
    R, t = T_kh[:, :3, :3], T_kh[:, :3, 3]
    xn = backproject(uv_e, np.ones(len(uv_e)), K)  # (x, y, 1) per observation
    f_h = backproject(points.pixel, np.ones(n), K)  # host bearing (z = 1)
    # linear DLT in the host frame: x·P₃ − P₁ = 0, y·P₃ − P₂ = 0 with P = [R | t]
    P = np.concatenate([R, t[:, :, None]], axis=2)
    A = np.stack([xn[:, :1] * P[:, 2] - P[:, 0], xn[:, 1:2] * P[:, 2] - P[:, 1]], axis=1)
    M = np.zeros((n, 4, 4))
    np.add.at(M, p_e, np.einsum("eri,erj->eij", A, A))
    _, vec = np.linalg.eigh(M)
    X = vec[:, :, 0]  # homogeneous point, smallest eigenvalue
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = X[:, 3] / X[:, 2]  # inverse depth in the host: z = X₂ / X₃
    bad[(bad == 0) & ~(np.isfinite(rho) & (rho > 0))] = 2
    rho = np.where(bad == 0, rho, 1.0)
    # Gauss–Newton on rho: Y = R f_h + rho t ∝ the point in the observing camera
    Rf = np.einsum("eij,ej->ei", R, f_h[p_e])
    H: np.ndarray = np.zeros(n)
    for _ in range(GN_ITERS):
        r, J, Y = _residuals(Rf, t, rho[p_e], uv_e, K)
        H = np.bincount(p_e, (J ** 2).sum(1), minlength=n)
        g = np.bincount(p_e, (J * r).sum(1), minlength=n)
        step = np.where(H > 0, -g / np.where(H > 0, H, 1.0), 0.0)
        new = rho + step
        rho = np.where(new > 0, new, 0.5 * rho)  # stay in front of the host camera
    r, J, Y = _residuals(Rf, t, rho[p_e], uv_e, K)
    H = np.bincount(p_e, (J ** 2).sum(1), minlength=n)
    behind = np.bincount(p_e, Y[:, 2] <= 1e-9, minlength=n) > 0
    bad[(bad == 0) & behind] = 2
    # parallax: angle at the point between the host ray and each other camera's ray
    Xh = f_h[p_e] / rho[p_e, None]
    C = -np.einsum("eji,ej->ei", R, t)  # observing camera centre in the host frame
    b = Xh - C
    cos = (Xh * b).sum(1) / (np.linalg.norm(Xh, axis=1) * np.linalg.norm(b, axis=1) + 1e-300)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    max_ang = np.zeros(n)
    np.maximum.at(max_ang, p_e, np.where(is_host, 0.0, ang))
    bad[(bad == 0) & (max_ang < MIN_PARALLAX_DEG)] = 3
    sq = np.bincount(p_e, np.where(is_host, 0.0, (r ** 2).sum(1)), minlength=n)
    cnt = np.bincount(p_e, ~is_host, minlength=n)
    rms = np.sqrt(sq / np.maximum(cnt, 1))
    med = float(np.median(rms[bad == 0])) if np.any(bad == 0) else float("nan")
    gate = max(MAX_RMS_PX, RMS_GATE_FACTOR * med) if max_rms_px is None else max_rms_px
    bad[(bad == 0) & (rms > gate)] = 4
    keep = bad == 0
    out = points.subset(keep)
    out.ids = np.arange(len(out), dtype=np.int64)
    out.inv_depth = rho[keep]
    out.sigma = SIGMA_PX / np.sqrt(np.maximum(H[keep], 1e-300))
    return out, _stats(bad, med, gate)


def _residuals(Rf: np.ndarray, t: np.ndarray, rho: np.ndarray, uv: np.ndarray,
               K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: residual ``(E, 2)`` px, d(residual)/d(rho) ``(E, 2)``, ``Y`` ``(E, 3)``."""
    Y = Rf + rho[:, None] * t
    pred, z = project(Y, K)
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    J = np.stack([K[0, 0] * (t[:, 0] * zs - Y[:, 0] * t[:, 2]),
                  K[1, 1] * (t[:, 1] * zs - Y[:, 1] * t[:, 2])], axis=1) / (zs ** 2)[:, None]
    return pred - uv, J, Y


def _stats(bad: np.ndarray, med: float, gate: float) -> dict:
    return {"rejected": {name: int(np.sum(bad == j + 1)) for j, name in enumerate(REASONS)},
            "rms_median_px": med, "rms_gate_px": gate}


def run_pose_oracle(seq: Sequence, cfg: VOConfig, seed: int = 0,
                    progress: Callable[[dict], None] | None = None, *, vo: VOResult | None = None) -> VOResult:
    """Our VO's keyframes and tracks with GT poses and a re-triangulated metric map.

    Args:
        seq: the sequence; keyframe GT poses are the frames' ``pose`` (the loader's GT
            interpolated at image times, as for the ``gt-depth`` oracle).
        cfg: VO options (passed to :func:`~mutualslam_cli.vo.frontend.run_vo`).
        seed: RANSAC seed of the VO run.
        progress: the VO's per-frame callback.
        vo: an ``svo`` result of this ``seq``/``cfg``/``seed`` to reuse (e.g. from the VO cache)
            instead of running the front end again.
    Returns:
        :class:`VOResult` in the GT world frame (metres): keyframes with GT ``T_wc`` (segment 0),
        points with ``inv_depth``/``sigma`` in 1/m, ``traj_all`` = GT poses at the frames the VO
        tracked that have GT (``frame_segment`` 0 there, −1 elsewhere), ``covisibility`` of
        the kept points; ``meta`` = ``{"mode": "gt", "oracle": "pose", "vo_meta", "keyframes":
        {"vo", "dropped_no_gt"}, "points": {"vo", "triangulated", "rehosted", "rejected":
        {reason: n}, "rms_median_px", "rms_gate_px"}, "vo_time_s", "time_s"}``.
    Raises:
        DatasetError: no keyframe of the VO has a GT pose.
    """
    t0 = time.perf_counter()
    if not seq.has_gt_poses:
        raise DatasetError(f"{seq.root}: --vo gt needs GT poses; the sequence has none")
    if vo is None:
        vo = run_vo(seq, cfg, seed=seed, progress=progress)
    t_vo = time.perf_counter() - t0
    gt_pose = [seq.frames[kf.frame_index].pose for kf in vo.keyframes]
    kept_kf = [kf for kf, T in zip(vo.keyframes, gt_pose) if T is not None]
    if not kept_kf:
        raise DatasetError(f"{seq.root}: --vo gt: none of the VO's {len(vo.keyframes)} keyframes has a GT pose")
    kf_map = -np.ones(len(vo.keyframes), np.int64)
    kf_map[[kf.id for kf in kept_kf]] = np.arange(len(kept_kf))
    keyframes = [Keyframe(k, kf.frame_index, kf.timestamp, np.array(seq.frames[kf.frame_index].pose), 0)
                 for k, kf in enumerate(kept_kf)]
    tracks, rehosted = remap_tracks(vo.points, kf_map)
    points, stats = retriangulate(tracks, np.stack([kf.pose for kf in keyframes]), vo.intrinsics.K())
    covis: dict[int, dict[int, int]] = {k: {} for k in range(len(keyframes))}
    for o in points.observations:
        for a, b in combinations(o.tolist(), 2):
            covis[a][b] = covis[a].get(b, 0) + 1
            covis[b][a] = covis[b].get(a, 0) + 1
    seg = np.array([0 if s >= 0 and f.pose is not None else -1 for s, f in zip(vo.frame_segment, seq.frames)])
    idx = np.flatnonzero(seg >= 0)
    traj = Trajectory(np.array([seq.frames[i].timestamp for i in idx]),
                      np.stack([cast(np.ndarray, seq.frames[i].pose) for i in idx])  # idx: frames with a pose
                      if len(idx) else np.zeros((0, 4, 4)))
    elapsed = time.perf_counter() - t0
    meta = {
        "mode": "gt", "oracle": "pose", "vo_meta": vo.meta,
        "keyframes": {"vo": len(vo.keyframes), "dropped_no_gt": len(vo.keyframes) - len(keyframes)},
        "points": {"vo": len(vo.points), "triangulated": len(points), "rehosted": rehosted, **stats},
        "min_parallax_deg": MIN_PARALLAX_DEG,
        "vo_time_s": t_vo, "time_s": elapsed, "reinitialisations": 0,
    }
    log.info("pose oracle: %d/%d keyframes with GT, %d/%d points re-triangulated (rejected %s; median "
             "RMS %.2f px, gate %.2f px; %.2f s)", len(keyframes), len(vo.keyframes), len(points), len(vo.points),
             stats["rejected"], stats["rms_median_px"], stats["rms_gate_px"], elapsed)
    return VOResult(keyframes, points, vo.intrinsics, traj, seg, covis, meta)

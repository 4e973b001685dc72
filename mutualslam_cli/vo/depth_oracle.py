"""GT-depth oracle front end (``--vo gt-depth``, DESIGN §4): GT poses and sparse points from GT depth.

It studies adaptation apart from VO error: keyframes every ``gt_kf_every`` frames that have a
GT pose and a depth image, map points at corners detected on a grid in each keyframe with
their GT depth, observed in every nearby keyframe where they project inside the image with
a consistent GT depth. Pixels are undistorted (pinhole ``K``) like the real front end's.

Besides exact poses it hands adaptation exact GT sparse depth at ~5× our map's density
(median 1,895 labels per keyframe against 358 for our VO on tum_fr1_xyz): an upper bound
that leaks GT depth. The honest oracle, GT poses only, is ``--vo gt``
(:mod:`~mutualslam_cli.vo.pose_oracle`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import cv2
import numpy as np

from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import backproject, project, se3_inv, transform
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.pixels import in_image, lookup_nearest
from mutualslam_cli.types import Intrinsics, Trajectory
from mutualslam_cli.vo.camera import distort_points, undistort_points

log = logging.getLogger(__name__)

#: Neighbouring keyframes (each side) searched for observations of a point.
OBS_WINDOW = 4
#: Relative depth agreement for a point to count as visible in another keyframe.
OBS_DEPTH_TOL = 0.05


def grid_corners(gray: np.ndarray, grid_size: int, max_fts: int) -> np.ndarray:
    """Strongest Shi–Tomasi corner per ``grid_size`` cell, at most ``max_fts``.

    Args:
        gray: ``(H, W)`` uint8 image.
    Returns:
        ``(N, 2)`` float64 pixels ``(u, v)``, strongest first.
    """
    h, w = gray.shape
    resp = cv2.cornerMinEigenVal(gray, 3)
    gh, gw = h // grid_size, w // grid_size
    if gh == 0 or gw == 0:
        return np.zeros((0, 2))
    cells = resp[: gh * grid_size, : gw * grid_size].reshape(gh, grid_size, gw, grid_size)
    cells = cells.transpose(0, 2, 1, 3).reshape(gh, gw, -1)
    arg = cells.argmax(axis=2)
    best = np.take_along_axis(cells, arg[..., None], axis=2)[..., 0]
    rows, cols = np.divmod(arg, grid_size)
    v = rows + np.arange(gh)[:, None] * grid_size
    u = cols + np.arange(gw)[None, :] * grid_size
    thresh = 0.01 * float(resp.max()) if resp.size else 0.0
    ok = best > max(thresh, 1e-6)
    order = np.argsort(-best[ok], kind="stable")[:max_fts]
    return np.stack([u[ok], v[ok]], axis=1)[order].astype(np.float64)


def run_oracle(seq: Sequence, cfg: VOConfig, seed: int = 0,
               progress: Callable[[dict], None] | None = None) -> VOResult:
    """Keyframes with GT poses and map points from GT depth (see module docstring).

    Raises:
        DatasetError: the sequence has no frame with both a GT pose and a depth image.
    """
    t0 = time.perf_counter()
    intr = seq.intrinsics
    pin = Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height, None)
    K = pin.K()
    eligible = [i for i, f in enumerate(seq.frames) if f.pose is not None and f.depth_path is not None]
    if not eligible:
        raise DatasetError(f"{seq.root}: --vo gt-depth needs frames with both a GT pose and a depth image; found none")
    kf_frames = eligible[:: max(1, cfg.gt_kf_every)]
    keyframes: list[Keyframe] = []
    depths: list[np.ndarray] = []
    hosts, pixels, invd = [], [], []
    for k, fi in enumerate(kf_frames):
        f = seq.frames[fi]
        keyframes.append(Keyframe(k, fi, f.timestamp, np.array(f.pose), 0))
        depth = seq.load_depth(fi)
        depths.append(depth)  # type: ignore[arg-type]
        raw = grid_corners(seq.load_gray(fi), cfg.grid_size, 4 * cfg.max_fts)
        d = lookup_nearest(depth, raw, fill=0.0)  # type: ignore[arg-type]
        ok = d > 0
        raw, d = raw[ok][: cfg.gt_max_points], d[ok][: cfg.gt_max_points]
        hosts.append(np.full(len(d), k))
        pixels.append(undistort_points(raw, intr))
        invd.append(1.0 / d.astype(np.float64))
        if progress:
            progress({"frame": fi, "n_frames": len(seq), "keyframes": k + 1, "tracked": int(ok.sum()),
                      "state": "oracle"})
    host = np.concatenate(hosts).astype(np.int64)
    pix = np.concatenate(pixels)
    inv = np.concatenate(invd)
    n = len(host)
    # World points once, then visibility in nearby keyframes with a GT-depth consistency test.
    pw = np.zeros((n, 3))
    for k, kf in enumerate(keyframes):
        m = host == k
        pw[m] = transform(kf.pose, backproject(pix[m], 1.0 / inv[m], K))
    obs: list[list[int]] = [[int(h)] for h in host]
    obs_pix: list[list[np.ndarray]] = [[p] for p in pix]
    cov: dict[int, dict[int, int]] = {k: {} for k in range(len(keyframes))}
    for k, kf in enumerate(keyframes):
        lo, hi = max(0, k - OBS_WINDOW), min(len(keyframes), k + OBS_WINDOW + 1)
        cand = np.flatnonzero((host >= lo) & (host < hi) & (host != k))
        if len(cand) == 0:
            continue
        uv, z = project(transform(se3_inv(kf.pose), pw[cand]), K)
        inside = (z > 0) & in_image(uv, pin.width, pin.height)
        dz = lookup_nearest(depths[k], distort_points(uv, intr), fill=0.0)
        vis = inside & (dz > 0) & (np.abs(dz - z) < OBS_DEPTH_TOL * np.maximum(z, 1e-6))
        for i, p in zip(cand[vis], uv[vis]):
            obs[i].append(k)
            obs_pix[i].append(p)
            h = int(host[i])
            cov[k][h] = cov[k].get(h, 0) + 1
            cov[h][k] = cov[h].get(k, 0) + 1
    points = MapPoints(
        ids=np.arange(n, dtype=np.int64), host=host, pixel=pix, inv_depth=inv, sigma=np.zeros(n),
        observations=[np.array(o, dtype=np.int64) for o in obs],
        obs_pixels=[np.array(p).reshape(-1, 2) for p in obs_pix],
    )
    gt = seq.gt_at_frames()
    assert gt is not None  # eligible frames exist
    seg = np.array([0 if f.pose is not None else -1 for f in seq.frames])
    elapsed = time.perf_counter() - t0
    log.info("oracle front end: %d keyframes, %d map points (%.2f s)", len(keyframes), n, elapsed)
    return VOResult(
        keyframes=keyframes, points=points, intrinsics=pin, traj_all=Trajectory(gt.timestamps, gt.poses),
        frame_segment=seg, covisibility=cov,
        meta={"mode": "gt-depth", "kf_every": cfg.gt_kf_every, "time_s": elapsed, "reinitialisations": 0},
    )

"""Synthetic photometric-BA problems and the global-BA benchmark (DESIGN §10).

``mslam bench ba`` (:func:`ba_bench`; and the ``ba`` section of ``make bench``, :func:`bench_ba`) times
:func:`~mutualslam_cli.backend.ba.photometric.solve` with 10 LM iterations on 100 keyframes × 10 000 points
(≤ 5 targets, 3×3 patch; design target ≤ 5 s) and reports what it recovers, before and after: keyframe centre
error (mm, max and RMS; also the map's scale error and the centre error after a Sim(3) alignment), rotation
error (deg), inverse-depth relative error (median, p95), cost and accepted steps (:func:`accuracy`, :func:`report`).

**The problem** (:data:`BENCH_PROBLEM`): 640×480 images (f = 576 px) of a back wall, five
vertical panels at staggered depths and a shelf, 1.1–2.2 m away, rendered by analytic
ray–plane intersection from 2.5 mm texels (below a pixel), so residuals vanish at the true state
up to the solver's bilinear interpolation. The 100 keyframes lie evenly (3.4–3.5 cm apart) on a
closed loop of about 3.5 m: 1.7 m across the panels and back up to 8 cm higher, ±10 cm towards
them, yawing ±5°, pitching ±3°, rolling ±2°. A point's targets are the nearest keyframes by
camera centre (of the 10 nearest) that see its patch unoccluded, so the two passes and the loop's
ends are linked (about a quarter of the observations are more than 10 keyframes from their host):
baselines 3.5–17 cm (median 5.8), parallax median 19 px (p10 11 px). (An open sweep linked by keyframe
index determined scale and bending too weakly: LM started 0.1 mm from the truth settled 5 mm away.)

**The perturbation** (:data:`BENCH_PERTURBATION`, :func:`perturb`, rng seed 1): every keyframe
but the gauge 2 mm and 0.05° off, then the centres rescaled about keyframe 0 to the true extent of
the trajectory (the solver's scale anchor: a monocular BA cannot recover the unit), every inverse
depth ±3 %, i.e. 6 % of a neighbour baseline, 0.5 px of rotation and ~0.6 px of depth parallax: a
VO front end's relative error between neighbouring keyframes.

**Measured** (one run, AMD EPYC, avx2 avx512_bf16, no AMX; median of 3): the BA before DSO's
outlier handling (Huber at 0.1, no gradient weights, a prior on the first baseline) took 1.56 s and
ended 5.6 mm (max) from the true centres, mostly scale (−0.32 %; 0.37 mm after a Sim(3) alignment);
the robust BA (Huber at 5 grey levels, gradient weights, two rounds of outlier classification, the
extent anchor) takes 3.5 s and ends 0.24 mm (max) from them, 0.06 mm RMS after Sim(3), inverse
depths 0.03 % (median) off; the cost at the true state is 0.0026, after BA 0.0082. ``path="compact"``
(the default of :func:`synthetic_problem`) is the unit tests' small scene.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import TypedDict, TypeGuard

import cv2
import numpy as np

from mutualslam_cli.backend.ba.lm import centres, extent
from mutualslam_cli.backend.ba.photometric import PhotoBAProblem, solve
from mutualslam_cli.geometry import exp_so3
from mutualslam_cli.metrics.alignment import umeyama
from mutualslam_cli.pixels import in_image_uv

# fronto-parallel panels z = depth (y down, z forward), each limited to a box in (x, y), so
# 3×3 patches sharing one inverse depth are exact: (depth, x_min, x_max, y_min, y_max)
_PLANES = [(3.0, -np.inf, np.inf, -np.inf, np.inf), (2.0, -np.inf, -0.3, -np.inf, np.inf),
           (2.4, 0.5, np.inf, 0.0, np.inf)]


def _texture(rng: np.random.Generator, size: int = 512, cells: int = 24) -> np.ndarray:
    """Smooth random texture in [0.1, 0.9]: upsampled noise blurred with a Gaussian."""
    t = cv2.resize(rng.random((cells, cells)).astype(np.float32), (size, size),
                   interpolation=cv2.INTER_CUBIC)
    t = cv2.GaussianBlur(t, (0, 0), size / cells * 0.6)
    t = (t - t.min()) / (t.max() - t.min())
    return 0.1 + 0.8 * t


def render(T_cw: np.ndarray, K: np.ndarray, hw: tuple[int, int], textures: list[np.ndarray],
           px_per_m: float = 100.0, planes: list[tuple] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render grey image ``(H, W)`` float32 and z-depth ``(H, W)`` (metres) of the plane scene
    ``planes`` (default the compact scene's), one texture per plane."""
    H, W = hw
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    ray_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R_wc = T_cw[:3, :3].T
    c = -R_wc @ T_cw[:3, 3]
    ray = ray_c @ R_wc.T
    best = np.full((H, W), np.inf)
    img = np.zeros((H, W), np.float32)
    for (d, x0, x1, y0, y1), tex in zip(_PLANES if planes is None else planes, textures):
        lam = (d - c[2]) / np.where(np.abs(ray[..., 2]) > 1e-9, ray[..., 2], 1e-9)
        X = c + lam[..., None] * ray
        hit = (lam > 0) & (lam < best) & (X[..., 0] > x0) & (X[..., 0] < x1) \
            & (X[..., 1] > y0) & (X[..., 1] < y1)
        mx = (X[..., 0] * px_per_m).astype(np.float32)
        my = (X[..., 1] * px_per_m).astype(np.float32)
        val = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        img = np.where(hit, val, img)
        best = np.where(hit, lam, best)
    return img, best  # ray_c has z = 1, so λ is the z-depth


def _pose(i: int, n: int, extent: float) -> np.ndarray:
    s = i / max(n - 1, 1)
    c = extent * np.array([s - 0.5 + 0.03 * np.sin(7 * s), 0.1 * np.sin(3 * s), 0.2 * np.cos(4 * s)])
    R = exp_so3(np.array([[0.01 * np.sin(5 * s), 0.02 * (s - 0.5), 0.01 * np.cos(2 * s)]]))[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ c
    return T


# the loop scene: a back wall, vertical panels at staggered depths and a low shelf in front, so
# every view of the loop path sees three or four depths between 1.5 and 3.6 m
_LOOP_PLANES = [(2.2, -np.inf, np.inf, -np.inf, np.inf), (1.25, -1.45, -0.9, -np.inf, np.inf),
                (1.55, -0.8, -0.3, -np.inf, np.inf), (1.2, -0.2, 0.25, -np.inf, np.inf),
                (1.7, 0.35, 0.85, -np.inf, np.inf), (1.4, 0.95, 1.5, -np.inf, np.inf),
                (1.1, -np.inf, np.inf, 0.22, np.inf)]


def _loop_poses(n: int, length: float) -> np.ndarray:
    """``(n, 4, 4)`` ``T_cw`` evenly spaced (arc length) on a closed loop about ``2·length``
    metres long: across the panels along x (``length`` metres, centred on 0) and back, the
    return pass up to 8 cm higher; z (towards the panels) goes ±10 cm along x, the camera yaws
    ±5°, pitches ±3° (up on the way out, down on the way back) and rolls ±2°."""
    t = np.linspace(0.0, 1.0, 20_001)
    curve = np.stack([-0.5 * length * np.cos(2 * np.pi * t), -0.04 * np.sin(2 * np.pi * t),
                      0.1 * np.cos(4 * np.pi * t)], 1)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))]
    ti = np.interp(np.arange(n) / n * arc[-1], arc, t)
    out = np.tile(np.eye(4), (n, 1, 1))
    for k, s in enumerate(ti):
        c = np.array([np.interp(s, t, curve[:, j]) for j in range(3)])
        phi = np.deg2rad([3.0 * np.sin(2 * np.pi * s), 5.0 * np.sin(2 * np.pi * c[0] / 1.1),
                          2.0 * np.cos(6 * np.pi * s)])
        R = exp_so3(phi[None])[0]  # camera-to-world rotation
        out[k, :3, :3], out[k, :3, 3] = R.T, -R.T @ c
    return out


def synthetic_problem(n_kf: int = 6, n_points: int = 600, hw: tuple[int, int] = (120, 160),
                      max_targets: int = 5, fy_sign: float = 1.0, extent: float = 0.4,
                      seed: int = 0, path: str = "compact", cells: int = 24,
                      ) -> tuple[PhotoBAProblem, np.ndarray]:
    """True-state problem on a plane scene.

    ``path="compact"`` (default, the unit tests' scene): camera centres within about
    ``extent`` metres along x in front of three panels at 2–3 m, nearly fronto-parallel.
    ``path="loop"`` (the benchmark's): :func:`_loop_poses` across ``extent`` metres and back in
    front of :data:`_LOOP_PLANES` (1.5–3.6 m). ``cells``: texture cells per 5.12 m (finer =
    sharper). Targets: nearest keyframes by index (compact) or by camera centre (loop).

    Returns:
        ``(problem, depths)``: a :class:`PhotoBAProblem` at the true poses/inverse depths with
        zero affine, and the rendered z-depths ``(K, H, W)``.
    """
    rng = np.random.default_rng(seed)
    H, W = hw
    f = 0.9 * W
    K = np.array([[f, 0, W / 2 - 0.5], [0, fy_sign * f, H / 2 - 0.5], [0, 0, 1]])
    if path not in ("compact", "loop"):
        raise ValueError(f"synthetic_problem: path must be 'compact' or 'loop', got {path!r}")
    planes = _PLANES if path == "compact" else _LOOP_PLANES
    # loop: 2.5 mm texels (< 1 px at 1.5 m), so the renders are smooth at the pixel scale
    size, ppm = (512, 100.0) if path == "compact" else (2048, 400.0)
    textures = [_texture(rng, size=size, cells=cells) for _ in planes]
    T = np.stack([_pose(i, n_kf, extent) for i in range(n_kf)]) if path == "compact" else _loop_poses(n_kf, extent)
    imgs, deps = zip(*(render(T[i], K, hw, textures, ppm, planes) for i in range(n_kf)))
    imgs, deps = np.stack(imgs), np.stack(deps)
    per = int(np.ceil(n_points / n_kf))
    hosts, pixs, rhos = [], [], []
    for k in range(n_kf):  # textured pixels away from the border
        gy, gx = np.gradient(imgs[k])
        g = np.hypot(gx, gy)
        g[:6], g[-6:], g[:, :6], g[:, -6:] = 0, 0, 0, 0
        z = deps[k]  # keep away from depth discontinuities (5×5 neighbourhood on one panel)
        flat = cv2.dilate(z, np.ones((5, 5))) - cv2.erode(z, np.ones((5, 5))) < 0.02 * z
        g[~flat] = 0
        cand = np.flatnonzero(g > np.quantile(g, 0.5))
        sel = rng.choice(cand, size=min(per, len(cand)), replace=False)
        vv, uu = np.unravel_index(sel, g.shape)
        hosts.append(np.full(len(sel), k))
        pixs.append(np.stack([uu, vv], 1).astype(float))
        rhos.append(1.0 / deps[k][vv, uu])
    host, pix, rho = np.concatenate(hosts)[:n_points], np.concatenate(pixs)[:n_points], \
        np.concatenate(rhos)[:n_points]
    # targets: nearest keyframes (by index or centre) where the point projects inside, unoccluded
    Kinv = np.linalg.inv(K)
    dmin = np.stack([cv2.erode(z, np.ones((7, 7))) for z in deps])
    Xh = (np.c_[pix, np.ones(len(pix))] @ Kinv.T) / rho[:, None]
    if path == "compact":
        offs = sorted((o for o in range(-n_kf + 1, n_kf) if o), key=lambda o: (abs(o), o))
        rank = np.arange(n_kf)[:, None] + np.array(offs, int)[None]  # may leave [0, n_kf)
    else:
        c = np.stack([-t[:3, :3].T @ t[:3, 3] for t in T])
        # the 2 × max_targets nearest only: a far keyframe seeing the point through another gap
        # between the panels (1.7 m away) is no neighbour a front end would link
        rank = np.argsort(np.linalg.norm(c[:, None] - c[None], axis=2), axis=1,
                          kind="stable")[:, 1:2 * max_targets + 1]
    obs_pts, obs_kfs, count = [], [], np.zeros(len(host), int)
    for j in range(rank.shape[1]):
        tk = rank[host, j]
        ok = (tk >= 0) & (tk < n_kf) & (count < max_targets)
        idx = np.flatnonzero(ok)
        T_th = T[tk[idx]] @ np.linalg.inv(T[host[idx]])
        X = np.einsum("nij,nj->ni", T_th[:, :3, :3], Xh[idx]) + T_th[:, :3, 3]
        uvw = X @ K.T
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        inside = (X[:, 2] > 0.1) & in_image_uv(u, v, W, H, margin=4)
        ui, vi = np.clip(np.round(u).astype(int), 0, W - 1), np.clip(np.round(v).astype(int), 0, H - 1)
        inside &= dmin[tk[idx], vi, ui] > 0.98 * X[:, 2]  # whole patch on the visible surface
        idx = idx[inside]
        obs_pts.append(idx)
        obs_kfs.append(tk[idx])
        count[idx] += 1
    obs_pt, obs_kf = np.concatenate(obs_pts), np.concatenate(obs_kfs)
    prob = PhotoBAProblem(imgs, K, T, np.zeros((n_kf, 2)), host, pix, rho, obs_pt, obs_kf)
    return prob, deps


def _spread(c: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1))))


def perturb(prob: PhotoBAProblem, rng: np.random.Generator, trans: float = 0.015,
            rot_deg: float = 0.5, rho_rel: float = 0.05) -> PhotoBAProblem:
    """Copy of ``prob`` with keyframes ≥ 1 and all inverse depths perturbed; the perturbed camera
    centres are then scaled about ``c_0`` so that the keyframe trajectory keeps its true extent
    (the BA's scale anchor, :func:`mutualslam_cli.backend.ba.lm.extent`): a monocular BA cannot recover scale."""
    T = prob.T_cw.copy()
    c = centres(T)
    new = c.copy()
    rots = T[:, :3, :3].copy()
    for k in range(1, len(T)):
        dc = rng.normal(size=3)
        new[k] = c[k] + dc * trans / np.linalg.norm(dc)
        ax = rng.normal(size=3)
        rots[k] = T[k, :3, :3] @ exp_so3((ax / np.linalg.norm(ax) * np.deg2rad(rot_deg))[None])[0]
    new = c[0] + (new - c[0]) * extent(T) / _spread(new)
    for k in range(1, len(T)):
        T[k, :3, :3], T[k, :3, 3] = rots[k], -rots[k] @ new[k]
    rho = prob.inv_depth * (1 + rho_rel * rng.choice([-1.0, 1.0], size=len(prob.inv_depth)))
    return PhotoBAProblem(prob.images, prob.K, T, prob.affine.copy(), prob.host, prob.pixel, rho,
                          prob.obs_pt, prob.obs_kf, prob.free)


#: the benchmark's problem (keyword arguments of :func:`synthetic_problem`, seed 0)
BENCH_PROBLEM = {"n_kf": 100, "n_points": 10_000, "hw": (480, 640), "path": "loop", "extent": 1.7,
                 "cells": 96}
#: the benchmark's start (keyword arguments of :func:`perturb`, rng seed 1); see the module doc
BENCH_PERTURBATION = {"trans": 0.002, "rot_deg": 0.05, "rho_rel": 0.03}


class ProblemInfo(TypedDict):
    """:func:`problem_info`: counts, the image ``WxH`` and the geometry (cm, px)."""

    keyframes: int
    points: int
    observations: int
    residuals: int
    image: str
    spacing_cm_min: float
    spacing_cm_median: float
    baseline_cm_median: float
    baseline_cm_max: float
    parallax_px_median: float
    parallax_px_p10: float
    targets_per_point: float


class BenchProblem(ProblemInfo):
    """``ba_problem`` of :func:`bench_ba`: the problem, its start's perturbation, the solver's settings."""

    perturbation: dict[str, float]
    iterations: int
    levels: int


class BABench(TypedDict):
    """:func:`bench_ba`'s figures (seconds, costs, counts; see there)."""

    ba_s: float
    ba_s_runs: list[float]
    ba_build_s: float
    ba_problem: BenchProblem
    ba_before: dict[str, float]  # accuracy()'s errors
    ba_after: dict[str, float]
    ba_cost0: float
    ba_cost: float
    ba_cost_truth: float
    ba_iterations: int
    ba_accepted: int


def holds_ba(figures: Mapping[str, object]) -> TypeGuard[BABench]:
    """Whether ``mslam bench suite``'s figures hold :func:`bench_ba`'s."""
    return "ba_before" in figures


def accuracy(truth: PhotoBAProblem, T_cw: np.ndarray, inv_depth: np.ndarray) -> dict[str, float]:
    """Errors of a state ``T_cw`` ``(K, 4, 4)``, ``inv_depth`` ``(P,)`` against ``truth``.

    Returns:
        over keyframes ≥ 1 (0 is the gauge): ``centre_mm_max``/``centre_mm_rms`` (camera
        centres, mm, in the solver's gauge: keyframe 0 fixed, scale from ``‖c_1 − c_0‖``),
        ``rot_deg_max``/``rot_deg_rms`` (angle of ``R_est R_trueᵀ``, degrees); over every
        keyframe after a Sim(3) alignment of the centres (Umeyama): ``scale_pct`` (the
        alignment's ``s − 1``, %, i.e. the map's scale error), ``centre_sim3_mm_max``/
        ``centre_sim3_mm_rms``; over every point ``rho_rel_median``/``rho_rel_p95``
        (``|ρ/ρ_true − 1|``).
    """
    def centres(T: np.ndarray) -> np.ndarray:
        return np.einsum("kji,kj->ki", T[:, :3, :3], -T[:, :3, 3])

    c, ct = centres(T_cw), centres(truth.T_cw)
    e = 1000.0 * np.linalg.norm(c - ct, axis=1)[1:]
    R, t, sc = umeyama(c, ct, with_scale=True)
    es = 1000.0 * np.linalg.norm(sc * c @ R.T + t - ct, axis=1)
    tr = np.einsum("kij,kij->k", T_cw[1:, :3, :3], truth.T_cw[1:, :3, :3])  # trace(R Rtᵀ)
    ang = np.degrees(np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0)))
    rel = np.abs(inv_depth / truth.inv_depth - 1)
    return {"centre_mm_max": float(e.max()), "centre_mm_rms": float(np.sqrt(np.mean(e**2))),
            "rot_deg_max": float(ang.max()), "rot_deg_rms": float(np.sqrt(np.mean(ang**2))),
            "scale_pct": 100.0 * (1.0 / sc - 1.0), "centre_sim3_mm_max": float(es.max()),
            "centre_sim3_mm_rms": float(np.sqrt(np.mean(es**2))),
            "rho_rel_median": float(np.median(rel)), "rho_rel_p95": float(np.quantile(rel, 0.95))}


def problem_info(prob: PhotoBAProblem) -> ProblemInfo:
    """Size and geometry of a problem: keyframes, points, observations, residuals (3×3 patch),
    image ``H×W``, keyframe spacing (cm, min/median), host–target baseline (cm, median/max),
    parallax ``f·baseline·ρ`` (px, median/p10) and the mean number of targets per point."""
    c = np.einsum("kji,kj->ki", prob.T_cw[:, :3, :3], -prob.T_cw[:, :3, 3])
    step = 100.0 * np.linalg.norm(np.diff(c, axis=0), axis=1)
    bl = 100.0 * np.linalg.norm(c[prob.host[prob.obs_pt]] - c[prob.obs_kf], axis=1)
    par = abs(prob.K[0, 0]) * bl / 100.0 * prob.inv_depth[prob.obs_pt]
    H, W = np.asarray(prob.images).shape[1:]
    return {"keyframes": len(prob.T_cw), "points": len(prob.host), "observations": len(prob.obs_pt),
            "residuals": 9 * len(prob.obs_pt), "image": f"{W}x{H}",
            "spacing_cm_min": float(step.min()), "spacing_cm_median": float(np.median(step)),
            "baseline_cm_median": float(np.median(bl)), "baseline_cm_max": float(bl.max()),
            "parallax_px_median": float(np.median(par)), "parallax_px_p10": float(np.quantile(par, 0.1)),
            "targets_per_point": len(prob.obs_pt) / len(prob.host)}


def bench_ba(runs: int = 3, iterations: int = 10, levels: int = 1, coarse_iterations: int = 5,
             problem: dict | None = None, perturbation: dict | None = None,
             log: Callable[[str], None] | None = None) -> BABench:
    """Median wall time of ``runs`` :func:`solve` calls from the perturbed start, and accuracy.

    Args:
        runs: timed solves (same start; the first also warms caches).
        iterations, levels, coarse_iterations: passed to :func:`solve`.
        problem, perturbation: override :data:`BENCH_PROBLEM` / :data:`BENCH_PERTURBATION` keys.
        log: called with one line per run.

    Returns:
        ``ba_s`` (median seconds), ``ba_s_runs``, ``ba_build_s`` (building the problem),
        ``ba_problem`` (:func:`problem_info` plus the perturbation), ``ba_before``/``ba_after``
        (:func:`accuracy` of the start and of the last run's result), ``ba_cost0``, ``ba_cost``,
        ``ba_cost_truth`` (cost at the true state), ``ba_iterations``, ``ba_accepted``.
    """
    t0 = time.perf_counter()
    prob, _ = synthetic_problem(**{**BENCH_PROBLEM, **(problem or {})})
    pert = {**BENCH_PERTURBATION, **(perturbation or {})}
    start = perturb(prob, np.random.default_rng(1), **pert)
    build_s = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        res = solve(start, iterations=iterations, levels=levels, coarse_iterations=coarse_iterations)
        times.append(res.stats["seconds"])
        if log is not None:
            log(f"  {times[-1]:.2f} s, iterations {res.stats['iterations']}, accepted "
                f"{res.stats['accepted']}, cost {res.stats['cost0']:.4g} -> {res.stats['cost']:.4g}")
    st = res.stats
    return {"ba_s": float(np.median(times)), "ba_s_runs": times, "ba_build_s": build_s,
            "ba_problem": {**problem_info(prob), "perturbation": pert, "iterations": iterations,
                           "levels": levels},
            "ba_before": accuracy(prob, start.T_cw, start.inv_depth),
            "ba_after": accuracy(prob, res.T_cw, res.inv_depth),
            "ba_cost0": st["cost0"], "ba_cost": st["cost"],
            "ba_cost_truth": solve(prob, iterations=0).stats["cost0"],
            "ba_iterations": st["iterations"], "ba_accepted": st["accepted"]}


def report(r: BABench) -> str:
    """Markdown table of :func:`bench_ba`'s accuracy, before → after."""
    rows = [("keyframe centre error, max (mm)", "centre_mm_max", 1.0),
            ("keyframe centre error, RMS (mm)", "centre_mm_rms", 1.0),
            ("rotation error, max (deg)", "rot_deg_max", 1.0),
            ("map scale error (%)", "scale_pct", 1.0),
            ("keyframe centre error after Sim(3) alignment, max (mm)", "centre_sim3_mm_max", 1.0),
            ("keyframe centre error after Sim(3) alignment, RMS (mm)", "centre_sim3_mm_rms", 1.0),
            ("inverse depth |ρ/ρ_true − 1|, median (%)", "rho_rel_median", 100.0),
            ("inverse depth |ρ/ρ_true − 1|, p95 (%)", "rho_rel_p95", 100.0)]
    lines = ["| global BA accuracy | before | after |", "|---|---|---|"]
    lines += [f"| {what} | {s * r['ba_before'][k]:.3g} | {s * r['ba_after'][k]:.3g} |" for what, k, s in rows]
    lines.append(f"| cost (true state {r['ba_cost_truth']:.3g}) | {r['ba_cost0']:.4g} | {r['ba_cost']:.4g} |")
    lines.append(f"| accepted / iterations | — | {r['ba_accepted']} / {r['ba_iterations']} |")
    return "\n".join(lines)


def ba_bench(iterations: int = 10, runs: int = 3, levels: int = 1, coarse_iterations: int = 5) -> BABench:
    """:func:`bench_ba` with a line per run, the problem, the median time (s) and :func:`report` printed to
    stdout; returns :func:`bench_ba`'s result. ``levels``: pyramid levels (1: full resolution)."""
    r = bench_ba(runs, iterations, levels, coarse_iterations, log=print)
    p = r["ba_problem"]
    print(f"built {p['keyframes']} keyframes {p['image']}, {p['points']} points, {p['observations']} "
          f"observations in {r['ba_build_s']:.1f} s; spacing {p['spacing_cm_median']:.1f} cm, baseline "
          f"median {p['baseline_cm_median']:.1f} cm, parallax median {p['parallax_px_median']:.1f} px")
    print(f"median {r['ba_s']:.2f} s over {runs} runs (levels {levels}, {iterations} "
          f"full-resolution iterations)\n")
    print(report(r))
    return r

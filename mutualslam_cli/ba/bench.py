"""Synthetic photometric-BA problems and the speed benchmark (DESIGN §10).

``python -m mutualslam_cli.ba.bench`` builds 100 keyframes × 10 000 points (≤ 5 targets, 3×3
patch), perturbs poses and inverse depths, runs 10 LM iterations three times and prints the
median wall time (``--levels L`` adds ``--coarse-iterations`` per coarser pyramid level,
each costing about as much as a full-resolution iteration). The scene is a few textured planes rendered by analytic
ray–plane
intersection, so residuals vanish (up to bilinear interpolation) at the true state.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from mutualslam_cli.ba.photometric import PhotoBAProblem, solve
from mutualslam_cli.geometry import exp_so3

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
           px_per_m: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Render grey image ``(H, W)`` float32 and z-depth ``(H, W)`` of the plane scene."""
    H, W = hw
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    ray_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R_wc = T_cw[:3, :3].T
    c = -R_wc @ T_cw[:3, 3]
    ray = ray_c @ R_wc.T
    best = np.full((H, W), np.inf)
    img = np.zeros((H, W), np.float32)
    for (d, x0, x1, y0, y1), tex in zip(_PLANES, textures):
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


def synthetic_problem(n_kf: int = 6, n_points: int = 600, hw: tuple[int, int] = (120, 160),
                      max_targets: int = 5, fy_sign: float = 1.0, extent: float = 0.4,
                      seed: int = 0):
    """True-state problem on the plane scene.

    The camera centres span about ``extent`` metres along x in front of panels at 2–3 m.

    Returns:
        ``(problem, depths)``: a :class:`PhotoBAProblem` at the true poses/inverse depths with
        zero affine, and the rendered z-depths ``(K, H, W)``.
    """
    rng = np.random.default_rng(seed)
    H, W = hw
    f = 0.9 * W
    K = np.array([[f, 0, W / 2 - 0.5], [0, fy_sign * f, H / 2 - 0.5], [0, 0, 1]])
    textures = [_texture(rng) for _ in _PLANES]
    T = np.stack([_pose(i, n_kf, extent) for i in range(n_kf)])
    imgs, deps = zip(*(render(T[i], K, hw, textures) for i in range(n_kf)))
    imgs, deps = np.stack(imgs), np.stack(deps)
    per = int(np.ceil(n_points / n_kf))
    host, pix, rho = [], [], []
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
        host.append(np.full(len(sel), k))
        pix.append(np.stack([uu, vv], 1).astype(float))
        rho.append(1.0 / deps[k][vv, uu])
    host, pix, rho = np.concatenate(host)[:n_points], np.concatenate(pix)[:n_points], \
        np.concatenate(rho)[:n_points]
    # targets: nearest keyframes (by index) where the point projects inside and is not occluded
    Kinv = np.linalg.inv(K)
    dmin = np.stack([cv2.erode(z, np.ones((7, 7))) for z in deps])
    Xh = (np.c_[pix, np.ones(len(pix))] @ Kinv.T) / rho[:, None]
    obs_pt, obs_kf, count = [], [], np.zeros(len(host), int)
    for off in sorted(range(-n_kf + 1, n_kf), key=lambda o: (abs(o), o)):
        if off == 0:
            continue
        tk = host + off
        ok = (tk >= 0) & (tk < n_kf) & (count < max_targets)
        idx = np.flatnonzero(ok)
        T_th = T[tk[idx]] @ np.linalg.inv(T[host[idx]])
        X = np.einsum("nij,nj->ni", T_th[:, :3, :3], Xh[idx]) + T_th[:, :3, 3]
        uvw = X @ K.T
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        inside = (X[:, 2] > 0.1) & (u > 4) & (u < W - 5) & (v > 4) & (v < H - 5)
        ui, vi = np.clip(np.round(u).astype(int), 0, W - 1), np.clip(np.round(v).astype(int), 0, H - 1)
        inside &= dmin[tk[idx], vi, ui] > 0.98 * X[:, 2]  # whole patch on the visible surface
        idx = idx[inside]
        obs_pt.append(idx)
        obs_kf.append(tk[idx])
        count[idx] += 1
    obs_pt, obs_kf = np.concatenate(obs_pt), np.concatenate(obs_kf)
    prob = PhotoBAProblem(imgs, K, T, np.zeros((n_kf, 2)), host, pix, rho, obs_pt, obs_kf)
    return prob, deps


def perturb(prob: PhotoBAProblem, rng: np.random.Generator, trans: float = 0.015,
            rot_deg: float = 0.5, rho_rel: float = 0.05) -> PhotoBAProblem:
    """Copy of ``prob`` with keyframes ≥ 1 and all inverse depths perturbed; keyframe 1 moves
    only perpendicular to ``c_1 − c_0`` so the scale prior keeps the true baseline."""
    T = prob.T_cw.copy()
    c = np.stack([-t[:3, :3].T @ t[:3, 3] for t in T])
    base = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
    for k in range(1, len(T)):
        dc = rng.normal(size=3)
        if k == 1:
            dc -= dc @ base * base
        dc *= trans / np.linalg.norm(dc)
        if k == 1:  # move on the sphere around c_0: the true baseline is kept exactly
            b = c[1] + dc - c[0]
            dc = c[0] + b * np.linalg.norm(c[1] - c[0]) / np.linalg.norm(b) - c[1]
        ax = rng.normal(size=3)
        Rn = T[k, :3, :3] @ exp_so3((ax / np.linalg.norm(ax) * np.deg2rad(rot_deg))[None])[0]
        T[k, :3, :3], T[k, :3, 3] = Rn, -Rn @ (c[k] + dc)
    rho = prob.inv_depth * (1 + rho_rel * rng.choice([-1.0, 1.0], size=len(prob.inv_depth)))
    return PhotoBAProblem(prob.images, prob.K, T, prob.affine.copy(), prob.host, prob.pixel, rho,
                          prob.obs_pt, prob.obs_kf, prob.free)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=100)
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--height", type=int, default=192)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--levels", type=int, default=1, help="pyramid levels (1: full resolution)")
    ap.add_argument("--coarse-iterations", type=int, default=5)
    a = ap.parse_args()
    t0 = time.perf_counter()
    prob, _ = synthetic_problem(a.keyframes, a.points, (a.height, a.width), seed=0)
    start = perturb(prob, np.random.default_rng(1), trans=0.01, rot_deg=0.3)
    print(f"built {a.keyframes} keyframes {a.width}x{a.height}, {len(prob.host)} points, "
          f"{len(prob.obs_pt)} observations in {time.perf_counter() - t0:.1f} s")
    times = []
    for _ in range(a.runs):
        res = solve(start, iterations=a.iterations, levels=a.levels,
                    coarse_iterations=a.coarse_iterations)
        st = res.stats
        times.append(st["seconds"])
        print(f"  {st['seconds']:.2f} s, iterations {st['iterations']}, accepted {st['accepted']}, "
              f"cost {st['cost0']:.4g} -> {st['cost']:.4g}")
    print(f"median {np.median(times):.2f} s over {a.runs} runs (levels {a.levels}, "
          f"{a.iterations} full-resolution iterations)")


if __name__ == "__main__":
    main()

"""The global BA survives outliers: occluded targets, a patch across a depth edge, gross map points;
and on real data started from GT poses it stays there (ICL: global shutter, exact pinhole)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mutualslam_cli.backend.ba.global_ba import run_global_ba
from mutualslam_cli.backend.ba.photometric import PhotoBAProblem, solve
from mutualslam_cli.backend.refine import ba_images
from mutualslam_cli.bench import ba as bench
from mutualslam_cli.config import BAConfig, RunConfig, VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.metrics.trajectory import ate
from mutualslam_cli.stages.frontend import run_frontend

#: Settings without DSO's outlier handling (the BA before it): Huber at ~25 grey levels, no
#: gradient weight, no block rejected.
NAIVE = {"huber_delta": 0.1, "grad_c": np.inf, "outlier_delta": 1e3}


@pytest.fixture(scope="module")
def small():
    """12 keyframes of the benchmark's loop scene (its resolution and texture, 1200 points)."""
    prob, _ = bench.synthetic_problem(**{**bench.BENCH_PROBLEM, "n_kf": 12, "n_points": 1200, "extent": 0.2})
    return prob


def _project(prob: PhotoBAProblem, m: np.ndarray) -> np.ndarray:
    """Pixels ``(len(m), 2)`` of the blocks ``m`` (point ``obs_pt``, target ``obs_kf``) at the true state."""
    K, p, t = prob.K, prob.obs_pt[m], prob.obs_kf[m]
    ray = np.c_[(prob.pixel[p] - K[:2, 2]) / np.diag(K)[:2], np.ones(len(m))] / prob.inv_depth[p, None]
    T = prob.T_cw[t] @ np.linalg.inv(prob.T_cw[prob.host[p]])
    X = np.einsum("nij,nj->ni", T[:, :3, :3], ray) + T[:, :3, 3]
    return X[:, :2] / X[:, 2:] * np.diag(K)[:2] + K[:2, 2]


def _occlude(prob: PhotoBAProblem, share: float, rng: np.random.Generator) -> tuple[PhotoBAProblem, np.ndarray]:
    """``prob`` with an occluder (a 9×9 square of another texture) pasted over ``share`` of its
    targets in the target image; returns the problem and the occluded blocks."""
    images = prob.images.copy()
    m = rng.choice(len(prob.obs_pt), int(share * len(prob.obs_pt)), replace=False)
    _H, _W = images.shape[1:]
    for (u, v), k in zip(np.rint(_project(prob, m)).astype(int), prob.obs_kf[m]):
        y0, x0 = max(v - 4, 0), max(u - 4, 0)
        patch = images[k, y0:v + 5, x0:u + 5]
        images[k, y0:v + 5, x0:u + 5] = rng.uniform(0.1, 0.9, size=patch.shape)
    return dataclasses.replace(prob, images=images), m


def test_occluded_targets_leave_the_poses_where_they_are(small):
    """2 % of the targets occluded: from the benchmark's start the BA ends < 1 mm from the true
    keyframes, the occluded blocks classified as outliers; without outlier handling it does not."""
    occluded, m = _occlude(small, 0.02, np.random.default_rng(7))
    start = bench.perturb(occluded, np.random.default_rng(1), **bench.BENCH_PERTURBATION)
    res = solve(start, iterations=10)
    acc = bench.accuracy(small, res.T_cw, res.inv_depth)
    assert acc["centre_mm_max"] < 1.0
    assert acc["rot_deg_max"] < 0.02
    assert res.stats["n_outlier_blocks"] >= 0.8 * len(m)
    for r in res.stats["rounds"]:  # the cost never increases over accepted steps
        assert np.all(np.diff(r["costs"]) <= 0)
    naive = solve(start, iterations=10, **NAIVE)
    assert bench.accuracy(small, naive.T_cw, naive.inv_depth)["centre_mm_max"] > 2 * acc["centre_mm_max"]


def test_point_on_a_depth_edge_is_dropped_not_averaged():
    """Points whose 3×3 patch straddles a panel and the wall behind it (the two parts move differently
    between views): mostly dropped, the rest at the front surface, never averaged between the two;
    the other points kept, the poses moved far less than by the BA without outlier handling."""
    prob, deps = bench.synthetic_problem(n_kf=6, n_points=600, hw=(180, 240), seed=0, extent=0.8)
    h = 2
    z = deps[h]
    edge = (np.abs(np.diff(z, axis=1)) > 0.15 * z[:, 1:])  # a depth step between (v, u) and (v, u + 1)
    edge[:8], edge[-8:], edge[:, :8], edge[:, -8:] = False, False, False, False
    vv, uu = np.nonzero(edge)
    pick = np.random.default_rng(0).choice(len(vv), 20, replace=False)
    front = np.minimum(z[vv[pick], uu[pick]], z[vv[pick], uu[pick] + 1])
    uv = np.c_[uu[pick] + np.where(z[vv[pick], uu[pick]] <= z[vv[pick], uu[pick] + 1], 0, 1), vv[pick]]
    P = len(prob.host)
    targets = [k for k in range(6) if k != h]
    new_pt = np.repeat(np.arange(P, P + 20), len(targets))
    prob = dataclasses.replace(prob, host=np.r_[prob.host, np.full(20, h)], pixel=np.r_[prob.pixel, uv.astype(float)],
                               inv_depth=np.r_[prob.inv_depth, 1.0 / front], obs_pt=np.r_[prob.obs_pt, new_pt],
                               obs_kf=np.r_[prob.obs_kf, np.tile(targets, 20)])
    res = solve(prob, iterations=6)
    dropped = res.stats["dropped"]
    assert dropped[P:].mean() >= 0.5
    assert dropped[:P].mean() < 0.02
    # an edge point that stays (six of its nine pixels on the front panel) is at the front surface
    # (within 2 %; the panels here are 2.0/2.4 m in front of a wall at 3.0 m), not in between
    kept = ~dropped[P:]
    assert kept.any()
    assert np.all(np.abs(res.inv_depth[P:][kept] * front[kept] - 1) < 0.02)
    c = lambda T: np.einsum("kji,kj->ki", T[:, :3, :3], -T[:, :3, 3])  # noqa: E731
    moved = np.linalg.norm(c(res.T_cw) - c(prob.T_cw), axis=1).max()
    naive = solve(prob, iterations=6, **NAIVE)
    # this six-keyframe scene is weakly determined (translation against rotation): 20 edge points
    # among 600 still move it (measured 6.9 mm, 0.1 mm without them), the BA without outlier handling 32 mm
    assert moved * 3 < np.linalg.norm(c(naive.T_cw) - c(prob.T_cw), axis=1).max()


@pytest.mark.data
def test_ba_started_from_gt_poses_stays_on_icl(shared_data: Path, tmp_path: Path):
    """ICL-NUIM (global shutter, exact pinhole, GT that fits the tracks to 0.4 px): the pose-oracle
    map (GT keyframe poses, triangulated points) after the global BA is < 1 mm RMS from GT."""
    seq = load_sequence(shared_data / "icl_lr_kt2")
    vo, _ = run_frontend(seq, RunConfig(vo=VOConfig(mode="gt")), cache_dir=tmp_path)
    r = run_global_ba(vo, ba_images(seq, vo), None, None, BAConfig(), cull=False)
    assert r.stats.n_refined > 0.8 * len(vo.points)
    assert r.stats.accepted >= 1
    assert ate(vo.traj_kf, r.vo.traj_kf).rmse < 1e-3

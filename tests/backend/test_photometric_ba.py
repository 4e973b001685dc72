"""Global photometric BA: Jacobians, zero residual, Schur step, convergence, gauge, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mutualslam_cli.backend.ba import lm, pyramid
from mutualslam_cli.backend.ba import photometric as ph
from mutualslam_cli.backend.ba.residuals import DSO_PATTERN
from mutualslam_cli.bench.ba import perturb, synthetic_problem
from mutualslam_cli.errors import ConfigError, ShapeError


@pytest.fixture(scope="module")
def scene():
    prob, _ = synthetic_problem(n_kf=6, n_points=600, hw=(120, 160), seed=0)
    return prob


def _centres(T: np.ndarray) -> np.ndarray:
    return np.stack([-t[:3, :3].T @ t[:3, 3] for t in T])


def test_jacobians_match_central_differences():
    prob, _ = synthetic_problem(n_kf=5, n_points=150, hw=(96, 128), fy_sign=-1.0, seed=3)
    prob = perturb(prob, np.random.default_rng(3))
    prob.affine[:] = np.random.default_rng(2).normal(scale=0.1, size=prob.affine.shape)
    d = ph.PatchData(prob, DSO_PATTERN, 2.0)
    T, ab, rho = prob.T_cw, prob.affine, prob.inv_depth
    res = ph.residuals(d, T, ab, rho, jac=True)
    Jc, Jp = res.d_cameras, res.d_inv_depth
    obs = np.flatnonzero(res.valid.all(1))[:15]
    assert len(obs) == 15
    eps = 1e-6
    for c in range(16):  # host (ρ, φ, a, b) then target (ρ, φ, a, b)
        kfs = d.h if c < 8 else d.t
        for j in obs:
            out = []
            for s in (1, 0, -1):
                dc = np.zeros(len(T) * 8)
                dc[kfs[j] * 8 + c % 8] = s * eps
                T2, ab2, _ = ph.apply_step(T, ab, rho, dc, 0.0, np.array([kfs[j]]))
                out.append(ph.residuals(d, T2, ab2, rho).values[j])
            # the bilinear interpolant is piecewise smooth: where a step crosses a pixel's edge the
            # analytic derivative (of the cell the sample is in) is the one-sided one on that side
            fd = [(out[0] - out[2]) / (2 * eps), (out[0] - out[1]) / eps, (out[1] - out[2]) / eps]
            tol = [1e-4 * np.abs(f) + 1e-6 * np.abs(fd[0]).max() + 1e-9 for f in fd]
            ok = np.any([np.abs(Jc[j, :, c] - f) <= t for f, t in zip(fd, tol)], axis=0)
            assert ok.all(), (c, j, Jc[j, :, c], fd[0])
    h = 1e-6 * rho
    rp = ph.residuals(d, T, ab, rho + h).values
    rm = ph.residuals(d, T, ab, rho - h).values
    num = (rp - rm) / (2 * h[d.p])[:, None]
    np.testing.assert_allclose(Jp[obs], num[obs], rtol=1e-4, atol=1e-6 * np.abs(num[obs]).max())


def test_zero_residual_at_truth(scene):
    d = ph.PatchData(scene, DSO_PATTERN, 2.0)
    res = ph.residuals(d, scene.T_cw, scene.affine, scene.inv_depth)
    r, valid = res.values, res.valid
    assert valid.mean() > 0.99
    # only the bilinear interpolation error of the rendered images remains, but for the few
    # pattern pixels that reach across a depth edge (the pattern spans 5×5 pixels)
    a = np.abs(r[valid])
    assert np.median(a) < 2e-4
    assert np.mean(a < 3e-3) > 0.99


def test_schur_step_equals_dense_solve(scene):
    prob = dataclasses.replace(scene, host=scene.host[:80], pixel=scene.pixel[:80],
                               inv_depth=scene.inv_depth[:80])
    keep = prob.obs_pt < 80
    prob = dataclasses.replace(prob, obs_pt=prob.obs_pt[keep], obs_kf=prob.obs_kf[keep])
    prob = perturb(prob, np.random.default_rng(4))
    d = ph.PatchData(prob, DSO_PATTERN, 2.0)
    T, ab, rho = prob.T_cw, prob.affine, prob.inv_depth
    nk, P = len(T), len(rho)
    ne = ph.normal_equations(d, T, ab, rho, 0.1)
    cols, lam = np.arange(8, nk * 8), 1e-3
    dc, dp = ne.step(lam, cols)
    res = ph.residuals(d, T, ab, rho, jac=True)
    r, valid, Jc, Jp = res.values, res.valid, res.d_cameras, res.d_inv_depth
    M, S = r.shape
    J = np.zeros((M, S, nk * 8 + P))
    for m in range(M):
        J[m, :, d.h[m] * 8:d.h[m] * 8 + 8] += Jc[m, :, :8]
        J[m, :, d.t[m] * 8:d.t[m] * 8 + 8] += Jc[m, :, 8:]
        J[m, :, nk * 8 + d.p[m]] = Jp[m]
    a = np.abs(r)
    w = (np.where(a < 0.1, 1.0, 0.1 / np.maximum(a, 1e-12)) * valid * d.wg[d.p]).ravel()  # IRLS × gradient weight
    J = J.reshape(M * S, -1)
    H, b = J.T @ (J * w[:, None]), J.T @ (w * r.ravel())
    idx = np.r_[cols, nk * 8 + np.arange(P)]
    Hk, nc = H[np.ix_(idx, idx)], len(cols)
    dg = np.diag(Hk).copy()
    Hk[np.diag_indices_from(Hk)] += np.r_[lam * np.maximum(dg[:nc], 1e-6) + 1e-9, lam * dg[nc:] + 1e-12]
    x = -np.linalg.solve(Hk, b[idx])
    np.testing.assert_allclose(dc[cols], x[:nc], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(dp, x[nc:], rtol=1e-6, atol=1e-9)


def _brightened(start):
    images = start.images.copy()
    images[3] = 1.1 * images[3] + 0.02  # brightness change of one keyframe
    return dataclasses.replace(start, images=images)


def test_solve_recovers_poses_depths_affine_and_scale(scene):
    # the brief's full noise: 1.5 cm / 0.5° poses + 5 % inverse depths + affine change; at full
    # resolution only, LM stalls here (near-similarity basin), so go coarse-to-fine
    start = _brightened(perturb(scene, np.random.default_rng(1), trans=0.015, rot_deg=0.5,
                                rho_rel=0.05))
    res = ph.solve(start, iterations=20, levels=2, coarse_iterations=5)
    c_true, c0, c1 = _centres(scene.T_cw), _centres(start.T_cw), _centres(res.T_cw)
    err0 = np.linalg.norm(c0 - c_true, axis=1)[1:]
    err1 = np.linalg.norm(c1 - c_true, axis=1)[1:]
    # 4×, not more: at a start this far off the robust test (DSO's energy threshold) leaves out informative
    # blocks in the first round (without it, outlier_delta=1: 23× here)
    assert err1.mean() * 4 <= err0.mean()
    rot0 = [np.linalg.norm(a[:3, :3].T @ b[:3, :3] - np.eye(3)) for a, b in zip(start.T_cw, scene.T_cw)]
    rot1 = [np.linalg.norm(a[:3, :3].T @ b[:3, :3] - np.eye(3)) for a, b in zip(res.T_cw, scene.T_cw)]
    assert np.mean(rot1) * 5 <= np.mean(rot0)
    e_rho0 = np.abs(start.inv_depth / scene.inv_depth - 1).mean()
    e_rho1 = np.abs(res.inv_depth / scene.inv_depth - 1).mean()
    assert e_rho1 * 2.5 <= e_rho0
    # DSO model: I_3 − b_3 = exp(a_3 − a_h)(I_h − b_h) with a = b = 0 elsewhere
    a3, b3 = res.affine[3]
    grey = np.linspace(0.1, 0.9, 9)
    np.testing.assert_allclose(np.exp(a3) * grey + b3, 1.1 * grey + 0.02, atol=5e-3)
    assert np.abs(np.delete(res.affine, 3, axis=0)).max() < 0.01
    np.testing.assert_array_equal(res.T_cw[0], start.T_cw[0])
    np.testing.assert_array_equal(res.affine[0], start.affine[0])
    lv = res.stats["rounds"]  # the coarse level's round, then the rounds at full resolution
    assert [x["level"] for x in lv] == [1, 0, 0]
    assert lv[0]["shape"] == (60, 80)
    for x in lv:  # cost non-increasing within each round (rounds' active blocks and levels differ)
        assert np.all(np.diff(x["costs"]) <= 0)
        assert x["accepted"] >= 1
    assert lv[-1]["costs"] == res.stats["costs"]
    assert res.stats["cost"] < 0.01 * res.stats["cost0"]
    assert res.stats["iterations"] == sum(x["iterations"] for x in lv)
    assert abs(lm.extent(res.T_cw) / lm.extent(start.T_cw) - 1) < 0.01  # the scale anchor holds


def test_single_level_is_unchanged(scene):
    """levels=1 is the single-resolution solver (it converges on the 3 % scenario; the pre-
    pyramid code gave 13 iterations, cost 29.35 → 0.00132 here), and a pyramid whose coarse
    levels do nothing gives the same bits."""
    start = _brightened(perturb(scene, np.random.default_rng(1), trans=0.015, rot_deg=0.5,
                                rho_rel=0.03))
    res = ph.solve(start, iterations=20)
    st = res.stats
    assert st["accepted"] >= 1
    assert st["cost"] < 1e-3 * st["cost0"]
    assert np.all(np.diff(st["costs"]) <= 0)
    assert [x["level"] for x in st["rounds"]] == [0, 0]
    same = ph.solve(start, iterations=20, levels=2, coarse_iterations=0)
    for a, b in ((res.T_cw, same.T_cw), (res.affine, same.affine), (res.inv_depth, same.inv_depth)):
        np.testing.assert_array_equal(a, b)
    assert same.stats["costs"] == st["costs"]
    assert same.stats["cost0"] == st["cost0"]


def test_pyramid_downsampling_and_intrinsics_agree(scene):
    ramp = 0.01 * np.arange(8.0)[None, None, :] + 0.003 * np.arange(6.0)[None, :, None]
    half = pyramid.downsample(np.broadcast_to(ramp, (1, 6, 8)))
    u, v = np.meshgrid(np.arange(4.0), np.arange(3.0))
    uf, vf = (u + 0.5) * 2 - 0.5, (v + 0.5) * 2 - 0.5  # coarse pixel centre in fine pixels
    np.testing.assert_allclose(half[0], 0.01 * uf + 0.003 * vf, atol=1e-6)
    # the scene at level 1 (images averaged, K and host pixels rescaled) is still consistent
    stack = pyramid.build(scene.images, 3)
    assert [s.shape[1:] for s in stack] == [(120, 160), (60, 80), (30, 40)]
    lp = pyramid.level_problem(scene, stack[1], 1, scene.T_cw, scene.affine, scene.inv_depth)
    med = {}
    for name, K, pix in (("half-pixel", lp.K, lp.pixel),
                         ("c/2", np.diag([0.5, 0.5, 1.0]) @ scene.K, scene.pixel / 2)):
        p2 = dataclasses.replace(lp, K=K, pixel=pix)
        res = ph.residuals(ph.PatchData(p2, DSO_PATTERN, 2.0), p2.T_cw, p2.affine, p2.inv_depth)
        r, valid = res.values, res.valid
        assert valid.mean() > 0.95
        med[name] = np.median(np.abs(r[valid]))  # median: patches over depth edges dominate RMS
    assert med["half-pixel"] < 3e-4  # box-filtered images are not exact renders at half size
    assert med["c/2"] > 1.5 * med["half-pixel"]  # a quarter-pixel shift shows
    with pytest.raises(ConfigError, match="levels"):
        ph.solve(scene, iterations=1, levels=5)


def test_fixed_keyframes_stay_put(scene):
    start = perturb(scene, np.random.default_rng(2))
    free = np.ones(len(scene.T_cw), bool)
    free[[0, 2]] = False
    res = ph.solve(dataclasses.replace(start, free=free), iterations=3)
    np.testing.assert_array_equal(res.T_cw[2], start.T_cw[2])
    assert not np.allclose(res.T_cw[4], start.T_cw[4])


@pytest.mark.parametrize(("change", "err", "match"), [
    (lambda p: dict(pixel=p.pixel[:-1]), ShapeError, "pixel"),
    (lambda p: dict(T_cw=p.T_cw[:-1]), ShapeError, "T_cw"),
    (lambda p: dict(obs_kf=np.r_[p.host[p.obs_pt[:1]], p.obs_kf[1:]]), ConfigError, "equals the host"),
    (lambda p: dict(T_cw=np.where(np.arange(4) == 3, np.nan, p.T_cw)), ConfigError, "NaN"),
    (lambda p: dict(free=np.ones(len(p.T_cw), bool)), ConfigError, "keyframe 0"),
    (lambda p: dict(inv_depth=-p.inv_depth), ConfigError, "inverse depths"),
])
def test_bad_input_raises(scene, change, err, match):
    bad = dataclasses.replace(scene, **change(scene))
    with pytest.raises(err, match=match):
        ph.solve(bad, iterations=1)


def test_too_many_targets_raises(scene):
    with pytest.raises(ConfigError, match="max_targets"):
        ph.solve(scene, iterations=1, max_targets=2)

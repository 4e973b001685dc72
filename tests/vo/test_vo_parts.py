"""Unit tests of the VO building blocks: camera model, detection, KLT, PnP, two-view
initialisation, depth filter and windowed BA (all on synthetic inputs, fast)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mutualslam_cli.geometry import exp_so3, se3_inv, to_normalized, to_pixels
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo import depth_filter as dfl
from mutualslam_cli.vo.camera import distort_points, undistort_points
from mutualslam_cli.vo.features import detect_grid
from mutualslam_cli.vo.initialization import initialize
from mutualslam_cli.vo.local_ba import BAProblem, residuals, solve
from mutualslam_cli.vo.tracking import estimate_pose, klt_track

FR1 = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))


def _pose(rng: np.random.Generator, rot: float, trans: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(rng.normal(0, rot, (1, 3)))[0]
    T[:3, 3] = rng.normal(0, trans, 3)
    return T


def _project(T_cw: np.ndarray, X: np.ndarray) -> np.ndarray:
    pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    return pc[:, :2] / pc[:, 2:3]


def _texture(rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    img = cv2.resize(rng.integers(0, 255, (h // 8, w // 8)).astype(np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (5, 5), 1.0)


def test_distortion_round_trip_fr1(rng):
    pix = np.c_[rng.uniform(40, 600, 200), rng.uniform(40, 440, 200)]
    und = undistort_points(pix, FR1)
    assert np.abs(und - pix).max() > 1.0  # the model really moves points
    np.testing.assert_allclose(distort_points(und, FR1), pix, atol=1e-3)


def test_normalised_coordinates_negative_fy(rng):
    icl = Intrinsics(481.2, -480.0, 319.5, 239.5, 640, 480)
    pix = np.c_[rng.uniform(0, 640, 50), rng.uniform(0, 480, 50)]
    xn = to_normalized(pix, icl.K())
    assert np.all(np.sign(xn[:, 1]) == -np.sign(pix[:, 1] - 239.5))
    np.testing.assert_allclose(to_pixels(xn, icl.K()), pix, atol=1e-9)


def test_grid_detection_one_per_cell_and_occupancy(rng):
    img = _texture(rng)
    pts = detect_grid(img, 20, 500)
    cells = set(zip((pts[:, 1] // 20).astype(int), (pts[:, 0] // 20).astype(int)))
    assert len(cells) == len(pts) > 100
    occupied = pts[:50]
    more = detect_grid(img, 20, 500, occupied_px=occupied)
    occ_cells = set(zip((occupied[:, 1] // 20).astype(int), (occupied[:, 0] // 20).astype(int)))
    new_cells = set(zip((more[:, 1] // 20).astype(int), (more[:, 0] // 20).astype(int)))
    assert not occ_cells & new_cells
    assert len(detect_grid(img, 20, 60, occupied_px=occupied)) == 10
    assert len(detect_grid(np.zeros_like(img), 20, 500)) == 0


def test_klt_tracks_a_shift_and_rejects_textureless(rng):
    img = _texture(rng)
    img[:, 200:] = 128  # flat right part: nothing to track there
    M = np.float32([[1, 0, 3.0], [0, 1, -2.0]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC)
    pts = np.float32([[60, 60], [100, 120], [150, 180], [250, 120], [280, 60]])
    out, ok = klt_track(img, moved, pts, 21, 3, 1.0)
    assert ok[:3].all()
    np.testing.assert_allclose(out[:3] - pts[:3], [[3.0, -2.0]] * 3, atol=0.1)
    assert not ok[3:].any()


def test_klt_guided_pass_recovers_from_a_bad_guess(rng):
    """A guess far outside the guided pass's 1-level capture range costs a retry, not the track."""
    img = _texture(rng)
    M = np.float32([[1, 0, 6.0], [0, 1, 4.0]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC)
    pts = np.float32([[80, 60], [120, 100], [160, 140], [200, 160], [240, 120]])
    good = pts + [6.0, 4.0]
    bad = pts + [6.0 - 30.0, 4.0 + 30.0]  # ~40 px off: beyond the 2-level guided search
    out, ok = klt_track(img, moved, pts, 17, 3, 1.0, pred=good)
    assert ok.all()
    np.testing.assert_allclose(out, good, atol=0.1)
    out_r, ok_r = klt_track(img, moved, pts, 17, 3, 1.0, pred=bad)
    assert ok_r.all()
    np.testing.assert_allclose(out_r, good, atol=0.1)
    _, ok_n = klt_track(img, moved, pts, 17, 3, 1.0, pred=bad, retry=False)
    assert not ok_n.all()  # without the retry the guided pass alone loses (some of) them


def test_pose_from_matches_with_outliers(rng):
    X = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(2, 5, 200)]
    T = _pose(rng, 0.05, 0.2)
    xn = _project(T, X) + rng.normal(0, 0.3 / 500, (200, 2))
    xn[:40] += rng.uniform(-0.1, 0.1, (40, 2))  # 20 % gross outliers
    T_est, inl = estimate_pose(X, xn, [np.eye(4)], 2.0 / 500, seed=0)
    assert T_est is not None
    assert np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < 5e-3
    assert inl[40:].mean() > 0.95
    assert inl[:40].mean() < 0.2


def _two_views(rng, planar: bool):
    n = 300
    if planar:
        X = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), np.full(n, 3.0)]
    else:
        X = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(2.0, 6.0, n)]
    T1 = np.eye(4)
    T1[:3, :3] = exp_so3(np.array([[0.0, 0.03, 0.01]]))[0]
    T1[:3, 3] = [-0.3, 0.05, 0.02]
    noise = 0.3 / 500
    return X, T1, _project(np.eye(4), X) + rng.normal(0, noise, (n, 2)), _project(T1, X) + rng.normal(0, noise, (n, 2))


@pytest.mark.parametrize("planar", [True, False])
def test_two_view_initialisation(rng, planar):
    X, T1, x0, x1 = _two_views(rng, planar)
    res = initialize(x0, x1, 2.0 / 500, seed=0)
    assert res is not None
    assert res.method == ("homography" if planar else "essential")
    assert np.median(res.points0[:, 2]) == pytest.approx(1.0)  # map scaled to median depth 1
    s = np.median(X[res.index, 2])
    rel = np.linalg.norm(res.points0 * s - X[res.index], axis=1) / X[res.index, 2]
    assert np.median(rel) < 0.02
    assert np.max(rel) < 0.1
    np.testing.assert_allclose(res.T_10[:3, 3] * s, T1[:3, 3], atol=0.02)


def test_depth_filter_converges_and_flags_outliers(rng):
    n = 50
    f_h = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), np.ones(n)]
    f_h /= np.linalg.norm(f_h, axis=1, keepdims=True)
    dist = rng.uniform(1.0, 3.0, n)
    s = dfl.new_seeds(n, dfl.SeedInit(2.0, 0.5))
    for i in range(1, 30):
        T_wc = np.eye(4)
        T_wc[:3, 3] = [0.01 * i, 0.002 * i, 0.0]
        Xc = f_h * dist[:, None] - T_wc[:3, 3]
        f_c = Xc / np.linalg.norm(Xc, axis=1, keepdims=True)
        f_c[:, :2] += rng.normal(0, 0.3 / 500, (n, 2))
        if i % 3 == 0:  # every third frame, seeds 0-9 get an outlier measurement
            f_c[:10, :2] += rng.uniform(0.02, 0.05, (10, 2))
        x, tau2, ok = dfl.measure(f_h, f_c / np.linalg.norm(f_c, axis=1, keepdims=True),
                                  np.repeat(T_wc[None], n, 0), 2 * np.arctan(0.5 / 500))
        dfl.update_seeds(s, np.flatnonzero(ok), x[ok], tau2[ok])
    conv = dfl.converged(s)
    assert conv[10:].mean() > 0.9
    np.testing.assert_allclose(1.0 / s["mu"][10:], dist[10:], rtol=0.02)
    ratio = s["a"] / (s["a"] + s["b"])
    assert ratio[:10].mean() < ratio[10:].mean()


def test_windowed_ba_reduces_error(rng):
    K, P = 5, 300
    T = np.stack([np.eye(4)] * K)
    for k in range(K):
        T[k, :3, 3] = [-0.1 * k, 0.02 * k, 0.0]
    X = np.c_[rng.uniform(-1, 1, (P, 2)), rng.uniform(2, 4, P)]
    host = rng.integers(0, K, P)
    ray = np.c_[np.array([_project(T[host[p]], X[p:p + 1])[0] for p in range(P)]), np.ones(P)]
    rho = np.array([1.0 / (X[p] @ T[host[p], :3, :3].T + T[host[p], :3, 3])[2] for p in range(P)])
    obs = [(p, k) for p in range(P) for k in range(K) if k != host[p]]
    o_pt = np.array([o[0] for o in obs])
    o_kf = np.array([o[1] for o in obs])
    o_xn = np.stack([_project(T[k], X[p:p + 1])[0] for p, k in obs]) + rng.normal(0, 0.3 / 500, (len(obs), 2))
    T0 = T.copy()
    for k in range(2, K):  # kf 0 and 1 fixed: gauge and scale
        T0[k] = _pose(rng, 0.01, 0.02) @ T0[k]
    prob = BAProblem(T0, np.arange(K) >= 2, host, ray, rho * (1 + rng.normal(0, 0.05, P)), o_pt, o_kf, o_xn)
    T_new, rho_new, st = solve(prob, 2.0 / 500, iters=10)
    assert st["cost"] < 0.1 * st["cost0"]
    err0 = max(np.linalg.norm(se3_inv(T0[k])[:3, 3] - se3_inv(T[k])[:3, 3]) for k in range(K))
    err1 = max(np.linalg.norm(se3_inv(T_new[k])[:3, 3] - se3_inv(T[k])[:3, 3]) for k in range(K))
    assert err1 < 0.2 * err0
    np.testing.assert_allclose(T_new[:2], T0[:2])  # fixed poses untouched
    assert np.median(np.abs(rho_new / rho - 1)) < 0.01


def test_ba_jacobians_match_finite_differences(rng):
    """Analytic target/host/inverse-depth Jacobians against central differences."""
    K, P = 3, 20
    T = np.stack([_pose(rng, 0.05, 0.1) for _ in range(K)])
    host = rng.integers(0, K, P)
    ray = np.c_[rng.uniform(-0.4, 0.4, (P, 2)), np.ones(P)]
    rho = rng.uniform(0.3, 0.6, P)
    o_pt = np.arange(P)
    o_kf = (host + 1 + rng.integers(0, K - 1, P)) % K  # never the host
    prob = BAProblem(T, np.ones(K, bool), host, ray, rho, o_pt, o_kf, rng.normal(0, 0.1, (P, 2)))
    _, J_t, J_h, J_p, front = residuals(prob, T, rho, jac=True)
    assert front.all()
    eps = 1e-6

    def moved(k: int, d: np.ndarray) -> np.ndarray:
        T2 = T.copy()
        inc = np.eye(4)
        inc[:3, :3] = exp_so3(d[None, 3:])[0]
        inc[:3, 3] = d[:3]
        T2[k] = inc @ T[k]
        return T2

    for m in range(P):
        for j in range(6):
            d = np.zeros(6)
            d[j] = eps
            for k, J in ((o_kf[m], J_t), (host[m], J_h)):
                num = (residuals(prob, moved(k, d), rho)[0][m] - residuals(prob, moved(k, -d), rho)[0][m]) / (2 * eps)
                np.testing.assert_allclose(J[m, :, j], num, atol=1e-6)
        dr = np.zeros(P)
        dr[m] = eps
        num = (residuals(prob, T, rho + dr)[0][m] - residuals(prob, T, rho - dr)[0][m]) / (2 * eps)
        np.testing.assert_allclose(J_p[m], num, atol=1e-6)


@pytest.mark.parametrize(("baseline", "expect_wait"), [(0.04, True), (0.5, False)])
def test_init_waits_while_a_low_parallax_motion_fits_as_well(rng, baseline, expect_wait):
    """Forward motion: with a short baseline the true motion has < 1° parallax, so a rival
    (any hypothesis fitting as well) cannot be ruled out and initialisation must wait."""
    from mutualslam_cli.vo.initialization import _check, _rival_too_short

    n = 300
    X = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(2.0, 6.0, n)]
    T = np.eye(4)
    T[:3, 3] = [0.02 * baseline, 0.0, -baseline]  # mostly along the optical axis
    x0 = X[:, :2] / X[:, 2:3] + rng.normal(0, 0.3 / 500, (n, 2))
    x1 = _project(T, X) + rng.normal(0, 0.3 / 500, (n, 2))
    T_unit = T.copy()
    T_unit[:3, 3] /= np.linalg.norm(T[:3, 3])
    _, _, par, _ = _check(x0, x1, T_unit, 2.0 / 500)
    assert (par < 1.0) == expect_wait  # the premise: short baseline ⇔ parallax below 1°
    assert _rival_too_short(x0, x1, 2.0 / 500, T_unit, [T_unit], 30) == expect_wait


def test_undistorter_depth_lands_in_the_pinhole_geometry():
    """Raw (distorted) depth of a smooth surface, resampled, equals the surface in pinhole pixels."""
    import cv2

    from mutualslam_cli.types import Intrinsics
    from mutualslam_cli.vo.camera import Undistorter, undistort_points

    intr = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))

    def surface(pix):  # depth (m) as a smooth function of the *pinhole* pixel
        return 1.0 + 0.002 * pix[:, 0] + 0.001 * pix[:, 1]

    vv, uu = np.mgrid[0:480, 0:640]
    raw_pix = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
    raw = surface(undistort_points(raw_pix, intr)).reshape(480, 640).astype(np.float32)
    und = Undistorter(intr)
    out = und.depth(raw)
    pin = surface(raw_pix).reshape(480, 640)
    inner = (slice(60, 420), slice(80, 560))
    assert np.all(out[inner] > 0)
    # nearest raw pixel: off by at most ~1 px of the surface's slope (0.002 m/px) — never a raw-geometry value
    assert np.max(np.abs(out[inner] - pin[inner])) < 0.004
    assert np.max(np.abs(raw[inner] - pin[inner])) > 0.015  # the raw image is ~8 px away in the same region
    rgb = (np.random.default_rng(0).random((480, 640, 3)) * 255).astype(np.uint8)
    np.testing.assert_array_equal(und.image(rgb), cv2.undistort(rgb, intr.K(), np.array(intr.dist)))
    plain = Undistorter(Intrinsics(500, 500, 320, 240, 640, 480, None))
    assert plain.depth(raw) is raw
    assert plain.image(rgb) is rgb

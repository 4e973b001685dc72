"""Closed-form checks of metrics.depth (STYLE §4): PCD under scalings, e_si, edges."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.metrics.depth import (
    PCD_THRESHOLD,
    DepthStats,
    abs_rel,
    align_inverse_depth,
    depth_frame_metrics,
    depth_stats,
    esi,
    percent_correct,
    pooled_mean,
    resize_to,
    running_mean,
    scale_factor,
    sequence_lsq_scale,
    valid_mask,
)
from mutualslam_cli.metrics.ratios import pcd_from_sketch


@pytest.fixture
def gt() -> np.ndarray:
    """(24, 32) GT depth in [0.5, 8] m with some missing (0) and too-far (> 10 m) pixels."""
    rng = np.random.default_rng(0)
    g = rng.uniform(0.5, 8.0, size=(24, 32))
    g[0, :5] = 0.0
    g[1, :3] = 12.0
    return g


def test_valid_mask_edges(gt: np.ndarray) -> None:
    g = gt.copy()
    g[2, 0], g[2, 1], g[2, 2] = np.nan, np.inf, -1.0
    g[2, 3] = 10.0  # exactly max_depth is kept
    pred = np.ones_like(g)
    pred[3, 0], pred[3, 1], pred[3, 2] = 0.0, np.nan, -2.0
    m = valid_mask(g, 10.0, pred)
    assert m.dtype == bool
    assert m.shape == g.shape
    assert not m[0, :5].any()
    assert not m[1, :3].any()
    assert not m[2, :3].any()
    assert not m[3, :3].any()
    assert m[2, 3]
    assert m.sum() == g.size - 5 - 3 - 3 - 3
    assert valid_mask(g, 10.0)[3, :3].all()  # without pred only GT matters


def test_pcd_without_scaling_closed_form(gt: np.ndarray) -> None:
    assert percent_correct(1.05 * gt, gt, "none") == 100.0
    assert percent_correct(1.2 * gt, gt, "none") == 0.0
    assert percent_correct(0.85 * gt, gt, "none") == 0.0  # |0.85−1| = 0.15 ≥ 0.1


@pytest.mark.parametrize("scaling", ["median", "lsq"])
@pytest.mark.parametrize("k", [1.2, 0.3, 7.0])
def test_pcd_with_scaling_removes_global_scale(gt: np.ndarray, scaling: str, k: float) -> None:
    assert percent_correct(k * gt, gt, scaling) == 100.0  # type: ignore[arg-type]


def test_pcd_counts_the_right_share(gt: np.ndarray) -> None:
    pred = gt.copy()
    m = valid_mask(gt, 10.0)
    idx = np.flatnonzero(m)[:100]  # make exactly 100 valid pixels 50 % off
    pred.flat[idx] *= 1.5
    expected = 100.0 * (m.sum() - 100) / m.sum()
    assert percent_correct(pred, gt, "none") == pytest.approx(expected)
    # the threshold is configurable and strict: an error of exactly 0.125 (binary-exact) is wrong
    assert percent_correct(pred, gt, "none", threshold=0.6) == 100.0
    two = np.full((4, 4), 2.0)
    assert percent_correct(1.125 * two, two, "none", threshold=0.125) == 0.0
    assert percent_correct(1.125 * two, two, "none", threshold=0.126) == 100.0


def test_lsq_scale_equals_analytic(gt: np.ndarray) -> None:
    rng = np.random.default_rng(1)
    pred = gt * rng.uniform(0.5, 1.5, size=gt.shape)
    m = valid_mask(gt, 10.0, pred)
    s = scale_factor(pred, gt, m, "lsq")
    p, g = pred[m], gt[m]
    s_np = np.linalg.lstsq(p[:, None], g, rcond=None)[0][0]
    assert s == pytest.approx(s_np, rel=1e-12)
    # it is the minimiser: nearby scales do worse
    cost = lambda x: np.sum((x * p - g) ** 2)  # noqa: E731
    assert cost(s) < cost(s * 1.001)
    assert cost(s) < cost(s * 0.999)
    assert scale_factor(pred, gt, m, "median") == pytest.approx(np.median(g) / np.median(p))
    assert scale_factor(pred, gt, m, "none") == 1.0


def test_unknown_scaling_lists_valid_ones(gt: np.ndarray) -> None:
    with pytest.raises(ConfigError, match="lsq, median, none"):
        percent_correct(gt, gt, "mean")  # type: ignore[arg-type]


def test_empty_mask_gives_nan_not_zero(gt: np.ndarray) -> None:
    far = np.full_like(gt, 50.0)
    assert np.isnan(percent_correct(far, far, "none"))
    assert np.isnan(percent_correct(far, far, "median"))
    empty = np.zeros(gt.shape, dtype=bool)
    assert np.isnan(scale_factor(gt, gt, empty, "lsq"))
    assert np.isnan(esi(gt, gt, empty))
    assert np.isnan(esi(np.zeros(5), np.zeros(5)))
    assert np.isnan(abs_rel(gt, gt, empty))
    row = depth_frame_metrics(far, far)
    assert row["n_valid"] == 0
    assert row["sum_pg"] == row["sum_pp"] == 0.0
    assert all(np.isnan(v) for k, v in row.items() if k not in ("n_valid", "sum_pg", "sum_pp"))


@pytest.mark.parametrize("k", [1.0, 0.01, 0.37, 2.0, 1e3])
def test_esi_zero_for_scaled_prediction(gt: np.ndarray, k: float) -> None:
    assert esi(k * gt, gt) < 1e-12
    pts = np.random.default_rng(2).uniform(0.1, 20.0, size=500)  # 1-D map points
    assert esi(k * pts, pts) < 1e-12


def test_esi_closed_form() -> None:
    # d = log(p/g) takes ±a with equal counts: mean 0, e_si = a
    g = np.ones(10)
    a = 0.3
    p = np.exp(np.r_[np.full(5, a), np.full(5, -a)])
    assert esi(p, g) == pytest.approx(a, rel=1e-12)
    assert esi(3.0 * p, g) == pytest.approx(a, rel=1e-12)
    # equals the paper's formula sqrt(1/N Σd² − 1/N² (Σd)²) on random data
    rng = np.random.default_rng(3)
    g, p = rng.uniform(0.5, 5, 200), rng.uniform(0.5, 5, 200)
    d = np.log(p) - np.log(g)
    assert esi(p, g) == pytest.approx(np.sqrt(np.mean(d**2) - np.mean(d) ** 2), rel=1e-9)
    # inverse depth gives the same value (d changes sign only)
    assert esi(1 / p, 1 / g) == pytest.approx(esi(p, g), rel=1e-12)


def test_esi_mask_and_shape_checks(gt: np.ndarray) -> None:
    pred = gt.copy()
    pred[5:, :] *= 2.0
    mask = np.zeros(gt.shape, dtype=bool)
    mask[:5] = True
    assert esi(pred, gt, mask) < 1e-12
    assert esi(pred, gt) > 0.1
    with pytest.raises(ShapeError):
        esi(pred[:3], gt)
    with pytest.raises(ShapeError):
        esi(pred, gt, mask[:3])


def test_resize_to_gt_resolution() -> None:
    small = np.arange(12, dtype=np.float32).reshape(3, 4) + 1.0
    big = resize_to(small, (6, 8))
    assert big.shape == (6, 8)
    assert big.dtype == np.float64
    # bilinear with pixel centres: a constant-gradient map stays a gradient, means agree
    assert big.mean() == pytest.approx(small.mean(), rel=1e-6)
    assert big[0, 0] == pytest.approx(1.0)
    assert big[-1, -1] == pytest.approx(12.0)
    np.testing.assert_array_equal(resize_to(small, (3, 4)), small)


def test_pcd_with_prediction_at_other_resolution() -> None:
    gt = np.full((48, 64), 2.0)
    gt[:, 32:] = 4.0
    pred = np.full((24, 32), 1.0)
    pred[:, 16:] = 2.0  # half of GT everywhere, at half resolution
    # bilinear blending at the step makes a 2-column band wrong; everything else is exact
    assert percent_correct(pred, gt, "none") == 0.0
    pcd = percent_correct(pred, gt, "median")
    assert 90.0 <= pcd < 100.0
    assert percent_correct(pred, gt, "median") == percent_correct(resize_to(pred, gt.shape), gt, "median")


def test_accepts_torch_tensors(gt: np.ndarray) -> None:
    pred_t = torch.from_numpy(1.2 * gt).float()[None, None]  # (1, 1, H, W) network output
    gt_t = torch.from_numpy(gt)
    assert percent_correct(pred_t, gt_t, "median") == 100.0
    assert esi(pred_t[0, 0], gt_t) < 1e-6  # float32 input


def test_depth_frame_metrics_row(gt: np.ndarray) -> None:
    row = depth_frame_metrics(1.2 * gt, gt, max_depth=10.0, threshold=0.1)
    assert set(row) == set(DepthStats.__dataclass_fields__) - {"sketch"}
    assert row["pcd_none"] == 0.0
    assert row["pcd_median"] == 100.0
    assert row["pcd_lsq"] == 100.0
    assert row["scale_median"] == pytest.approx(1 / 1.2)
    assert row["scale_lsq"] == pytest.approx(1 / 1.2)
    assert row["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert row["esi"] < 1e-12
    assert row["n_valid"] == valid_mask(gt, 10.0).sum()
    row2 = depth_frame_metrics(1.3 * gt, gt, max_depth=5.0)
    assert row2["n_valid"] == valid_mask(gt, 5.0).sum() < row["n_valid"]


def test_running_mean_ignores_nan() -> None:
    v = np.array([np.nan, 10.0, np.nan, 20.0, 60.0])
    r = running_mean(v)
    assert np.isnan(r[0])
    np.testing.assert_allclose(r[1:], [10.0, 10.0, 15.0, 30.0])
    assert np.isnan(running_mean([np.nan, np.nan])).all()
    assert running_mean([]).shape == (0,)


# ---- depth_stats with an error that is NOT one global scale (lsq and median scales differ) --------


def _ref_stats(pred: np.ndarray, gt: np.ndarray, max_depth: float = 10.0, thr: float = 0.1) -> dict[str, float]:
    """Independent numpy reference from the module docstring / DESIGN §7 definitions."""
    with np.errstate(invalid="ignore"):
        m = np.isfinite(gt) & (gt > 0) & (gt <= max_depth) & np.isfinite(pred) & (pred > 0)
    p, g = pred[m], gt[m]
    s_lsq = float(np.linalg.lstsq(p[:, None], g, rcond=None)[0][0])  # argmin_s Σ(s·p − g)²
    s_med = float(np.median(g) / np.median(p))
    rel = lambda s: np.abs(s * p - g) / g  # noqa: E731
    d = np.log(p) - np.log(g)
    return {
        "pcd_lsq": 100.0 * np.mean(rel(s_lsq) < thr),
        "pcd_median": 100.0 * np.mean(rel(s_med) < thr),
        "pcd_none": 100.0 * np.mean(rel(1.0) < thr),
        "esi": float(np.sqrt(np.mean(d ** 2) - np.mean(d) ** 2)),  # paper Eq. 13
        "abs_rel": float(np.mean(rel(s_med))),  # after median scaling
        "scale_lsq": s_lsq,
        "scale_median": s_med,
        "n_valid": int(m.sum()),
        "_margin": float(min(np.abs(rel(s) - thr).min() for s in (s_lsq, s_med, 1.0))),
    }


def _assert_row(row: dict, ref: dict) -> None:
    assert set(row) == set(DepthStats.__dataclass_fields__) - {"sketch"}
    assert row["n_valid"] == ref["n_valid"]
    for k in ("scale_lsq", "scale_median", "esi", "abs_rel"):
        assert row[k] == pytest.approx(ref[k], rel=1e-9), k
    for k in ("pcd_lsq", "pcd_median", "pcd_none"):
        assert row[k] == pytest.approx(ref[k], abs=1e-9), k


def test_depth_stats_two_region_error_hand_computed() -> None:
    # left half: pred = gt = 2 (ratio 1); right half: gt = 4, pred = 6 (ratio 1.5); 30 valid pixels each
    gt = np.full((8, 8), 2.0)
    gt[:, 4:] = 4.0
    pred = np.where(gt == 2.0, 2.0, 6.0)
    gt[0, 0], gt[0, 7] = 0.0, 12.0  # missing / beyond max_depth (one per half)
    pred[1, 0], pred[1, 7] = np.nan, -1.0  # invalid predictions (one per half)
    st = depth_frame_metrics(pred, gt)
    # s_lsq = Σpg/Σp² = (2·2 + 6·4)/(2² + 6²) = 0.7; s_med = median(g)/median(p) = 3/4 (even count)
    assert st["n_valid"] == 60
    assert st["scale_lsq"] == pytest.approx(0.7, rel=1e-12)
    assert st["scale_median"] == pytest.approx(0.75, rel=1e-12)
    assert st["pcd_lsq"] == 50.0  # 0.7·1 = 0.7 (30 % off), 0.7·1.5 = 1.05 (5 % off: correct)
    assert st["pcd_median"] == 0.0  # 0.75 (25 % off), 0.75·1.5 = 1.125 (12.5 % off)
    assert st["pcd_none"] == 50.0  # ratio 1 correct, 1.5 not
    assert st["abs_rel"] == pytest.approx((0.25 + 0.125) / 2, rel=1e-12)
    assert st["esi"] == pytest.approx(np.log(1.5) / 2, rel=1e-12)  # d ∈ {0, log 1.5}, equal counts
    _assert_row(st, _ref_stats(pred, gt))


def _ramp_gt(h: int = 24, w: int = 32) -> np.ndarray:
    """GT depth ramping 0.5 → 9.5 m over the image, with missing and too-far pixels."""
    v, u = np.mgrid[0:h, 0:w]
    g = 0.5 + 9.0 * (v * w + u) / (h * w - 1)
    g[0, :5] = 0.0
    g[1, :3] = 12.0
    return g


def test_depth_stats_depth_dependent_error_matches_reference() -> None:
    gt = _ramp_gt()
    pred = gt * (0.8 + 0.1 * gt)  # relative error grows with depth: no single scale fits
    pred[2, :2] = [np.nan, -1.0]
    ref = _ref_stats(pred, gt)
    assert ref["_margin"] > 1e-6  # no pixel sits on the PCD threshold (robust to rounding)
    # the case tells the scales, the three PCD columns and std/mean/rms of d apart (else a swap hides)
    assert abs(ref["scale_lsq"] - ref["scale_median"]) > 0.05
    assert len({round(ref[k], 6) for k in ("pcd_lsq", "pcd_median", "pcd_none")}) == 3
    m = valid_mask(gt, 10.0, pred)
    d = np.log(pred[m] / gt[m])
    assert abs(ref["esi"] - abs(d.mean())) > 0.01
    assert abs(ref["esi"] - np.sqrt(np.mean(d ** 2))) > 0.01
    row = depth_frame_metrics(pred, gt)
    _assert_row(row, ref)
    # depth_stats (the dataclass) and the dict row the pipeline writes are the same numbers
    assert {k: v for k, v in depth_stats(pred, gt).__dict__.items() if k != "sketch"} == row
    # the per-metric functions agree with the row
    assert percent_correct(pred, gt, "lsq") == pytest.approx(row["pcd_lsq"], abs=1e-9)
    assert percent_correct(pred, gt, "median") == pytest.approx(row["pcd_median"], abs=1e-9)
    assert esi(pred, gt, m) == pytest.approx(row["esi"], rel=1e-9)
    assert abs_rel(pred, gt, m, row["scale_median"]) == pytest.approx(row["abs_rel"], rel=1e-9)
    # max_depth and threshold are honoured
    _assert_row(depth_frame_metrics(pred, gt, max_depth=6.0, threshold=0.2), _ref_stats(pred, gt, 6.0, 0.2))


def test_depth_frame_metrics_resizes_prediction_to_gt_first() -> None:
    import cv2

    gt = _ramp_gt(24, 32)
    v, u = np.mgrid[0:12, 0:16].astype(np.float64)
    small = 0.4 + 0.02 * (u + 16 * v) * (1.0 + 0.01 * u)  # (12, 16) network-resolution prediction
    small *= 1.0 + 0.3 * (u >= 8)  # with a step, so the interpolation (bilinear) matters
    small_t = torch.from_numpy(small).float()[None, None]  # as the network returns it
    up = cv2.resize(small_t[0, 0].numpy().astype(np.float64), (32, 24), interpolation=cv2.INTER_LINEAR)
    ref = _ref_stats(up, gt)
    assert ref["_margin"] > 1e-6
    assert abs(ref["scale_lsq"] - ref["scale_median"]) > 0.05
    nearest = _ref_stats(cv2.resize(small, (32, 24), interpolation=cv2.INTER_NEAREST), gt)
    assert abs(nearest["pcd_median"] - ref["pcd_median"]) > 1.0  # the case tells the interpolations apart
    assert len({round(ref[k], 6) for k in ("pcd_lsq", "pcd_median", "pcd_none")}) == 3
    _assert_row(depth_frame_metrics(small_t, gt), ref)
    _assert_row(depth_frame_metrics(small, gt), _ref_stats(
        cv2.resize(small, (32, 24), interpolation=cv2.INTER_LINEAR), gt))


# ----------------------------------------------------------------------------- scale-and-shift alignment


@pytest.mark.parametrize(("s_true", "t_true"), [(0.3, 0.05), (2.0, -0.1), (-1.5, 3.0)])
def test_align_inverse_depth_recovers_an_affine_map_of_inverse_depth(gt: np.ndarray, s_true: float,
                                                                     t_true: float) -> None:
    """x = s·(1/D*) + t on every pixel → the fit inverts it exactly: D = D*, scale 1/s, shift −t/s."""
    with np.errstate(divide="ignore"):
        x = np.where(gt > 0, s_true / gt + t_true, 7.0)  # missing GT: any finite value
    depth, s, t = align_inverse_depth(x, gt)
    m = valid_mask(gt, 10.0)
    np.testing.assert_allclose(depth[m], gt[m], rtol=1e-9)
    assert s == pytest.approx(1.0 / s_true, rel=1e-9)
    assert t == pytest.approx(-t_true / s_true, rel=1e-9, abs=1e-12)
    assert percent_correct(depth, gt, "none") == 100.0


def test_align_inverse_depth_fits_in_inverse_depth_not_in_depth() -> None:
    """A fit in depth (s·x + t ≈ D*) gives another answer: hand-computed on four pixels."""
    gt = np.array([[1.0, 2.0], [4.0, 5.0]])
    x = np.array([[1.0, 0.0], [0.0, 1.0]])  # y = 1/D* = [1, .5, .25, .2]
    # centred normal equations: x̄ = .5, ȳ = .4875, Σ(x−x̄)² = 1, Σ(x−x̄)(y−ȳ) = .5·(1 + .2 − .5 − .25) = .225
    depth, s, t = align_inverse_depth(x, gt)
    assert s == pytest.approx(0.225)
    assert t == pytest.approx(0.4875 - 0.225 * 0.5)
    np.testing.assert_allclose(depth, 1.0 / (0.225 * x + 0.375))


def test_align_inverse_depth_caps_depth_and_ignores_pixels_beyond_max_depth(gt: np.ndarray) -> None:
    with np.errstate(divide="ignore"):
        x = np.where(gt > 0, 1.0 / gt, 0.0)
    x[1, :3] = 50.0  # GT 12 m > max_depth: not fitted, so these wild values must not move s, t
    x[5, 5] = -3.0  # aligned inverse depth below 1/max_depth: capped at max_depth (MiDaS's depth cap)
    x[6, 6] = np.nan
    gt2 = gt.copy()
    gt2[5, 5] = 0.0
    depth, s, t = align_inverse_depth(x, gt2, max_depth=10.0)
    assert s == pytest.approx(1.0, rel=1e-9)
    assert t == pytest.approx(0.0, abs=1e-9)
    assert depth[5, 5] == pytest.approx(10.0)
    assert np.isnan(depth[6, 6])
    assert depth[1, 0] == pytest.approx(1.0 / 50.0)


def test_align_inverse_depth_degenerate_is_nan_not_zero(gt: np.ndarray) -> None:
    # 0.3 on these 760 pixels: the mean is off by rounding, so Σ(x−x̄)² ≈ 2e-30, not 0
    one_pixel = np.where(np.arange(gt.size).reshape(gt.shape) == 40, 1.0, np.nan)
    for x in (np.full_like(gt, 0.7), np.full_like(gt, 0.3), one_pixel):
        depth, s, t = align_inverse_depth(x, gt)
        assert np.isnan(s)
        assert np.isnan(t)
        assert np.isnan(depth).all()


# ---- sequence-level least squares from per-frame sketches, pooled means ------------------------------


def _exact_pcd(p: np.ndarray, g: np.ndarray, s: float, thr: float = 0.1) -> float:
    return 100.0 * float(np.mean(np.abs(s * p - g) / g < thr))


def test_sequence_scale_and_sketch_match_the_exact_pooled_fit() -> None:
    """Three frames with different scale errors: one lsq scale over all their pixels (computed here
    on the concatenation), and each frame's PCD under it, read off its sketch within 0.1 points."""
    rng = np.random.default_rng(4)
    frames = []
    for f in (0.8, 1.0, 1.3):
        g = rng.uniform(0.5, 6.0, size=(60, 80))
        p = f * g * np.exp(rng.normal(0.0, 0.08, size=g.shape))
        frames.append((p, g))
    stats = [depth_stats(p, g, sketch=True) for p, g in frames]
    s = sequence_lsq_scale([st.sum_pg for st in stats], [st.sum_pp for st in stats])
    P = np.concatenate([p.ravel() for p, _ in frames])
    G = np.concatenate([g.ravel() for _, g in frames])
    assert s == pytest.approx(float(np.dot(P, G) / np.dot(P, P)), rel=1e-12)
    for st, (p, g) in zip(stats, frames):
        exact = _exact_pcd(p.ravel(), g.ravel(), s)
        assert pcd_from_sketch(st.sketch, s, PCD_THRESHOLD) == pytest.approx(exact, abs=0.1)
        assert pcd_from_sketch(st.sketch, st.scale_lsq, PCD_THRESHOLD) == pytest.approx(st.pcd_lsq, abs=0.1)
    # frames at 0.8 and 1.3 are far from one common scale: their seq_lsq PCD drops, per-frame lsq does not
    assert pcd_from_sketch(stats[2].sketch, s, PCD_THRESHOLD) < stats[2].pcd_lsq - 20
    assert np.isnan(pcd_from_sketch(None, s, PCD_THRESHOLD))
    assert np.isnan(sequence_lsq_scale([np.nan], [np.nan]))
    assert depth_stats(frames[0][0], frames[0][1]).sketch is None


def test_pooled_mean_weights_frames_by_pixels() -> None:
    assert pooled_mean([100.0, 0.0], [3, 1]) == pytest.approx(75.0)
    assert pooled_mean([100.0, np.nan, 0.0], [3, 5, 1]) == pytest.approx(75.0)
    assert np.isnan(pooled_mean([np.nan], [4]))


def test_the_fast_median_and_the_sorted_count_are_numpys_to_the_bit():
    from mutualslam_cli.metrics.ratios import count_within, median

    rng = np.random.default_rng(3)
    for n in (1, 2, 11, 12, 10001):
        for dtype in (np.float32, np.float64):
            x = rng.random(n).astype(dtype) + 0.5
            assert median(x) == float(np.median(x))
    t = 0.25
    for s in (1.0, 0.8, 1.37, 2.0):
        # ratios packed around both ends of |s·r − 1| < t, the ends themselves included
        ends = np.array([(1 - t) / s, (1 + t) / s])
        r = np.sort(np.concatenate([rng.random(5000) * 3, ends, np.nextafter(ends, 0), np.nextafter(ends, 9),
                                    np.repeat(ends, 3)]))
        assert count_within(r, s, t) == np.count_nonzero(np.abs(s * r - 1.0) < t)
    assert count_within(np.sort(rng.random(100)), float("nan"), t) == 0

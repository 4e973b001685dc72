"""Warp (Eq. 5) and losses (Eq. 3, 4, 6, 7, 8): gradients, synthetic geometry, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.losses import (
    photometric_error,
    photometric_loss,
    smoothness_loss,
    sparse_depth_loss,
    ssim,
    train_loss,
)
from mutualslam_cli.adapt.warp import warp
from mutualslam_cli.errors import ShapeError


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _pose(t, r=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rot(*r)
    T[:3, 3] = t
    return T


def _texture(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Smooth multi-frequency colour texture on the plane (world X, Y in metres)."""
    r = 0.5 + 0.2 * np.sin(7 * X + 1) + 0.2 * np.cos(5 * Y + 0.3 * X)
    g = 0.5 + 0.25 * np.sin(4 * X - 6 * Y)
    b = 0.5 + 0.2 * np.cos(9 * Y) * np.sin(3 * X + 2)
    return np.stack([r, g, b])


def _render_plane(T_wc: np.ndarray, K: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the tilted plane Z = 2 + 0.3·X (world): image (3, H, W), z-depth (H, W)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays_c = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(h * w)]))
    R, c = T_wc[:3, :3], T_wc[:3, 3]
    rays_w = R @ rays_c
    n, d0 = np.array([-0.3, 0.0, 1.0]), 2.0  # plane n·X = d0
    lam = (d0 - n @ c) / (n @ rays_w)
    Xw = c[:, None] + lam * rays_w
    img = _texture(Xw[0], Xw[1]).reshape(3, h, w)
    return img, lam.reshape(h, w)  # rays_c has z = 1, so lam is the z-depth


def _pair(h=48, w=64, fy_sign=1.0):
    K = np.array([[60.0, 0, (w - 1) / 2], [0, fy_sign * 60.0, (h - 1) / 2], [0, 0, 1]])
    T_t, T_s = _pose([0, 0, 0]), _pose([0.12, -0.05, 0.05], (0.02, -0.04, 0.01))
    It, Dt = _render_plane(T_t, K, h, w)
    Is, _ = _render_plane(T_s, K, h, w)
    T_t2s = np.linalg.inv(T_s) @ T_t
    f = lambda a: torch.tensor(a, dtype=torch.float32)[None]  # noqa: E731
    return f(It), f(Is), f(Dt)[None], f(K), f(T_t2s)


@pytest.mark.parametrize("fy_sign", [1.0, -1.0])
def test_warp_gt_geometry_reconstructs_target(fy_sign):
    It, Is, Dt, K, T = _pair(fy_sign=fy_sign)
    warped, valid = warp(Is, Dt, K, T)
    assert valid.dtype == torch.bool
    assert 0.5 < float(valid.float().mean()) < 1.0
    pe_gt = float(photometric_error(It, warped)[valid].mean())
    T_bad = T.clone()
    T_bad[0, :3, 3] += torch.tensor([0.04, 0.03, 0.0])
    warped_bad, valid_bad = warp(Is, Dt, K, T_bad)
    pe_bad = float(photometric_error(It, warped_bad)[valid_bad].mean())
    assert pe_gt < 0.01
    assert pe_bad > 5 * pe_gt
    # and the full Eq. 3 loss agrees
    assert float(photometric_loss(It, [Is], Dt, K, [T])) < 0.01


def test_warp_identity_and_validity():
    torch.manual_seed(0)
    src = torch.rand(2, 3, 8, 10)
    depth = torch.rand(2, 1, 8, 10) + 1
    K = torch.tensor([[8.0, 0, 4.5], [0, 8.0, 3.5], [0, 0, 1]]).expand(2, 3, 3)
    warped, valid = warp(src, depth, K, torch.eye(4).expand(2, 4, 4))
    assert torch.allclose(warped, src, atol=1e-5)
    assert bool(valid.all())
    behind = torch.eye(4).expand(2, 4, 4).clone()
    behind[:, 2, 3] = -5.0  # every point ends up behind the source camera
    assert not bool(warp(src, depth, K, behind)[1].any())
    with pytest.raises(ShapeError):
        warp(src, depth[:, :, :4], K, torch.eye(4).expand(2, 4, 4))


def test_photometric_loss_takes_per_pixel_minimum():
    It, Is, Dt, K, T = _pair()
    noise = torch.rand_like(Is, generator=torch.Generator().manual_seed(1))
    one = float(photometric_loss(It, [noise], Dt, K, [T]))
    both = float(photometric_loss(It, [noise, Is], Dt, K, [T, T]))
    assert both < 0.2 * one  # the good source wins wherever it is valid
    with pytest.raises(ShapeError):
        photometric_loss(It, [Is, Is], Dt, K, [T])


def test_ssim_properties():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 12, 12, generator=g)
    assert float(ssim(x, x).max()) < 1e-6
    d = ssim(x, torch.rand(1, 3, 12, 12, generator=g))
    assert d.shape == x.shape
    assert 0.2 < float(d.mean()) <= 1.0


def test_sparse_loss_values_and_empty_mask():
    depth = torch.full((2, 1, 6, 8), 2.0, requires_grad=True)
    uv = torch.tensor([[[1.5, 2.25], [7.0, 5.0]], [[0.0, 0.0], [3.0, 3.0]]])
    d = torch.tensor([[4.0, 1.0], [2.0, 0.0]])
    mask = torch.tensor([[True, False], [True, False]])
    # image 0: |1/2 − 1/4| = 0.25; image 1: |1/2 − 1/2| = 0 → mean over images 0.125
    assert float(sparse_depth_loss(depth, uv, d, mask).detach()) == pytest.approx(0.125)
    empty = sparse_depth_loss(depth, uv, d, torch.zeros_like(mask))
    assert float(empty) == 0.0
    assert empty.requires_grad
    empty.backward()
    assert torch.isfinite(depth.grad).all()
    assert float(depth.grad.abs().sum()) == 0.0


def test_sparse_loss_bilinear_subpixel():
    depth = torch.arange(1.0, 13.0).reshape(1, 1, 3, 4)  # D(u, v) = 1 + u + 4v
    uv = torch.tensor([[[1.5, 0.5]]])  # bilinear: 1 + 1.5 + 2 = 4.5
    got = sparse_depth_loss(depth, uv, torch.tensor([[1.0]]), torch.tensor([[True]]))
    assert float(got) == pytest.approx(1.0 - 1 / 4.5, rel=1e-6)


def test_smoothness_edge_aware_and_scale_invariant():
    g = torch.Generator().manual_seed(0)
    depth = 1 + torch.rand(1, 1, 10, 12, generator=g)
    flat = torch.full((1, 3, 10, 12), 0.5)
    edges = torch.rand(1, 3, 10, 12, generator=g)
    assert float(smoothness_loss(depth, edges)) < float(smoothness_loss(depth, flat))
    assert float(smoothness_loss(3 * depth, flat)) == pytest.approx(float(smoothness_loss(depth, flat)), rel=1e-5)
    assert float(smoothness_loss(torch.ones_like(depth), flat)) == 0.0


def test_train_loss_combines_terms_and_stays_fp32_under_autocast():
    It, Is, Dt, K, T = _pair()
    uv = torch.tensor([[[10.0, 10.0], [30.0, 20.0]]])
    d = torch.tensor([[2.5, 3.0]])
    mask = torch.tensor([[True, True]])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        total, parts = train_loss(Dt.bfloat16(), It.bfloat16(), [Is.bfloat16()], K, [T], uv, d, mask,
                                  lambda_sparse=0.5, lambda_smooth=0.2)
    assert total.dtype == torch.float32
    assert set(parts) == {"photo", "sparse", "smooth", "total"}
    assert parts["total"] == pytest.approx(parts["photo"] + 0.5 * parts["sparse"] + 0.2 * parts["smooth"], rel=1e-5)
    assert parts["sparse"] > 0


# ---- float64 gradchecks on tiny inputs ------------------------------------------------------------

def _tiny(seed=0, h=5, w=6):
    g = torch.Generator().manual_seed(seed)
    img = lambda: torch.rand(1, 3, h, w, generator=g, dtype=torch.float64)  # noqa: E731
    depth = (1.5 + 0.5 * torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)).requires_grad_()
    K = torch.tensor([[[5.0, 0, 2.5], [0, 5.0, 2.0], [0, 0, 1]]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, :3, 3] = torch.tensor([0.15, 0.05, 0.02])
    return img(), img(), depth, K, T


def test_gradcheck_ssim_and_pe():
    t, s, *_ = _tiny()
    s.requires_grad_()
    assert torch.autograd.gradcheck(lambda y: ssim(t, y), (s,))
    assert torch.autograd.gradcheck(lambda y: photometric_error(t, y), (s,))


def test_gradcheck_photometric_loss_wrt_depth():
    t, s, depth, K, T = _tiny()
    T2 = T.clone()
    T2[0, :3, 3] = torch.tensor([-0.1, 0.02, 0.0])
    assert torch.autograd.gradcheck(lambda dd: photometric_loss(t, [s, t.flip(-1)], dd, K, [T, T2]), (depth,))


def test_gradcheck_sparse_and_smooth():
    t, _, depth, _, _ = _tiny()
    uv = torch.tensor([[[1.3, 2.7], [4.2, 0.6], [2.5, 3.1]]], dtype=torch.float64)
    d = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, False]])
    assert torch.autograd.gradcheck(lambda dd: sparse_depth_loss(dd, uv, d, mask), (depth,))
    assert torch.autograd.gradcheck(lambda dd: smoothness_loss(dd, t), (depth,))


# ---- exact values of SSIM and pe (Eq. 4) against an independent numpy reference -----------------

_C1, _C2 = 0.01 ** 2, 0.03 ** 2  # Wang et al. 2004 constants for images in [0, 1]


def _ssim_np(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """SSIM (not the dissimilarity) of ``(C, H, W)`` images from its definition: 3×3 mean windows
    on reflection-padded images (``np.pad(mode="reflect")`` = torch ``reflect``: the edge is not repeated)."""
    h, w = x.shape[1:]

    def box(a: np.ndarray) -> np.ndarray:
        a = np.pad(a, ((0, 0), (1, 1), (1, 1)), mode="reflect")
        return sum(a[:, i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0

    mx, my = box(x), box(y)
    vx, vy, cxy = box(x * x) - mx ** 2, box(y * y) - my ** 2, box(x * y) - mx * my
    return ((2 * mx * my + _C1) * (2 * cxy + _C2)) / ((mx ** 2 + my ** 2 + _C1) * (vx + vy + _C2))


def _pe_np(x: np.ndarray, y: np.ndarray, alpha: float) -> np.ndarray:
    """Eq. 4 per pixel, channels averaged: α/2·(1 − SSIM) + (1 − α)·|x − y|  →  ``(H, W)``."""
    return (alpha / 2 * (1 - _ssim_np(x, y)) + (1 - alpha) * np.abs(x - y)).mean(0)


def test_ssim_is_the_half_dissimilarity_closed_form_on_constant_images():
    # constant images: all local variances/covariances are 0, so SSIM = (2ab + C1) / (a² + b² + C1)
    a = np.array([0.2, 0.9, 0.5])
    b = np.array([0.6, 0.1, 0.5])  # the third channel is identical
    x = torch.tensor(a, dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 5, 7).contiguous()
    y = torch.tensor(b, dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 5, 7).contiguous()
    s = (2 * a * b + _C1) / (a ** 2 + b ** 2 + _C1)
    got = ssim(x, y)
    assert got.shape == (1, 3, 5, 7)
    for c in range(3):
        np.testing.assert_allclose(got[0, c].numpy(), (1 - s[c]) / 2, rtol=0, atol=1e-12)
    assert float(got[0, 2].abs().max()) == 0.0  # identical channel: exactly the minimum, 0


def test_ssim_extremes_identical_is_zero_and_matches_numpy_reference():
    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 3, 9, 11, generator=g, dtype=torch.float64)
    y = torch.rand(2, 3, 9, 11, generator=g, dtype=torch.float64)
    assert float(ssim(x, x).abs().max()) == 0.0  # identical images → dissimilarity exactly 0 (SSIM = 1)
    assert float(photometric_error(x, x).abs().max()) == 0.0
    # anti-correlated structure (y = 1 − x on a checkerboard): SSIM ≈ −1 → dissimilarity close to its max 1
    cb = torch.tensor((np.indices((8, 8)).sum(0) % 2).astype(np.float64))[None, None]
    assert float(ssim(cb, 1 - cb).min()) > 0.95
    for i in range(2):  # general case, borders included (reflection padding)
        np.testing.assert_allclose(ssim(x, y)[i].numpy(), (1 - _ssim_np(x[i].numpy(), y[i].numpy())) / 2,
                                   rtol=0, atol=1e-12)


@pytest.mark.parametrize("alpha", [0.85, 0.3])
def test_pe_equals_eq4_on_constant_images(alpha):
    # hand-computable: per channel SSIM = (2ab + C1)/(a² + b² + C1), L1 = |a − b|; pe averages channels
    a = np.array([0.2, 0.9, 0.5])
    b = np.array([0.6, 0.1, 0.45])
    x = torch.tensor(a, dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 4, 6).contiguous()
    y = torch.tensor(b, dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 4, 6).contiguous()
    s = (2 * a * b + _C1) / (a ** 2 + b ** 2 + _C1)
    want = float(np.mean(alpha / 2 * (1 - s) + (1 - alpha) * np.abs(a - b)))
    got = photometric_error(x, y, alpha)
    assert got.shape == (1, 1, 4, 6)
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    # float32 inputs (the training path): σ² = E[x²] − μ² cancels in fp32 (error ~ eps·μ² ≈ 5e-8, against
    # C2 = 9e-4 in a flat window), so flat regions are only good to ~2e-5; still far below the SSIM term
    np.testing.assert_allclose(photometric_error(x.float(), y.float(), alpha).numpy(), want, rtol=0, atol=5e-5)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.85, 1.0])
def test_pe_equals_eq4_numpy_reference(alpha):
    # α = 1 isolates the SSIM term (α/2·(1 − SSIM)), α = 0 the L1 term; 0.3 and 0.85 pin the mix
    g = torch.Generator().manual_seed(11)
    x = torch.rand(2, 3, 10, 13, generator=g, dtype=torch.float64)
    y = (0.6 * x + 0.4 * torch.rand(2, 3, 10, 13, generator=g, dtype=torch.float64)).clamp(0, 1)
    got = photometric_error(x, y, alpha)
    assert got.shape == (2, 1, 10, 13)
    for i in range(2):
        want = _pe_np(x[i].numpy(), y[i].numpy(), alpha)
        np.testing.assert_allclose(got[i, 0].numpy(), want, rtol=0, atol=1e-10)
        np.testing.assert_allclose(photometric_error(x.float(), y.float(), alpha)[i, 0].numpy(), want,
                                   rtol=0, atol=1e-5)  # fp32 rounding of the local variances


def test_ssim_of_one_target_against_stacked_sources_equals_the_repeated_target():
    """Target statistics computed once per target give exactly the numbers of a repeated target."""
    g = torch.Generator().manual_seed(3)
    t = torch.rand(2, 3, 9, 11, generator=g)
    w = torch.rand(6, 3, 9, 11, generator=g)
    assert torch.equal(ssim(t, w), ssim(t.repeat(3, 1, 1, 1), w))
    assert torch.equal(photometric_error(t, w), photometric_error(t.repeat(3, 1, 1, 1), w))
    s = torch.rand(4, 3, 6, 7, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda y: ssim(t[:, :, :6, :7].double(), y), (s,))
    with pytest.raises(ShapeError):
        ssim(t, w[:5])

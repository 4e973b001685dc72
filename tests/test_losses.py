"""Warp (Eq. 5) and losses (Eq. 3, 4, 6, 7, 8): gradients, synthetic geometry, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.losses import (photometric_error, photometric_loss, smoothness_loss, sparse_depth_loss,
                                         ssim, train_loss)
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
    assert valid.dtype == torch.bool and 0.5 < float(valid.float().mean()) < 1.0  # some pixels leave the view
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
    assert torch.allclose(warped, src, atol=1e-5) and bool(valid.all())
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
    assert d.shape == x.shape and 0.2 < float(d.mean()) <= 1.0


def test_sparse_loss_values_and_empty_mask():
    depth = torch.full((2, 1, 6, 8), 2.0, requires_grad=True)
    uv = torch.tensor([[[1.5, 2.25], [7.0, 5.0]], [[0.0, 0.0], [3.0, 3.0]]])
    d = torch.tensor([[4.0, 1.0], [2.0, 0.0]])
    mask = torch.tensor([[True, False], [True, False]])
    # image 0: |1/2 − 1/4| = 0.25; image 1: |1/2 − 1/2| = 0 → mean over images 0.125
    assert float(sparse_depth_loss(depth, uv, d, mask).detach()) == pytest.approx(0.125)
    empty = sparse_depth_loss(depth, uv, d, torch.zeros_like(mask))
    assert float(empty) == 0.0 and empty.requires_grad
    empty.backward()
    assert torch.isfinite(depth.grad).all() and float(depth.grad.abs().sum()) == 0.0


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

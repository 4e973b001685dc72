"""Inverse warping of a source image into the target view (paper Eq. 5).

Pixel convention (``types.py``): ``(u, v)`` = (column, row) with the origin at the centre
of the top-left pixel, so ``grid_sample`` is used with ``align_corners=True``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mutualslam_cli.errors import ShapeError
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import check_shape

#: Minimum source-camera z (same units as depth) for a projection to count as valid.
MIN_Z = 1e-3


def pixel_grid(b: int, h: int, w: int, dtype: torch.dtype, device: torch.device | str = "cpu") -> torch.Tensor:
    """Homogeneous pixel coordinates ``(B, 3, H·W)``: rows ``u``, ``v``, ``1``."""
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype, device=device),
                          torch.arange(w, dtype=dtype, device=device), indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=dtype, device=device)])
    return pix.unsqueeze(0).expand(b, 3, h * w)


def project_to_source(depth_t: torch.Tensor, K: torch.Tensor, T_t2s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Source-image pixel of every target pixel: ``p' ~ K T_{t→s} D(p) K⁻¹ p`` (Eq. 5).

    Args:
        depth_t: ``(B, 1, H, W)`` target depth.
        K: ``(B, 3, 3)`` intrinsics at this resolution (``fy`` may be negative).
        T_t2s: ``(B, 4, 4)`` maps target-camera points to source-camera points
            (``T_t2s = inv(T_wc_s) @ T_wc_t``).

    Returns:
        ``uv`` ``(B, H, W, 2)`` source pixels and ``z`` ``(B, 1, H, W)`` source-camera depth.
    """
    b, _, h, w = depth_t.shape
    dtype = depth_t.dtype
    K = K.to(dtype)
    T = T_t2s.to(dtype)
    rays = torch.linalg.inv(K) @ pixel_grid(b, h, w, dtype, depth_t.device)    # K⁻¹ p, (B, 3, HW)
    pts = rays * depth_t.reshape(b, 1, h * w)                                    # D(p) K⁻¹ p
    pts_s = T[:, :3, :3] @ pts + T[:, :3, 3:4]                                   # T_{t→s} X
    proj = K @ pts_s                                                              # K X_s
    z = proj[:, 2:3]
    z_safe = torch.where(z.abs() > MIN_Z, z, torch.full_like(z, MIN_Z))
    uv = (proj[:, :2] / z_safe).permute(0, 2, 1).reshape(b, h, w, 2)
    return uv, pts_s[:, 2:3].reshape(b, 1, h, w)


def warp(src: torch.Tensor, depth_t: torch.Tensor, K: torch.Tensor,
         T_t2s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reconstruct the target view from ``src``: ``I_{s→i}(p) = I_s(p')`` (Eq. 5), bilinear.

    Args:
        src: ``(B, C, H, W)`` source image.
        depth_t: ``(B, 1, H, W)`` depth of the target view (predicted or GT).
        K: ``(B, 3, 3)`` intrinsics at this resolution.
        T_t2s: ``(B, 4, 4)`` target-camera → source-camera transform.

    Returns:
        ``warped`` ``(B, C, H, W)`` (border padding outside the image) and ``valid``
        ``(B, 1, H, W)`` bool: ``p'`` lies inside the source image (pixel centres
        ``[0, W−1] × [0, H−1]``) and the point is in front of the source camera (z > ``MIN_Z``).
    """
    check_shape(src, ["B", "C", "H", "W"], "warp.src")
    check_shape(depth_t, ["B", 1, "H", "W"], "warp.depth_t")
    if depth_t.shape[0] != src.shape[0] or depth_t.shape[2:] != src.shape[2:]:
        raise ShapeError(f"warp: src {tuple(src.shape)} and depth_t {tuple(depth_t.shape)} differ in B, H or W")
    b, _, h, w = src.shape
    check_shape(K, [b, 3, 3], "warp.K")
    check_shape(T_t2s, [b, 4, 4], "warp.T_t2s")
    uv, z = project_to_source(depth_t, K, T_t2s)
    u, v = uv[..., 0], uv[..., 1]
    valid = (z[:, 0] > MIN_Z) & in_image(uv, w, h)
    grid = torch.stack([2.0 * u / max(w - 1, 1) - 1.0, 2.0 * v / max(h - 1, 1) - 1.0], dim=-1)
    warped = F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode="border", align_corners=True)
    return warped, valid.unsqueeze(1)

"""Pixel positions against an image: the package's one bounds rule and nearest-pixel lookup.

Pixel centres have integer coordinates, so an ``H × W`` image spans ``[0, W − 1] × [0, H − 1]``
(the domain of bilinear sampling). A projected position is *inside* when it lies in that span
shrunk by ``margin`` on every side, with a tolerance of :data:`PIXEL_TOL`: positions computed by a
projection (``K · (K⁻¹ · p)``, an SE(3) round trip) carry rounding errors that depend on the CPU's
kernels and thread count, and an exact border pixel must not fall outside on one machine and
inside on another. Every bounds test of the package goes through :func:`in_image`, in numpy and in
torch alike.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

Coords = TypeVar("Coords", "np.ndarray", "torch.Tensor")
"""Pixel coordinates and the mask of them: all numpy or all torch (torch is not imported here)."""

#: Positions up to this far (px) outside the span still count as inside. Measured: float32 round
#: trips ``p → d·K⁻¹p → T → T⁻¹ → K`` of border pixels (random intrinsics up to 640 px with |fx|,
#: |fy| ≤ 800, depth 0.5–10, |t| ≤ 0.5, any rotation) land within 2.7e-4 px; float64 within
#: 1e-11. Half of the 1e-3 px that must still count as outside.
PIXEL_TOL = 5e-4


def in_image(uv: Coords, width: int, height: int, margin: float = 0.0, tol: float = PIXEL_TOL) -> Coords:
    """Whether pixel positions lie inside the image (the bounds rule of the module docstring).

    ``margin − tol ≤ u ≤ W − 1 − margin + tol`` and the same for ``v`` with ``H``.

    Args:
        uv: ``(..., 2)`` positions ``(u, v)`` in pixels, a numpy array or a torch tensor.
        width, height: image size ``W``, ``H`` in pixels.
        margin: pixels kept free on every side (a patch's half-width, a KLT window's).
        tol: rounding tolerance in pixels.

    Returns:
        ``(...)`` bool mask of the same kind as ``uv`` (numpy or torch).
    """
    return in_image_uv(uv[..., 0], uv[..., 1], width, height, margin, tol)


def in_image_uv(u: Coords, v: Coords, width: int, height: int, margin: float = 0.0,
                tol: float = PIXEL_TOL) -> Coords:
    """:func:`in_image` for coordinates held apart: ``u`` and ``v`` of one shape (numpy or torch)."""
    lo = margin - tol
    return (u >= lo) & (u <= width - 1 - margin + tol) & (v >= lo) & (v <= height - 1 - margin + tol)


def lookup_nearest(image: np.ndarray, uv: np.ndarray, size: tuple[int, int] | None = None,
                   fill: float = np.nan) -> np.ndarray:
    """Values of a one-channel ``image`` ``(h, w)`` at the pixels nearest to positions ``uv``.

    ``uv`` are positions in a frame of ``size = (W, H)`` pixels (default: the image's own). Inside
    is decided there (:func:`in_image`); the positions are then carried to the image's resolution
    by the pixel-centre rule ``(u + 0.5)·w/W − 0.5`` and rounded, clipped into the image.

    Args:
        image: ``(h, w)`` values (depth, intensity).
        uv: ``(N, 2)`` positions in pixels of the ``size`` frame.
        size: ``(W, H)`` of the frame ``uv`` is measured in.
        fill: value for positions outside.

    Returns:
        ``(N,)`` float64.
    """
    h, w = image.shape[:2]
    W, H = (w, h) if size is None else size
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    cols = np.clip(np.rint((uv[:, 0] + 0.5) * (w / W) - 0.5), 0, w - 1).astype(np.int64)
    rows = np.clip(np.rint((uv[:, 1] + 0.5) * (h / H) - 0.5), 0, h - 1).astype(np.int64)
    return np.where(in_image(uv, W, H), image[rows, cols], fill).astype(np.float64)

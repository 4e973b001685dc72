"""The one pixel-bounds rule (mutualslam_cli.pixels) and the sites that decide "inside the image" with it.

An exact border pixel sent through a projection comes back a few ulps off, by an amount that
depends on the CPU's kernels and thread count; it must stay inside on every machine, while a
position 1e-3 px outside must be outside.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

import mutualslam_cli
from mutualslam_cli.adapt.warp import warp
from mutualslam_cli.backend.culling import cull_map_points
from mutualslam_cli.datasets.fy_sign import warp_error
from mutualslam_cli.geometry import exp_so3 as _exp_so3
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.pixels import PIXEL_TOL, in_image, in_image_uv, lookup_nearest
from mutualslam_cli.types import Intrinsics, Trajectory


def exp_so3(phi: np.ndarray) -> np.ndarray:
    return _exp_so3(np.asarray(phi, float)[None])[0]


def _random_camera(rng: np.random.Generator) -> tuple[np.ndarray, int, int]:
    w, h = int(rng.choice([64, 320, 640])), int(rng.choice([48, 192, 480]))
    fy = rng.uniform(100, 800) * rng.choice([-1.0, 1.0])  # ICL-NUIM's frame has fy < 0
    K = np.array([[rng.uniform(100, 800), 0, rng.uniform(0.3, 0.7) * w], [0, fy, rng.uniform(0.3, 0.7) * h],
                  [0, 0, 1]])
    return K, w, h


def _border_pixels(w: int, h: int, rng: np.random.Generator) -> np.ndarray:
    """The four corners and a pixel on each side: every one exactly on the border."""
    return np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1],
                     [0, rng.integers(h)], [w - 1, rng.integers(h)], [rng.integers(w), 0], [rng.integers(w), h - 1]],
                    float)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_se3_round_trips_keep_exact_border_pixels_inside(dtype):
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(500):
        K, w, h = _random_camera(rng)
        p = _border_pixels(w, h, rng)
        T = np.eye(4)
        T[:3, :3] = exp_so3(rng.normal(size=3))
        T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
        Kd, Td = K.astype(dtype), T.astype(dtype)
        d = rng.uniform(0.5, 10, len(p)).astype(dtype)
        X = (np.linalg.inv(Kd) @ np.c_[p, np.ones(len(p))].T.astype(dtype)) * d  # back-project
        Y = Td[:3, :3] @ X + Td[:3, 3:]  # into another camera …
        X2 = Td[:3, :3].T @ (Y - Td[:3, 3:])  # … and back
        q = Kd @ X2
        uv = (q[:2] / q[2]).T
        worst = max(worst, float(np.abs(uv - p).max()))
        assert in_image(uv, w, h).all(), (uv, w, h)
        assert in_image(torch.from_numpy(uv.copy()), w, h).all()
    assert worst < PIXEL_TOL


def test_a_point_1e3_px_outside_is_outside_and_margins_shrink_the_span():
    w, h = 64, 48
    for uv in ([-1e-3, 10], [w - 1 + 1e-3, 10], [10, -1e-3], [10, h - 1 + 1e-3]):
        assert not in_image(np.array([uv]), w, h)[0]
        assert not bool(in_image(torch.tensor([uv]), w, h)[0])
    assert in_image(np.array([[0.0, 0.0], [w - 1, h - 1]]), w, h).all()
    assert in_image(np.array([[2.0, 2.0], [w - 3, h - 3]]), w, h, margin=2).all()
    assert not in_image(np.array([[1.99, 5.0]]), w, h, margin=2).any()
    assert not in_image(np.array([[5.0, h - 3 + 1e-3]]), w, h, margin=2).any()
    u, v = np.array([[0.0, w - 1.0], [-1.0, w]]), np.array([[0.0, h - 1.0], [0.0, 0.0]])
    np.testing.assert_array_equal(in_image_uv(u, v, w, h), [[True, True], [False, False]])


def test_lookup_nearest_at_a_lower_resolution_keeps_the_border():
    depth = np.arange(12, dtype=float).reshape(3, 4)  # a 4×3 map of a 640×480 frame
    uv = np.array([[0.0, 0.0], [639.0, 479.0], [-1e-6, 479.0 + 1e-6], [-0.01, 100.0], [320.0, 480.5]])
    got = lookup_nearest(depth, uv, (640, 480))
    np.testing.assert_array_equal(got[:3], [0.0, 11.0, 8.0])
    assert np.isnan(got[3:]).all()
    np.testing.assert_array_equal(lookup_nearest(depth, np.array([[3.0, 2.0], [4.0, 0.0]]), fill=-1.0), [11.0, -1.0])


# ----------------------------------------------------------------------------- the sites


def test_warp_keeps_a_border_column_a_rounding_error_outside():
    """adapt/warp.py: a source pose 1e-5 px off the identity keeps column 0 valid; 2e-3 px does not."""
    src = torch.rand(1, 3, 8, 10, generator=torch.Generator().manual_seed(0))
    depth = torch.full((1, 1, 8, 10), 2.0)
    K = torch.tensor([[[8.0, 0, 4.5], [0, -8.0, 3.5], [0, 0, 1]]])
    for shift_px, col0_valid in ((1e-5, True), (2e-3, False)):
        T = torch.eye(4)[None].clone()
        T[0, 0, 3] = -shift_px * 2.0 / 8.0  # u' = u − shift_px at depth 2
        valid = warp(src, depth, K, T)[1][0, 0]
        assert bool(valid[:, 0].all()) is col0_valid
        assert bool(valid[:, 1:].all())


def _border_vo() -> tuple[VOResult, np.ndarray]:
    """Two rotated keyframes; points hosted in kf 0 on its four corners (pixels of an SE(3) round trip)."""
    intr = Intrinsics(100.0, -100.0, 50.3, 40.7, 100, 80)
    T0, T1 = np.eye(4), np.eye(4)
    T0[:3, :3], T0[:3, 3] = exp_so3(np.array([0.3, -0.2, 0.1])), [0.31, -0.17, 0.05]
    T1[:3, :3], T1[:3, 3] = exp_so3(np.array([0.1, 0.2, -0.1])), [0.5, 0.1, 0.0]
    pix = np.array([[0.0, 0.0], [99.0, 0.0], [0.0, 79.0], [99.0, 79.0]])
    z = np.array([1.3, 0.7, 2.9, 1.1])
    pts = MapPoints(np.arange(4), np.zeros(4, np.int64), pix, 1.0 / z, np.zeros(4), [np.array([0, 1])] * 4,
                    [np.zeros((2, 2))] * 4)
    kfs = [Keyframe(0, 0, 0.0, T0), Keyframe(1, 1, 0.1, T1)]
    return VOResult(kfs, pts, intr, Trajectory(np.array([0.0, 0.1]), np.stack([T0, T1])), np.zeros(2, np.int64)), z


def test_sparse_depth_keeps_map_points_on_the_border():
    """vo/output.py (D_sparse of Eq. 6): points hosted on the border corners survive the world round trip."""
    vo, z = _border_vo()
    pix, d = vo.sparse_depth(0)
    assert len(pix) == 4
    np.testing.assert_allclose(d, z, rtol=1e-9)


def test_culling_judges_map_points_on_the_border():
    """backend/culling.py: a corner point is compared with the CNN depth, not left unjudged."""
    vo, _z = _border_vo()
    res = cull_map_points(vo, {0: 0.1, 1: 0.2}, lambda k, px: np.full(len(px), 1.0), 0.5, 1.5)
    assert res.judged.all()


def test_fy_sign_warp_counts_every_pixel_of_an_identity_warp():
    """datasets/fy_sign.py: with the same pose twice every sampled pixel lands inside, border included."""
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 255, (48, 64)).astype(np.uint8)
    depth = rng.uniform(0.5, 4.0, (48, 64)).astype(np.float32)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = exp_so3(np.array([0.4, -0.3, 0.2])), [0.7, -0.2, 0.3]
    K = np.array([[50.3, 0, 31.7], [0, -50.1, 23.9], [0, 0, 1]])
    err, n = warp_error(gray, depth, gray, T, T, K, step=1)
    assert n == 48 * 64
    assert err < 1e-3


# Hand-written bounds tests: a position compared with 0 and with W−1 / H−1 / W (the rule lives in
# pixels.py; an integer index loop bound such as `idx < len(x)` is not a pixel position).
_HAND_BOUNDS = re.compile(r"(>=?\s*0\)?\s*&[^\n]*(<=?)\s*\(?\s*(w|h|W|H|width|height|self\.W|self\.H)\b)"
                          r"|(<=?\s*(w|h|W|H)\s*-\s*\d)|(<\s*d\.shape\[[01]\])")


def test_no_module_decides_inside_the_image_by_hand():
    """vo/frontend.py, vo/reproject.py, vo/tracking.py, vo/oracle.py, backend/ba/global_ba.py, backend/ba/residuals.py,
    evaluation.py and the dense stage use :mod:`mutualslam_cli.pixels` rather than their own comparison."""
    root = Path(mutualslam_cli.__file__).parent
    hits = [f"{f.relative_to(root)}:{i}: {line.strip()}"
            for f in sorted(root.rglob("*.py")) if f.name != "pixels.py"
            for i, line in enumerate(f.read_text().splitlines(), 1) if _HAND_BOUNDS.search(line)]
    assert not hits, "\n".join(hits)

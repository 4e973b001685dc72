"""Analytic ray casting of a box scene with mip-mapped textures (the synthetic renderer).

Each frame is ray-cast analytically (slab method, Kay & Kajiya 1986): camera rays
``d = R_wc K⁻¹ [u, v, 1]ᵀ`` have unit camera z, so the ray parameter at the hit *is* the
z-depth. The enclosing box (the room) is seen from inside, every other box from outside and
z-buffered. Texture coordinates come from the hit point and are sampled from a mip-mapped atlas
(:mod:`~mutualslam_cli.datasets.synthetic.textures`) with ``cv2.remap``, blending two mip levels
(trilinear filtering, Williams 1983).
"""

from __future__ import annotations

import cv2
import numpy as np

from mutualslam_cli.datasets.synthetic.scenes import SceneDef
from mutualslam_cli.datasets.synthetic.textures import N_LEVELS, Atlas
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import Intrinsics

assert N_LEVELS == 4, "Renderer._shade blends mip levels 0..3"

_BOX_EDGES = [(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit]
"""The 12 edges of a box as pairs of corner indices (corners differ in one coordinate bit)."""


class Renderer:
    """Ray-caster of one scene at one resolution (precomputed rays, atlas)."""

    def __init__(self, scene: SceneDef, atlas: Atlas, intr: Intrinsics) -> None:
        self.scene, self.atlas, self.intr = scene, atlas, intr
        W, H = intr.width, intr.height
        self.xn = ((np.arange(W, dtype=np.float64) - intr.cx) / intr.fx).astype(np.float32)
        self.yn = ((np.arange(H, dtype=np.float64) - intr.cy) / intr.fy).astype(np.float32)
        # |K⁻¹[u, v, 1]| per pixel (rotation-invariant): ray length per unit z-depth.
        self.rnorm = np.sqrt(1.0 + self.xn[None, :] ** 2 + self.yn[:, None] ** 2).astype(np.float32)
        self.f_pix = float(np.sqrt(abs(intr.fx * intr.fy)))
        # Per-face lookup tables for cv2.LUT (face id is uint8 → ≤ 256 faces, 42 boxes).
        F = len(scene.face_axis)
        if F > 256:
            raise ConfigError(f"synthetic scene has {F} faces; at most 256 are supported")
        self.a_idx = np.array([(1, 0, 0)[k] for k in scene.face_axis])  # in-plane axes per face
        self.b_idx = np.array([(2, 2, 1)[k] for k in scene.face_axis])
        self.lut = {}
        for name, val, dt in (("axis", scene.face_axis, np.uint8), ("scale", atlas.scale, np.float32),
                              ("ox", atlas.ox + np.float32(0.5), np.float32),
                              ("oy", atlas.oy + np.float32(0.5), np.float32)):
            t = np.zeros((1, 256), dt)
            t[0, :F] = val
            self.lut[name] = t

    def _rays(self, R: np.ndarray) -> list[np.ndarray]:
        """World ray directions (3 × ``(H, W)`` float32), camera z component = 1."""
        out = []
        for k in range(3):
            row = (R[k, 0] * self.xn).astype(np.float32)[None, :]
            col = (R[k, 1] * self.yn + R[k, 2]).astype(np.float32)[:, None]
            out.append(row + col)
        return out

    def render(self, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame: ``(H, W, 3)`` uint8 RGB and ``(H, W)`` float32 z-depth (metres)."""
        R, o = T_wc[:3, :3], T_wc[:3, 3]
        d = self._rays(R)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = [np.float32(1.0) / dk for dk in d]
            depth, fid = self._enclosure(o, inv)
            for b in range(1, len(self.scene.boxes)):
                self._box(b, T_wc, o, inv, depth, fid)
        return self._shade(o, d, depth, fid), depth

    def _enclosure(self, o: np.ndarray, inv: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Exit of the rays from the enclosing box (camera inside): depth and face id."""
        lo, hi = self.scene.boxes[0].lo, self.scene.boxes[0].hi
        ts, sides = [], []
        for k in range(3):
            # Camera inside: hi − o > 0 > lo − o, so the exit is the positive one of the two.
            t = np.maximum(np.float32(hi[k] - o[k]) * inv[k], np.float32(lo[k] - o[k]) * inv[k])
            ts.append(t)
            sides.append((inv[k] > 0).view(np.uint8))
        depth = np.minimum(np.minimum(ts[0], ts[1]), ts[2])
        m0 = ts[0] == depth
        m1 = ts[1] == depth
        fid = np.where(m0, sides[0], np.where(m1, sides[1] + np.uint8(2), sides[2] + np.uint8(4)))
        return depth, fid

    def _roi(self, b: int, T_wc: np.ndarray) -> tuple[slice, slice] | None:
        """Image rows/cols that box ``b`` can cover (its projected corners' bounding box)."""
        box = self.scene.boxes[b]
        corners = np.array([[x, y, z] for x in (box.lo[0], box.hi[0]) for y in (box.lo[1], box.hi[1])
                            for z in (box.lo[2], box.hi[2])])
        pc = (corners - T_wc[:3, 3]) @ T_wc[:3, :3]
        zn = 1e-3
        front = pc[:, 2] >= zn
        if not front.any():
            return None
        pts = [pc[front]]
        if not front.all():
            # Clip the box by the plane z = zn: add where its edges cross it (corners i, j
            # differ in one coordinate bit). The hull of the projections bounds the image.
            for i, j in _BOX_EDGES:
                if front[i] != front[j]:
                    a_, b_ = pc[i], pc[j]
                    pts.append((a_ + (zn - a_[2]) / (b_[2] - a_[2]) * (b_ - a_))[None])
        pv = np.concatenate(pts)
        H, W = self.intr.height, self.intr.width
        u = self.intr.fx * pv[:, 0] / pv[:, 2] + self.intr.cx
        v = self.intr.fy * pv[:, 1] / pv[:, 2] + self.intr.cy
        u, v = np.clip(u, -2.0, W + 2.0), np.clip(v, -2.0, H + 2.0)
        c0, c1 = max(0, int(np.floor(u.min())) - 1), min(W, int(np.ceil(u.max())) + 2)
        r0, r1 = max(0, int(np.floor(v.min())) - 1), min(H, int(np.ceil(v.max())) + 2)
        if c0 >= c1 or r0 >= r1:
            return None
        return slice(r0, r1), slice(c0, c1)

    def _box(self, b: int, T_wc: np.ndarray, o: np.ndarray, inv: list[np.ndarray],
             depth: np.ndarray, fid: np.ndarray) -> None:
        """Z-buffer the entry points of the rays into box ``b`` (seen from outside)."""
        roi = self._roi(b, T_wc)
        if roi is None:
            return
        box = self.scene.boxes[b]
        tn, tf, sides = [], None, []
        for k in range(3):
            ik = inv[k][roi]
            t1 = np.float32(box.lo[k] - o[k]) * ik
            t2 = np.float32(box.hi[k] - o[k]) * ik
            tn.append(np.minimum(t1, t2))
            far = np.maximum(t1, t2)
            tf = far if tf is None else np.minimum(tf, far)
            sides.append((ik < 0).view(np.uint8))  # entering through the hi face when moving towards −axis
        tnear = np.maximum(np.maximum(tn[0], tn[1]), tn[2])
        hit = (tnear < tf) & (tnear > 1e-4) & (tnear < depth[roi])
        if not hit.any():
            return
        m0, m1 = tn[0] == tnear, tn[1] == tnear
        base = np.uint8(6 * b)
        local = np.where(m0, sides[0] + base,
                         np.where(m1, sides[1] + (base + np.uint8(2)), sides[2] + (base + np.uint8(4))))
        np.copyto(depth[roi], tnear, where=hit)
        np.copyto(fid[roi], local, where=hit)

    def _shade(self, o: np.ndarray, d: list[np.ndarray], depth: np.ndarray, fid: np.ndarray) -> np.ndarray:
        """Trilinear atlas lookup at the hit points: ``(H, W, 3)`` uint8."""
        at, lut = self.atlas, self.lut
        axis = cv2.LUT(fid, lut["axis"])
        ax0, ax2 = axis == 0, axis == 2
        # In-plane coordinates (a, b): x-faces (y, z), y-faces (x, z), z-faces (x, y).
        # Level-0 texel (+0.5) of the hit o + depth·d: (o_a + depth·d_a)·scale + ox + 0.5, with the
        # per-face constant o_a·scale + ox + 0.5 folded into a per-frame lookup table.
        F = len(self.a_idx)
        cx, cy = np.zeros((1, 256), np.float32), np.zeros((1, 256), np.float32)
        cx[0, :F] = o[self.a_idx] * at.scale + lut["ox"][0, :F]
        cy[0, :F] = o[self.b_idx] * at.scale + lut["oy"][0, :F]
        sc = cv2.LUT(fid, lut["scale"])
        x0 = np.where(ax0, d[1], d[0])
        x0 *= depth
        x0 *= sc
        x0 += cv2.LUT(fid, cx)
        y0 = np.where(ax2, d[1], d[2])
        y0 *= depth
        y0 *= sc
        y0 += cv2.LUT(fid, cy)
        # Texel footprint (texels per pixel): a pixel spans depth / (|d|·f) metres across the
        # ray; on the surface that is stretched by 1/cosθ (cosθ = |d_axis| / |d|) along one
        # axis; isotropic estimate = geometric mean → depth·scale / (f·sqrt(|d|·|d_axis|)).
        dn = np.abs(np.where(ax0, d[0], np.where(ax2, d[2], d[1])))
        dn *= self.rnorm
        np.maximum(dn, np.float32(1e-6), out=dn)
        foot: np.ndarray = depth * sc
        foot /= np.sqrt(dn, out=dn)
        foot *= np.float32(1.0 / self.f_pix)
        # Mip level l0 ∈ {0, 1, 2} and its scale s0 = 2^-l0; blend weight linear in the
        # footprint between levels l0 and l0 + 1 (Williams 1983, trilinear filtering).
        s0 = np.float32(1.0) - np.float32(0.5) * (foot >= 2) - np.float32(0.25) * (foot >= 4)
        frac = foot * s0
        frac -= 1.0
        np.clip(frac, 0.0, 1.0, out=frac)
        # Level-0 texel → level-l texel: x_l = (x0 + 0.5)·2^-l − 0.5 + origin_l.
        xa = x0 * s0
        ya = y0 * s0
        W0, H0 = np.float32(at.w0), np.float32(at.h0)
        xb = xa * np.float32(0.5)
        xb += W0 - np.float32(0.5)
        yb = ya * np.float32(0.5)
        yb += H0 * (np.float32(1.0) - s0) - np.float32(0.5)
        xa += W0 * (s0 < 1) - np.float32(0.5)
        ya += np.maximum(H0 * (np.float32(1.0) - 2 * s0), 0) - np.float32(0.5)
        img_a = cv2.remap(at.image, xa, ya, cv2.INTER_LINEAR)
        img_b = cv2.remap(at.image, xb, yb, cv2.INTER_LINEAR)
        out = cv2.blendLinear(img_a, img_b, np.float32(1.0) - frac, frac)
        return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB)

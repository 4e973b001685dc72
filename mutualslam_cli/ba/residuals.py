"""Photometric residuals of the global BA, their Jacobians and the robust cost.

One residual per (point, target keyframe) pair and per pixel of a ``patch × patch`` pattern
around the host pixel, all sharing the point's inverse depth (fronto-parallel patch), with
DSO's affine brightness model (Engel et al. 2018, "Direct Sparse Odometry", eq. 4):

    r = (I_t(π(T_t T_h⁻¹ π⁻¹(p + δ, ρ))) − b_t) − exp(a_t − a_h) · (I_h(p + δ) − b_h)

robustified with the Huber loss (Alismail et al. 2016, "Photometric Bundle Adjustment for
Vision-Based SLAM"). Poses are world-to-camera ``T_cw`` with left increments ``(ρ, φ)``
(:func:`mutualslam_cli.geometry.left_update`).

Image derivatives are those of the bilinear interpolant itself (not interpolated central-
difference gradient images): the Jacobians are then exact for the cost being minimised, which
the LM acceptance test compares. Residuals beyond the 2-px margin get weight 0 but keep their
(clamped) value in the cost, so the cost is continuous and a step is never rejected only
because one patch crossed the margin.
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.ba.problem import PhotoBAProblem
from mutualslam_cli.ba.schur import BlockStructure
from mutualslam_cli.pixels import in_image, in_image_uv


class PatchData:
    """Per-solve constants: image stack, patch rays, host intensities, block structure."""

    def __init__(self, prob: PhotoBAProblem, patch: int, margin: float):
        im = np.asarray(prob.images, np.float32)
        self.nk, self.H, self.W = im.shape
        self.flat = im.reshape(-1)
        Kc = np.asarray(prob.K, float)
        self.fx, self.fy, self.cx, self.cy = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]
        self.margin = margin
        r = np.arange(patch) - (patch - 1) / 2
        du, dv = [g.ravel() for g in np.meshgrid(r, r)]
        q = np.asarray(prob.pixel, float)[:, None, :] + np.stack([du, dv], 1)[None]  # (P, S, 2)
        self.xq = (q[..., 0] - self.cx) / self.fx  # normalised patch rays (P, S)
        self.yq = (q[..., 1] - self.cy) / self.fy
        hv = in_image(q, self.W, self.H)
        kf = np.broadcast_to(np.asarray(prob.host)[:, None], hv.shape)
        self.Ih = self.sample(kf, q[..., 0], q[..., 1])[0].astype(float)  # (P, S), constant
        p, t = np.asarray(prob.obs_pt), np.asarray(prob.obs_kf)
        order = np.argsort(np.asarray(prob.host)[p] * self.nk + t, kind="stable")  # by pair
        self.p, self.t = p[order], t[order]
        self.h = np.asarray(prob.host)[self.p]
        self.host_ok = hv[self.p]
        self.st = BlockStructure(np.asarray(prob.host), self.p, self.t, self.nk)

    def sample(self, kf: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Bilinear intensity at ``(u, v)`` (clamped inside the image) and its exact
        derivatives ``∂I/∂u``, ``∂I/∂v`` (those of the bilinear interpolant itself, so the
        Jacobians are consistent with the cost being minimised)."""
        u = np.clip(u, 0, self.W - 1.0001)
        v = np.clip(v, 0, self.H - 1.0001)
        x0, y0 = np.floor(u), np.floor(v)
        ax, ay = u - x0, v - y0
        i = (kf * self.H + y0.astype(np.int64)) * self.W + x0.astype(np.int64)
        f, W = self.flat, self.W
        i00, i01, i10, i11 = f[i], f[i + 1], f[i + W], f[i + W + 1]
        top = i00 + ax * (i01 - i00)
        bot = i10 + ax * (i11 - i10)
        return top + ay * (bot - top), bot - top, (1 - ay) * (i01 - i00) + ay * (i11 - i10)


def residuals(d: PatchData, T: np.ndarray, ab: np.ndarray, rho: np.ndarray, jac: bool = False):
    """Photometric residuals ``(M, S)`` (DSO eq. 4), validity mask and optional Jacobians.

    Returns:
        ``(r, valid, counted)`` or, with ``jac``, ``(r, valid, counted, Jc, Jp)``: ``valid``
        ``(M, S)`` marks residuals inside the image margin and in front (weight > 0),
        ``counted`` those entering the cost (in front, host pixel inside); ``Jc`` ``Jc`` ``(M, S, 16)`` holds
        the derivatives w.r.t. ``[host (ρ, φ, a, b), target (ρ, φ, a, b)]`` and ``Jp`` ``(M, S)``
        the derivative w.r.t. the point's inverse depth.
    """
    h, t, p = d.h, d.t, d.p
    Rh, Rt = T[h, :3, :3], T[t, :3, :3]
    R = np.einsum("mij,mkj->mik", Rt, Rh)  # R_t R_hᵀ
    tr = T[t, :3, 3] - np.einsum("mij,mj->mi", R, T[h, :3, 3])
    x, y, ir = d.xq[p], d.yq[p], 1.0 / rho[p][:, None]
    Xh = [x * ir, y * ir, np.broadcast_to(ir, x.shape)]  # host-frame point π⁻¹(p + δ, ρ)
    X = [R[:, i, 0, None] * Xh[0] + R[:, i, 1, None] * Xh[1] + R[:, i, 2, None] * Xh[2]
         + tr[:, i, None] for i in range(3)]
    front = X[2] > 1e-6
    iz = 1.0 / np.where(front, X[2], 1.0)
    un, vn = X[0] * iz, X[1] * iz
    u, v = d.fx * un + d.cx, d.fy * vn + d.cy
    valid = front & d.host_ok & in_image_uv(u, v, d.W, d.H, d.margin)
    It, Iv, Iu = d.sample(t[:, None], u, v)
    e = np.exp(ab[t, 0] - ab[h, 0])[:, None]
    Ihb = d.Ih[p] - ab[h, 1][:, None]
    # residuals beyond the margin keep their (clamped-sample) value so the cost stays continuous,
    # but get weight 0; residuals behind the camera or off the host image are not evaluated
    counted = front & d.host_ok
    r = np.where(counted, It - ab[t, 1][:, None] - e * Ihb, 0.0)  # DSO eq. 4
    if not jac:
        return r, valid, counted
    gx, gy = Iu * d.fx * valid, Iv * d.fy * valid  # ∂I/∂(un, vn)
    dX = [gx * iz, gy * iz, -(gx * un + gy * vn) * iz]  # ∂r/∂X_t
    G = [dX[0] * R[:, 0, i, None] + dX[1] * R[:, 1, i, None] + dX[2] * R[:, 2, i, None]
         for i in range(3)]  # ∂r/∂X_h = ∂r/∂X_t · R_th
    Jc = np.empty(x.shape + (16,))
    # host: T_h ← exp(ξ) T_h ⇒ dX_h = −[I | −[X_h]×] ξ ⇒ [−G, G × X_h]
    Jc[..., 0], Jc[..., 1], Jc[..., 2] = -G[0], -G[1], -G[2]
    Jc[..., 3] = G[1] * Xh[2] - G[2] * Xh[1]
    Jc[..., 4] = G[2] * Xh[0] - G[0] * Xh[2]
    Jc[..., 5] = G[0] * Xh[1] - G[1] * Xh[0]
    Jc[..., 6] = e * Ihb * valid
    Jc[..., 7] = e * valid
    # target: T_t ← exp(ξ) T_t ⇒ dX_t = [I | −[X_t]×] ξ ⇒ [∂r/∂X, X × ∂r/∂X]
    Jc[..., 8], Jc[..., 9], Jc[..., 10] = dX
    Jc[..., 11] = X[1] * dX[2] - X[2] * dX[1]
    Jc[..., 12] = X[2] * dX[0] - X[0] * dX[2]
    Jc[..., 13] = X[0] * dX[1] - X[1] * dX[0]
    Jc[..., 14] = -Jc[..., 6]
    Jc[..., 15] = -1.0 * valid
    Jp = -(G[0] * x + G[1] * y + G[2]) * ir**2  # ∂X_h/∂ρ = −(x, y, 1)/ρ²
    return r, valid, counted, Jc, Jp


def huber_cost(r: np.ndarray, counted: np.ndarray, host_ok: np.ndarray, delta: float) -> float:
    """Total Huber cost; a residual behind the camera costs the constant ``δ²/2``."""
    a = np.abs(r)
    c = np.where(a < delta, 0.5 * r * r, delta * (a - 0.5 * delta))
    return float(np.sum(np.where(counted, c, 0.5 * delta * delta * host_ok)))

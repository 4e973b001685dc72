"""Global photometric bundle adjustment (DSO-style direct BA over keyframes).

Unknowns: per free keyframe an SE(3) left increment ``(ρ, φ)`` on ``T_cw`` plus the affine
brightness ``(a, b)`` (8 values); per point its inverse depth in the host keyframe. One
residual per (point, target keyframe) pair and per pixel of a ``patch × patch`` pattern around
the host pixel, all sharing the point's inverse depth (fronto-parallel patch), with DSO's affine
brightness model (Engel et al. 2018, "Direct Sparse Odometry", eq. 4):

    r = (I_t(π(T_t T_h⁻¹ π⁻¹(p + δ, ρ))) − b_t) − exp(a_t − a_h) · (I_h(p + δ) − b_h)

robustified with the Huber loss through IRLS weights (Alismail et al. 2016, "Photometric
Bundle Adjustment for Vision-Based SLAM"). Solver: Levenberg–Marquardt with the Schur
complement on the diagonal inverse-depth block (Triggs et al. 2000, §6); the reduced camera
system (8 unknowns per free keyframe) is solved densely. Gauge: keyframe 0 fixed; the
monocular scale is held by the prior ``w_s (‖c_1 − c_0‖ − s_0)²`` (paper §III-C runs this BA
after culling). Conventions follow :mod:`mutualslam_cli.vo.local_ba`.

Image derivatives are those of the bilinear interpolant itself (not interpolated central-
difference gradient images): the Jacobians are then exact for the cost being minimised, which
the LM acceptance test compares. Residuals beyond the 2-px margin get weight 0 but keep their
(clamped) value in the cost, so the cost is continuous and a step is never rejected only
because one patch crossed the margin.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.vo.local_ba import left_update

log = logging.getLogger(__name__)
NP = 8  # unknowns per keyframe: (ρx, ρy, ρz, φx, φy, φz, a, b)


@dataclass
class PhotoBAProblem:
    """Inputs of one global photometric BA.

    Attributes:
        images: ``(K, H, W)`` float grey images in [0, 1], undistorted pinhole.
        K: ``(3, 3)`` intrinsics (``fy`` may be negative).
        T_cw: ``(K, 4, 4)`` initial world-to-camera poses.
        affine: ``(K, 2)`` initial brightness parameters ``(a, b)``.
        host: ``(P,)`` host keyframe of each point.
        pixel: ``(P, 2)`` host pixel ``(u, v)``.
        inv_depth: ``(P,)`` inverse z-depth in the host (> 0).
        obs_pt, obs_kf: ``(M,)`` point and target keyframe of each (point, target) pair.
        free: ``(K,)`` bool, keyframes whose pose and affine are optimised (``None``: all but 0).
    """

    images: np.ndarray
    K: np.ndarray
    T_cw: np.ndarray
    affine: np.ndarray
    host: np.ndarray
    pixel: np.ndarray
    inv_depth: np.ndarray
    obs_pt: np.ndarray
    obs_kf: np.ndarray
    free: np.ndarray | None = None


@dataclass
class PhotoBAResult:
    """Output of :func:`solve`: ``T_cw`` ``(K, 4, 4)``, ``affine`` ``(K, 2)``,
    ``inv_depth`` ``(P,)`` and ``stats`` (cost0, cost, costs, iterations, accepted, seconds)."""

    T_cw: np.ndarray
    affine: np.ndarray
    inv_depth: np.ndarray
    stats: dict


def _shape(x: np.ndarray, want: tuple, name: str) -> None:
    if x.shape != want:
        raise ShapeError(f"PhotoBAProblem.{name}: expected shape {want}, got {x.shape}")


def validate(prob: PhotoBAProblem, max_targets: int = 5) -> np.ndarray:
    """Check shapes and values; returns the ``(K,)`` free mask.

    Raises:
        ShapeError: an array has the wrong shape.
        ConfigError: non-finite values, bad indices, a target equal to its host, a duplicate
            (point, target) pair, more than ``max_targets`` targets, or keyframe 0 free.
    """
    im = np.asarray(prob.images)
    if im.ndim != 3:
        raise ShapeError(f"PhotoBAProblem.images: expected shape (K, H, W), got {im.shape}")
    nk, P, M = im.shape[0], len(np.atleast_1d(prob.host)), len(np.atleast_1d(prob.obs_pt))
    _shape(np.asarray(prob.K), (3, 3), "K")
    _shape(np.asarray(prob.T_cw), (nk, 4, 4), "T_cw")
    _shape(np.asarray(prob.affine), (nk, 2), "affine")
    _shape(np.asarray(prob.host), (P,), "host")
    _shape(np.asarray(prob.pixel), (P, 2), "pixel")
    _shape(np.asarray(prob.inv_depth), (P,), "inv_depth")
    _shape(np.asarray(prob.obs_pt), (M,), "obs_pt")
    _shape(np.asarray(prob.obs_kf), (M,), "obs_kf")
    for name in ("images", "K", "T_cw", "affine", "pixel", "inv_depth"):
        if not np.all(np.isfinite(getattr(prob, name))):
            raise ConfigError(f"PhotoBAProblem.{name}: contains NaN or inf; expected finite values")
    if np.any(np.asarray(prob.inv_depth) <= 0):
        raise ConfigError("PhotoBAProblem.inv_depth: expected inverse depths > 0")
    for name, arr, n in (("host", prob.host, nk), ("obs_kf", prob.obs_kf, nk), ("obs_pt", prob.obs_pt, P)):
        a = np.asarray(arr)
        if a.dtype.kind not in "iu" or (len(a) and (a.min() < 0 or a.max() >= n)):
            raise ConfigError(f"PhotoBAProblem.{name}: expected integer indices in [0, {n})")
    host, obs_pt, obs_kf = np.asarray(prob.host), np.asarray(prob.obs_pt), np.asarray(prob.obs_kf)
    bad = np.flatnonzero(obs_kf == host[obs_pt])
    if len(bad):
        raise ConfigError(f"PhotoBAProblem.obs_kf[{bad[0]}]: target keyframe equals the host of "
                          f"point {obs_pt[bad[0]]}; targets must differ from the host")
    if len(np.unique(obs_pt.astype(np.int64) * nk + obs_kf)) != M:
        raise ConfigError("PhotoBAProblem.obs_pt/obs_kf: duplicate (point, target) pair")
    cnt = np.bincount(obs_pt, minlength=P)
    if M and cnt.max() > max_targets:
        raise ConfigError(f"PhotoBAProblem.obs_pt: point {int(cnt.argmax())} has {cnt.max()} "
                          f"targets; expected at most max_targets={max_targets}")
    free = np.arange(nk) > 0 if prob.free is None else np.asarray(prob.free, bool)
    _shape(free, (nk,), "free")
    if free[0]:
        raise ConfigError("PhotoBAProblem.free[0]: keyframe 0 must be fixed (gauge)")
    return free


class _Structure:
    """Static sparsity of the normal equations. Observations are sorted by (host, target)
    keyframe pair, so each pair's 8×8 blocks come from one contiguous run of residuals."""

    def __init__(self, host: np.ndarray, p: np.ndarray, t: np.ndarray, nk: int):
        h = host[p]
        self.nk, self.host, self.p, self.h, self.t = nk, host, p, h, t
        key = h * nk + t
        self.starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else key[:0]
        self.ends = np.r_[self.starts[1:], len(key)]
        self.ph, self.pt = h[self.starts], t[self.starts]

    def scatter_vec(self, kf: np.ndarray, V: np.ndarray) -> np.ndarray:
        """Sum rows of ``V`` ``(N, 8)`` into the ``(8K,)`` vector at keyframes ``kf``."""
        idx = (kf[:, None] * NP + np.arange(NP)).ravel()
        return np.bincount(idx, V.ravel(), minlength=self.nk * NP)

    def camera_system(self, Jc: np.ndarray, Jw: np.ndarray, bblk: np.ndarray):
        """Dense ``H_cc`` ``(8K, 8K)`` and ``b_c`` ``(8K,)``: every residual of one (host,
        target) pair adds to the same 16×16 block, so each pair is one small matrix product
        (a loop over keyframe pairs, not over points)."""
        nk, S = self.nk, Jc.shape[1]
        J2, W2 = Jc.reshape(-1, 2 * NP), Jw.reshape(-1, 2 * NP)
        B = np.empty((len(self.starts), 2 * NP, 2 * NP))
        for u, (a, b) in enumerate(zip(self.starts * S, self.ends * S)):
            B[u] = W2[a:b].T @ J2[a:b]
        kf = np.r_[self.ph, self.pt]
        Dv = np.concatenate([B[:, :NP, :NP], B[:, NP:, NP:]]).reshape(len(kf), -1)
        D = np.bincount((kf[:, None] * NP * NP + np.arange(NP * NP)).ravel(), Dv.ravel(),
                        minlength=nk * NP * NP).reshape(nk, NP, NP)
        H = np.zeros((nk, NP, nk, NP))
        H[self.ph, :, self.pt, :] = B[:, :NP, NP:]  # (h, t) cross blocks, unique per pair
        H = H.reshape(nk * NP, nk * NP)
        H = H + H.T
        H4 = H.reshape(nk, NP, nk, NP)
        H4[np.arange(nk), :, np.arange(nk), :] += D
        b = self.scatter_vec(np.r_[self.h, self.t], np.concatenate([bblk[:, :NP], bblk[:, NP:]]))
        return H, b

    def _chunks(self) -> list:
        """Points grouped by host keyframe, with the keyframes their observations touch."""
        out, P = [], len(self.host)
        ps = np.argsort(self.host, kind="stable")
        pb = np.searchsorted(self.host[ps], np.arange(self.nk + 1))
        ob = np.searchsorted(self.h, np.arange(self.nk + 1))  # observations sorted by host
        for k in range(self.nk):
            pts, obs = ps[pb[k]:pb[k + 1]], np.arange(ob[k], ob[k + 1])
            if len(pts) == 0:
                continue
            touched = np.unique(np.r_[k, self.t[obs]])
            out.append((pts, obs, touched, int(np.searchsorted(touched, k)),
                        np.searchsorted(touched, self.t[obs]), np.searchsorted(pts, self.p[obs])))
        assert sum(len(c[0]) for c in out) == P
        return out

    def schur(self, A: np.ndarray, Ct: np.ndarray, inv_hd: np.ndarray, frow: np.ndarray) -> np.ndarray:
        """``H_cp H_pp⁻¹ H_pc`` on the free keyframes ``(8F, 8F)``.

        Each point's column of ``H_cp`` has at most ``1 + max_targets`` non-zero 8-blocks (host
        slot ``A`` ``(P, 8)``, target slots ``Ct`` ``(M, 8)``). Per host keyframe, the columns
        scaled by ``H_pp^{-1/2}`` form a dense ``Z`` over the few keyframes they touch and
        ``Z Zᵀ`` is added to those rows/columns (a loop over keyframes, BLAS inside).
        ``frow`` ``(K,)`` maps a keyframe to its free index, ``F`` if fixed.
        """
        if not hasattr(self, "chunks"):
            self.chunks = self._chunks()
        F = int(frow.max(initial=0))
        sq = np.sqrt(inv_hd)
        S = np.zeros((F * NP, F * NP))
        for pts, obs, touched, lh, lt, lc in self.chunks:
            Z = np.zeros((len(touched), NP, len(pts)))
            Z[lh] = (A[pts] * sq[pts][:, None]).T
            Z[lt, :, lc] = Ct[obs] * sq[self.p[obs]][:, None]
            fr = frow[touched]
            keep = fr < F
            Zf = Z[keep].reshape(-1, len(pts))
            rows = (fr[keep][:, None] * NP + np.arange(NP)).ravel()
            S[np.ix_(rows, rows)] += Zf @ Zf.T
        return S


class _Data:
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
        hv = (q[..., 0] >= 0) & (q[..., 0] <= self.W - 1) & (q[..., 1] >= 0) & (q[..., 1] <= self.H - 1)
        kf = np.broadcast_to(np.asarray(prob.host)[:, None], hv.shape)
        self.Ih = self.sample(kf, q[..., 0], q[..., 1])[0].astype(float)  # (P, S), constant
        p, t = np.asarray(prob.obs_pt), np.asarray(prob.obs_kf)
        order = np.argsort(np.asarray(prob.host)[p] * self.nk + t, kind="stable")  # by pair
        self.p, self.t = p[order], t[order]
        self.h = np.asarray(prob.host)[self.p]
        self.host_ok = hv[self.p]
        self.st = _Structure(np.asarray(prob.host), self.p, self.t, self.nk)

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


def residuals(d: _Data, T: np.ndarray, ab: np.ndarray, rho: np.ndarray, jac: bool = False):
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
    m = d.margin
    valid = front & d.host_ok & (u >= m) & (u <= d.W - 1 - m) & (v >= m) & (v <= d.H - 1 - m)
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


class _Normal:
    """Gauss–Newton normal equations in Schur form (point block diagonal)."""

    def __init__(self, st: _Structure, Hcc, bc, A, Ct, Hpp, bp):
        self.st, self.Hcc, self.bc, self.A, self.Ct, self.Hpp, self.bp = st, Hcc, bc, A, Ct, Hpp, bp

    def step(self, lam: float, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LM step ``(dc (8K,), dp (P,))`` with damping ``λ·diag(H)``; ``cols`` are the
        optimised columns of ``dc`` (sorted, keyframe-major)."""
        st, A, Ct = self.st, self.A, self.Ct
        fk = np.unique(cols // NP)
        frow = np.full(st.nk, len(fk))
        frow[fk] = np.arange(len(fk))
        loc = frow[cols // NP] * NP + cols % NP  # column positions inside the free block
        Hd = self.Hpp * (1 + lam) + 1e-12
        Ssch = st.schur(A, Ct, 1.0 / Hd, frow)[np.ix_(loc, loc)]
        Sf = self.Hcc[np.ix_(cols, cols)] - Ssch  # reduced camera system (Schur complement)
        q = self.bp / Hd
        g = self.bc - st.scatter_vec(np.r_[st.host, st.t],
                                     np.concatenate([A * q[:, None], Ct * q[st.p][:, None]]))
        hdiag = np.diag(self.Hcc)[cols]
        Sf[np.diag_indices_from(Sf)] += lam * np.maximum(hdiag, 1e-6) + 1e-9
        dc = np.zeros(len(self.bc))
        dc[cols] = -np.linalg.solve(Sf, g[cols])
        dck = dc.reshape(-1, NP)
        Hcp_dc = np.einsum("pi,pi->p", A, dck[st.host]) + np.bincount(
            st.p, np.einsum("mi,mi->m", Ct, dck[st.t]), minlength=len(Hd))
        return dc, -(self.bp + Hcp_dc) / Hd  # back-substitution


def normal_equations(d: _Data, T: np.ndarray, ab: np.ndarray, rho: np.ndarray,
                     huber_delta: float, res: tuple | None = None) -> _Normal:
    """IRLS-weighted normal equations at the current state (Huber weights); ``res`` may pass
    the output of ``residuals(..., jac=True)`` at this state."""
    P = len(rho)
    r, valid, _, Jc, Jp = residuals(d, T, ab, rho, jac=True) if res is None else res
    a = np.abs(r)
    w = np.where(a < huber_delta, 1.0, huber_delta / np.maximum(a, 1e-12)) * valid  # IRLS
    Jw = Jc * w[..., None]
    bblk = np.einsum("msi,ms->mi", Jw, r)
    hcp = np.einsum("msi,ms->mi", Jw, Jp)  # (M, 16) column of H_cp per observation
    A = np.stack([np.bincount(d.p, hcp[:, i], minlength=P) for i in range(NP)], 1)  # host slots
    Hpp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, Jp), minlength=P)
    bp = np.bincount(d.p, np.einsum("ms,ms->m", w * Jp, r), minlength=P)
    Hcc, bc = d.st.camera_system(Jc, Jw, bblk)
    return _Normal(d.st, Hcc, bc, A, hcp[:, NP:], Hpp, bp)


def _huber(r: np.ndarray, counted: np.ndarray, host_ok: np.ndarray, delta: float) -> float:
    """Total Huber cost; a residual behind the camera costs the constant ``δ²/2``."""
    a = np.abs(r)
    c = np.where(a < delta, 0.5 * r * r, delta * (a - 0.5 * delta))
    return float(np.sum(np.where(counted, c, 0.5 * delta * delta * host_ok)))


def _centre(T: np.ndarray) -> np.ndarray:
    return -T[:3, :3].T @ T[:3, 3]


def _apply(T, ab, rho, dc, dp, fidx):
    ab = ab.copy()
    d = dc.reshape(-1, NP)[fidx]
    T = left_update(T, fidx, d[:, :6])
    ab[fidx] += d[:, 6:]
    return T, ab, np.maximum(rho + dp, 1e-6)


def _solve_level(d: _Data, T, ab, rho, fidx, cols, s0, iterations, huber_delta, scale_weight,
                 lambda0, max_tries, callback, it_offset=0):
    """LM iterations at one resolution; returns ``(T, ab, rho, costs, iterations, accepted)``.
    ``s0`` is the scale-prior baseline (from the input state, shared by all levels)."""
    nk = d.nk
    k1 = int(fidx[0]) if len(fidx) else -1  # scale prior on the first free keyframe
    c0 = _centre(T[0])
    ws = scale_weight / s0**2 if s0 > 1e-9 else 0.0

    def total(T_, res_):
        e = np.linalg.norm(_centre(T_[k1]) - c0) - s0 if ws else 0.0
        return _huber(res_[0], res_[2], d.host_ok, huber_delta) + ws * e * e

    res = residuals(d, T, ab, rho, jac=iterations > 0)  # trial states keep Jacobians for reuse
    cost = total(T, res)
    costs, accepted, lam, it = [cost], 0, lambda0, 0
    for it in range(1, iterations + 1):
        ne = normal_equations(d, T, ab, rho, huber_delta, res)
        if ws:  # scale prior: ∂c_k/∂ρ_k = −R_kᵀ under the left increment, ∂c_k/∂φ_k = 0
            c1 = _centre(T[k1])
            n = (c1 - c0) / np.linalg.norm(c1 - c0)
            Js = np.zeros(nk * NP)
            Js[k1 * NP:k1 * NP + 3] = -T[k1, :3, :3] @ n
            es = np.linalg.norm(c1 - c0) - s0
            ne.Hcc += 2 * ws * np.outer(Js, Js)
            ne.bc += 2 * ws * Js * es
        ok = False
        for _ in range(max_tries):
            try:
                dc, dp = ne.step(lam, cols)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T2, ab2, rho2 = _apply(T, ab, rho, dc, dp, fidx)
            res2 = residuals(d, T2, ab2, rho2, jac=True)
            c_new = total(T2, res2)
            if c_new < cost:
                T, ab, rho, cost, res = T2, ab2, rho2, c_new, res2
                lam, ok = max(lam / 10, 1e-7), True
                accepted += 1
                break
            lam *= 10
        costs.append(cost)
        log.debug("photometric BA it %d cost %.6g lambda %.1e accepted %s", it, cost, lam, ok)
        if callback is not None:
            callback(it_offset + it, cost)
        if not ok:
            break
    return T, ab, rho, costs, it, accepted


def solve(prob: PhotoBAProblem, iterations: int = 10, huber_delta: float = 0.1, patch: int = 3,
          max_targets: int = 5, scale_weight: float = 1e4, margin: float = 2.0,
          lambda0: float = 1e-3, max_tries: int = 4, affine: bool = True,
          callback: Callable[[int, float], None] | None = None, levels: int = 1,
          coarse_iterations: int = 5) -> PhotoBAResult:
    """Levenberg–Marquardt photometric BA with a Schur complement on the inverse depths,
    optionally coarse-to-fine over an image pyramid (:mod:`mutualslam_cli.ba.pyramid`).

    Args:
        prob: the problem (see :class:`PhotoBAProblem`).
        iterations: LM iterations at full resolution (each tries at most ``max_tries`` dampings).
        huber_delta: Huber threshold in intensity units.
        patch: side of the square residual pattern, pixels of each level.
        max_targets: largest allowed number of targets per point.
        scale_weight: ``w_s · s_0²`` of the scale prior ``w_s (‖c_1 − c_0‖ − s_0)²``, i.e. the
            cost of a relative scale error of 1 (``s_0`` from the input, shared by all levels).
        margin: pixels (of each level) at the border where a projection is invalid.
        lambda0: initial LM damping (reset at each level).
        max_tries: damping increases per iteration before giving up (ends that level).
        affine: optimise the affine brightness ``(a, b)`` (else keep it fixed).
        callback: ``callback(iteration, cost)`` after each iteration (iterations count across
            levels; the cost is the current level's).
        levels: pyramid levels. 1 (default): full resolution only, bit-identical to the solver
            before the pyramid existed. ``L > 1``: ``coarse_iterations`` at each level
            ``L−1 … 1`` (resolution / 2^level), then ``iterations`` at full resolution. An
            iteration costs about the same at every level (it scales with points, not pixels).
        coarse_iterations: LM iterations at each coarse level.

    Returns:
        :class:`PhotoBAResult`. Within each level the robust cost never increases across
        accepted steps; costs of different levels are not comparable. ``stats``: ``cost0`` and
        ``cost`` full-resolution costs of the input and final states (``cost <= cost0``),
        ``costs`` the full-resolution stage's sequence, ``levels`` per level (coarsest first)
        ``{level, shape, costs, iterations, accepted}``, ``iterations``/``accepted`` totals.
    """
    from mutualslam_cli.ba import pyramid  # local import: pyramid refers back to this module

    t0 = time.perf_counter()
    free = validate(prob, max_targets)
    if patch < 1 or patch % 2 == 0:
        raise ConfigError(f"solve: patch must be a positive odd integer, got {patch}")
    if coarse_iterations < 0:
        raise ConfigError(f"solve: coarse_iterations must be >= 0, got {coarse_iterations}")
    stack = pyramid.build(np.asarray(prob.images), levels)
    state = tuple(np.asarray(x, float).copy() for x in (prob.T_cw, prob.affine, prob.inv_depth))
    fidx = np.flatnonzero(free)
    cols = (fidx[:, None] * NP + np.arange(NP if affine else 6)).ravel()
    k1 = int(fidx[0]) if len(fidx) else -1
    T = state[0]
    s0 = float(np.linalg.norm(_centre(T[k1]) - _centre(T[0]))) if k1 > 0 else 0.0

    def run(d, T_, ab_, rho_, n, offset):
        return _solve_level(d, T_, ab_, rho_, fidx, cols, s0, n, huber_delta, scale_weight,
                            lambda0, max_tries, callback, offset)

    def make_data(p):
        return _Data(p, patch, margin)

    per_level, n_it, n_acc, cost0 = [], 0, 0, None
    if levels > 1:
        state, per_level, n_it, n_acc, d, cost0 = pyramid.coarse_to_fine(
            prob, stack, state, coarse_iterations, make_data, run)
    else:
        d = make_data(prob)
    T, ab, rho, costs, it, acc = run(d, *state, iterations, n_it)
    costs = [float(c) for c in costs]
    per_level.append({"level": 0, "shape": stack[0].shape[1:], "costs": costs,
                      "iterations": it, "accepted": acc})
    stats = {"cost0": float(costs[0] if cost0 is None else cost0), "cost": costs[-1],
             "costs": costs, "iterations": n_it + it, "accepted": n_acc + acc,
             "levels": per_level, "seconds": time.perf_counter() - t0}
    return PhotoBAResult(T, ab, rho, stats)

"""SVO's probabilistic inverse-depth filter, vectorised over all seeds.

Each seed models the inverse depth ``ρ`` of one feature in its host keyframe with the
parametric approximation of Vogiatzis & Hernández (2011, "Video-based, real-time multi-view
stereo"): a Gaussian ``N(ρ | μ, σ²)`` for good measurements times a Beta ``B(π | a, b)`` on
the inlier probability, against a uniform outlier density on ``[0, ρ_max]``. SVO (Forster et
al. 2014/2017) fuses one triangulated depth per frame; here the measurement comes from the
KLT track of the seed (triangulation of the host ray against the current bearing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONVERGENCE_RATIO = 200.0
"""A seed converges when σ < ρ_range / CONVERGENCE_RATIO (SVO's ``seed_convergence_sigma2_thresh``)."""


@dataclass
class SeedInit:
    """Prior of new seeds in a keyframe: mean and minimum scene depth (map units)."""

    depth_mean: float
    depth_min: float


def new_seeds(n: int, prior: SeedInit) -> dict[str, np.ndarray]:
    """Arrays ``a, b, mu, sigma2, z_range`` (each ``(n,)``) of fresh seeds (SVO's Seed ctor).

    ``a = b = 10``, ``μ = 1/d_mean``, ``ρ_range = 1/d_min``, ``σ² = ρ_range²/36``.
    """
    z_range = 1.0 / max(prior.depth_min, 1e-3)
    return {
        "a": np.full(n, 10.0),
        "b": np.full(n, 10.0),
        "mu": np.full(n, 1.0 / max(prior.depth_mean, 1e-3)),
        "sigma2": np.full(n, z_range * z_range / 36.0),
        "z_range": np.full(n, z_range),
    }


def triangulate_host_depth(f_h: np.ndarray, f_c: np.ndarray, T_hc: np.ndarray) -> np.ndarray:
    """Depth along the host bearing from two rays (midpoint least squares), vectorised.

    Solves ``z_h f_h ≈ R_hc z_c f_c + t_hc`` for ``(z_h, z_c)``.

    Args:
        f_h: ``(N, 3)`` unit bearings in the host camera.
        f_c: ``(N, 3)`` unit bearings in the current camera.
        T_hc: ``(N, 4, 4)`` current-camera-to-host transforms.

    Returns:
        ``(N,)`` depth ``z_h`` along ``f_h`` (distance along the unit bearing); NaN if degenerate.
    """
    rf = np.einsum("nij,nj->ni", T_hc[:, :3, :3], f_c)
    t = T_hc[:, :3, 3]
    a12 = -np.sum(f_h * rf, axis=1)
    b1 = np.sum(f_h * t, axis=1)
    b2 = -np.sum(rf * t, axis=1)
    det = 1.0 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (b1 - a12 * b2) / det
    return np.where(det > 1e-10, z, np.nan)


def compute_tau(T_hc: np.ndarray, f_h: np.ndarray, z: np.ndarray, px_error_angle: float) -> np.ndarray:
    """Depth uncertainty of one triangulation from a one-pixel bearing error (SVO ``computeTau``).

    With ``t`` the current camera centre in the host frame, ``a = f z − t``,
    ``α = ∠(f, t)``, ``β = ∠(a, −t)``, ``β⁺ = β + δ_px``, ``γ⁺ = π − α − β⁺``:
    ``z⁺ = ‖t‖ sin β⁺ / sin γ⁺`` and ``τ = z⁺ − z``.

    Returns:
        ``(N,)`` τ in depth units (NaN where undefined).
    """
    t = T_hc[:, :3, 3]
    a = f_h * z[:, None] - t
    tn = np.linalg.norm(t, axis=1)
    an = np.linalg.norm(a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.arccos(np.clip(np.sum(f_h * t, 1) / tn, -1, 1))
        beta = np.arccos(np.clip(np.sum(a * -t, 1) / (tn * an), -1, 1))
        beta_p = beta + px_error_angle
        gamma_p = np.pi - alpha - beta_p
        z_p = tn * np.sin(beta_p) / np.sin(gamma_p)
    return z_p - z


def update_seeds(s: dict[str, np.ndarray], idx: np.ndarray, x: np.ndarray, tau2: np.ndarray) -> None:
    """Fuse inverse-depth measurements ``x`` (variance ``tau2``) into seeds ``idx`` in place.

    Vogiatzis & Hernández (2011) Eq. 19–26, in SVO's ``updateSeed`` form: with
    ``s² = (1/σ² + 1/τ²)⁻¹``, ``m = s²(μ/σ² + x/τ²)``,
    ``C1 ∝ a/(a+b)·N(x | μ, σ² + τ²)``, ``C2 ∝ b/(a+b)/ρ_range``,
    ``μ' = C1 m + C2 μ``, ``σ'² = C1(s² + m²) + C2(σ² + μ²) − μ'²`` and the Beta
    parameters from matching the first two moments of the inlier probability.
    """
    if len(idx) == 0:
        return
    a, b, mu, sig2, zr = (s[k][idx] for k in ("a", "b", "mu", "sigma2", "z_range"))
    norm_scale = np.sqrt(sig2 + tau2)
    s2 = 1.0 / (1.0 / sig2 + 1.0 / tau2)
    m = s2 * (mu / sig2 + x / tau2)
    c1 = a / (a + b) * np.exp(-0.5 * ((x - mu) / norm_scale) ** 2) / (norm_scale * np.sqrt(2 * np.pi))
    c2 = b / (a + b) / zr
    nc = c1 + c2
    c1, c2 = c1 / nc, c2 / nc
    f = c1 * (a + 1) / (a + b + 1) + c2 * a / (a + b + 1)
    e = (c1 * (a + 1) * (a + 2) / ((a + b + 1) * (a + b + 2))
         + c2 * a * (a + 1) / ((a + b + 1) * (a + b + 2)))
    mu_new = c1 * m + c2 * mu
    sig2_new = c1 * (s2 + m * m) + c2 * (sig2 + mu * mu) - mu_new * mu_new
    a_new = (e - f) / (f - e / f)
    b_new = a_new * (1 - f) / f
    good = np.isfinite(mu_new) & np.isfinite(sig2_new) & (sig2_new > 0) & np.isfinite(a_new)
    for k, v in (("a", a_new), ("b", b_new), ("mu", mu_new), ("sigma2", sig2_new)):
        cur = s[k][idx]
        s[k][idx] = np.where(good, v, cur)


def measure(
    f_h: np.ndarray, f_c: np.ndarray, T_hc: np.ndarray, px_error_angle: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse-depth measurements and their variances from host/current bearings.

    Returns:
        ``x = 1/z`` ``(N,)``, ``τ²`` in inverse depth ``(N,)`` (SVO:
        ``τ_ρ = ½ (1/(z−τ) − 1/(z+τ))``) and the ``(N,)`` bool mask of usable measurements.
    """
    z = triangulate_host_depth(f_h, f_c, T_hc)
    ok = np.isfinite(z) & (z > 1e-6)
    zz = np.where(ok, z, 1.0)
    tau = compute_tau(T_hc, f_h, zz, px_error_angle)
    ok &= np.isfinite(tau) & (tau > 0)
    tau = np.where(ok, tau, 1.0)
    tau_inv = 0.5 * (1.0 / np.maximum(1e-7, zz - tau) - 1.0 / (zz + tau))
    return 1.0 / zz, tau_inv * tau_inv, ok & (tau_inv > 0)


def converged(s: dict[str, np.ndarray]) -> np.ndarray:
    """``(N,)`` bool: σ below ``ρ_range / CONVERGENCE_RATIO`` and inlier ratio above one half."""
    return (np.sqrt(s["sigma2"]) < s["z_range"] / CONVERGENCE_RATIO) & (s["a"] / (s["a"] + s["b"]) > 0.5)

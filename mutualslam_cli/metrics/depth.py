"""Depth accuracy: percent correct depth (PCD), scale-invariant error e_si, abs_rel (DESIGN §7).

Conventions: depth in metres (or map units), ``(H, W)`` maps or ``(N,)`` point arrays;
numpy arrays or torch tensors (converted to float64 numpy; leading size-1 dimensions of
maps, e.g. ``(1, 1, H, W)``, are squeezed). A pixel is *valid* when its GT depth is finite,
``> 0`` and ``<= max_depth`` **and** the prediction there is finite and ``> 0``. Statistics
over an empty set are ``float('nan')``, never 0.

Scaling protocols (monocular depth has no metric scale), named in every output:

- ``median``: ``s = median(D_gt) / median(D)`` per frame (Zhou et al. 2017 / Monodepth2
  ``evaluate_depth.py``; the paper's Table 2).
- ``lsq``: ``s = Σ D·D_gt / Σ D²``, the least-squares fit of ``s·D`` to ``D_gt`` per frame
  ("scaled to GT", the paper's Tables 1 and 3).
- ``none``: ``s = 1``.
- ``seq_lsq``: one least-squares scale for the whole sequence, ``s = Σ_frames Σ D·D_gt / Σ_frames Σ D²``
  ("scaled to GT" read as one scale per sequence). It needs every frame before any frame can be
  scored, so each frame keeps a sketch of its log depth ratios (:func:`ratio_sketch`, 2,049
  quantiles) and is scored from it once the scale is known (:func:`pcd_from_sketch`): at most
  two quantile steps (≤ 0.1 percentage points) from the exact count.

PCD is averaged over frames (each frame's percentage weighs the same, as Monodepth2 averages its
metrics); *pooled* over pixels it is the ``n_valid``-weighted mean of the frames' percentages
(:func:`pooled_mean`).

Relative inverse depth (MiDaS-style outputs, known up to scale *and shift*) is first turned into
depth by :func:`align_inverse_depth` (least-squares scale and shift in inverse depth per frame),
then scored like any depth map.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal, TypeAlias

import cv2
import numpy as np
import numpy.typing as npt

from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.metrics.ratios import count_within, median, ratio_sketch
from mutualslam_cli.types import check_shape

SCALINGS = ("lsq", "median", "none")
"""Quantiles of ``log(D / D_gt)`` a frame keeps for sequence-level scaling (:func:`ratio_sketch`)."""
PCD_THRESHOLD = 0.1
"""Relative error below which a pixel counts as correct (paper §IV-B, after Luo et al.)."""
MAX_DEPTH = 10.0
"""GT depth above this (metres) is not evaluated (indoor sensors; DESIGN §7)."""

Scaling = Literal["lsq", "median", "none"]

DepthLike: TypeAlias = npt.ArrayLike
"""Depths as given: a numpy array, a torch tensor (it has ``__array__``; detached and moved to the CPU
here), a pandas column, nested lists or a number."""


def _as_array(x: DepthLike) -> np.ndarray:
    """numpy or torch → float64 numpy (detached, on CPU)."""
    if hasattr(x, "detach"):  # torch.Tensor, without importing torch here
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _as_map(x: DepthLike, name: str) -> np.ndarray:
    """float64 ``(H, W)`` map; leading size-1 dimensions are dropped."""
    a = _as_array(x)
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    check_shape(a, ["H", "W"], name)
    return a


def _check_scaling(scaling: str) -> None:
    if scaling not in SCALINGS:
        raise ConfigError(f"unknown depth scaling {scaling!r}; valid: {', '.join(SCALINGS)}")


def valid_mask(gt: DepthLike, max_depth: float = MAX_DEPTH, pred: DepthLike | None = None) -> np.ndarray:
    """Pixels (or points) where the metrics are evaluated.

    Args:
        gt: ``(H, W)`` or ``(N,)`` GT depth; 0, negative or non-finite means missing.
        max_depth: GT depth above this is ignored (metres).
        pred: optional prediction of the same shape; it must also be finite and ``> 0``.

    Returns:
        bool array of ``gt``'s shape.
    """
    g = _as_array(gt)
    with np.errstate(invalid="ignore"):
        m = np.isfinite(g) & (g > 0) & (g <= max_depth)
        if pred is not None:
            p = _as_array(pred)
            if p.shape != g.shape:
                raise ShapeError(f"valid_mask: pred shape {p.shape} differs from gt shape {g.shape}")
            m &= np.isfinite(p) & (p > 0)
    return m


def resize_to(pred: DepthLike, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of a depth map to ``shape = (H, W)`` (``cv2.INTER_LINEAR``), float64.

    Returned unchanged (as float64) when it already has that shape.
    """
    p = _as_map(pred, "pred")
    h, w = int(shape[0]), int(shape[1])
    if p.shape == (h, w):
        return p
    return cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR)


def scale_factor(pred: DepthLike, gt: DepthLike, mask: np.ndarray, scaling: Scaling) -> float:
    """Scale ``s`` applied to ``pred`` before comparing with ``gt``, over ``mask``.

    ``median``: ``median(gt)/median(pred)``; ``lsq``: ``Σ pred·gt / Σ pred²``; ``none``: 1.
    Returns NaN for ``median``/``lsq`` when ``mask`` is empty.

    Raises:
        ConfigError: unknown ``scaling``.
    """
    _check_scaling(scaling)
    if scaling == "none":
        return 1.0
    return _scale(_as_array(pred)[mask], _as_array(gt)[mask], scaling)


def _scale(p: np.ndarray, g: np.ndarray, scaling: str) -> float:
    """:func:`scale_factor` on the valid values only (1-D)."""
    if scaling == "none":
        return 1.0
    if p.size == 0:
        return float("nan")
    if scaling == "median":
        return median(g) / median(p)  # median scaling, Zhou et al. 2017 / Monodepth2
    return float(np.dot(p, g) / np.dot(p, p))  # argmin_s Σ(s·p − g)²: d/ds = 0 ⇒ s = Σpg/Σp²


def _pcd(p: np.ndarray, g: np.ndarray, s: float, threshold: float) -> float:
    if p.size == 0:
        return float("nan")
    return float(100.0 * np.mean(np.abs(s * p - g) / g < threshold))  # paper §IV-B: |D − D_gt|/D_gt < 0.1


def percent_correct(
    pred: DepthLike,
    gt: DepthLike,
    scaling: Scaling,
    threshold: float = PCD_THRESHOLD,
    max_depth: float = MAX_DEPTH,
) -> float:
    """Percent correct depth (paper §IV-B): share of valid pixels with ``|s·D − D_gt|/D_gt < threshold``.

    Args:
        pred: ``(h, w)`` predicted depth (any resolution; resized bilinearly to GT's).
        gt: ``(H, W)`` GT depth, metres; 0 = missing.
        scaling: ``lsq`` | ``median`` | ``none`` (module docstring).
        threshold: relative error bound (strict ``<``).
        max_depth: GT depth above this is ignored.

    Returns:
        Percent in ``[0, 100]``; NaN when no pixel is valid.
    """
    g = _as_map(gt, "gt")
    p = resize_to(pred, g.shape)
    m = valid_mask(g, max_depth, p)
    _check_scaling(scaling)
    pv, gv = p[m], g[m]
    return _pcd(pv, gv, _scale(pv, gv, scaling), threshold)


def esi(pred: DepthLike, gt: DepthLike, mask: np.ndarray | None = None) -> float:
    """Scale-invariant log error e_si (paper Eq. 13, §IV-D; Eigen et al. 2014, eq. 4 with λ = 1).

    ``e_si = sqrt(mean(d²) − mean(d)²)``, ``d = log z − log z*``; the same value as the
    paper's inverse-depth form (``d`` only changes sign). Computed as the population
    standard deviation of ``d``, which is algebraically identical and does not cancel
    catastrophically (``pred = k·gt`` gives 0 to rounding).

    Args:
        pred: ``(H, W)`` depth map or ``(N,)`` map-point depths.
        gt: same shape, GT depth.
        mask: optional bool selection; pixels/points where either value is not finite or
            ``<= 0`` are always excluded.

    Returns:
        e_si (dimensionless, log units); NaN when nothing is valid.
    """
    p, g = _as_array(pred), _as_array(gt)
    if p.shape != g.shape:
        raise ShapeError(f"esi: pred shape {p.shape} differs from gt shape {g.shape}")
    m = valid_mask(g, np.inf, p)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != g.shape:
            raise ShapeError(f"esi: mask shape {mask.shape} differs from gt shape {g.shape}")
        m &= mask
    return _esi(p[m], g[m])


def _esi(p: np.ndarray, g: np.ndarray) -> float:
    """:func:`esi` on valid (finite, positive) 1-D values."""
    if p.size == 0:
        return float("nan")
    d = np.log(p) - np.log(g)  # d_i = log z_i − log z_i* (paper §IV-D)
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))  # = sqrt(1/N Σd² − 1/N² (Σd)²), Eigen et al. 2014


def abs_rel(pred: DepthLike, gt: DepthLike, mask: np.ndarray, scale: float = 1.0) -> float:
    """Mean absolute relative error ``mean(|s·D − D_gt| / D_gt)`` (Eigen et al. 2014); NaN if empty."""
    return _abs_rel(_as_array(pred)[mask], _as_array(gt)[mask], scale)


def _abs_rel(p: np.ndarray, g: np.ndarray, scale: float) -> float:
    if p.size == 0:
        return float("nan")
    return float(np.mean(np.abs(scale * p - g) / g))  # abs_rel, Eigen et al. 2014 §4


def align_inverse_depth(pred_inv: DepthLike, gt: DepthLike,
                        max_depth: float = MAX_DEPTH) -> tuple[np.ndarray, float, float]:
    """Depth from a *relative* inverse-depth map (MiDaS-style: known only up to an affine map) by a
    per-frame least-squares scale and shift in inverse depth against the GT, as MiDaS is evaluated
    (Ranftl et al. 2022, "Towards Robust Monocular Depth Estimation", arXiv 1907.01341: alignment in
    disparity space; the authors' ``compute_scale_and_shift`` and depth cap).

    .. math::
        (s, t) = \\arg\\min_{s,t} \\sum_{i \\in V} (s x_i + t - 1/D^*_i)^2, \\qquad
        D_i = 1 / \\max(s x_i + t,\\ 1/d_{max})

    ``V``: pixels with valid GT (finite, ``> 0``, ``<= max_depth``) and a finite ``x``; ``x`` may
    be zero or negative (an affine map of inverse depth). The aligned inverse depth is clamped at
    ``1/max_depth`` before inverting (MiDaS's depth cap), so every finite ``x`` gets a depth in
    ``(0, max_depth]``.

    Args:
        pred_inv: ``(h, w)`` relative inverse depth (resized bilinearly to GT's resolution).
        gt: ``(H, W)`` GT depth, metres; 0 = missing.
        max_depth: GT above this is not fitted, and the depth cap (metres).

    Returns:
        ``(depth, s, t)``: ``(H, W)`` float64 depth in metres (NaN where ``x`` is not finite), and
        the fitted scale and shift. When fewer than 2 pixels are valid or ``x`` is constant on
        them the fit is degenerate: ``depth`` is all NaN and ``s``, ``t`` are NaN (never 0).
    """
    g = _as_map(gt, "gt")
    x = resize_to(pred_inv, g.shape)
    m = valid_mask(g, max_depth) & np.isfinite(x)
    xv, yv = x[m], 1.0 / g[m]  # y_i = 1/D*_i: the GT in inverse depth
    dx = xv - xv.mean() if xv.size else xv
    sxx = float(np.dot(dx, dx))
    # constant x: Σ(x−x̄)² is then only the rounding of x̄ (~ε|x|), so "> 0" would fit noise
    if xv.size < 2 or not sxx > xv.size * (1e-12 * float(np.abs(xv).max())) ** 2:
        nan = float("nan")
        return np.full(g.shape, nan), nan, nan
    # normal equations of the 2-parameter fit, centred (same solution as MiDaS's 2×2 system
    # [Σx² Σx; Σx n]·[s t]ᵀ = [Σxy Σy]ᵀ, without its cancellation): s = Σ(x−x̄)(y−ȳ)/Σ(x−x̄)², t = ȳ − s·x̄
    s = float(np.dot(dx, yv - yv.mean()) / sxx)
    t = float(yv.mean() - s * xv.mean())
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.maximum(s * x + t, 1.0 / max_depth)  # depth cap: aligned inverse depth >= 1/d_max
        depth = 1.0 / inv
    depth[~np.isfinite(x)] = np.nan
    return depth, s, t


@dataclass
class DepthStats:
    """Per-frame depth metrics (one row of ``per_frame.csv``).

    Attributes:
        pcd_lsq, pcd_median, pcd_none: percent correct under each scaling.
        esi: scale-invariant log error over valid pixels.
        abs_rel: mean absolute relative error after median scaling.
        scale_lsq, scale_median: the per-frame scale factors.
        sum_pg, sum_pp: ``Σ D·D_gt`` and ``Σ D²`` over the valid pixels (m², the sequence's lsq scale).
        n_valid: number of valid pixels (all values are NaN when 0).
        sketch: :func:`ratio_sketch` of the frame when asked for (not a ``per_frame.csv`` column).
    """

    pcd_lsq: float
    pcd_median: float
    pcd_none: float
    esi: float
    abs_rel: float
    scale_lsq: float
    scale_median: float
    sum_pg: float
    sum_pp: float
    n_valid: int
    sketch: np.ndarray | None = None


def depth_stats(
    pred: DepthLike, gt: DepthLike, max_depth: float = MAX_DEPTH, threshold: float = PCD_THRESHOLD, sketch: bool = False
) -> DepthStats:
    """All per-frame depth metrics of one prediction (resized to GT resolution first);
    ``sketch``: also keep :func:`ratio_sketch` of the frame (sequence-level scaling)."""
    g = _as_map(gt, "gt")
    p = resize_to(pred, g.shape)
    m = valid_mask(g, max_depth, p)
    pv, gv = p[m], g[m]
    if pv.size == 0:
        nan = float("nan")
        return DepthStats(nan, nan, nan, nan, nan, nan, nan, 0.0, 0.0, 0, None)
    # One sorted copy of the ratio r = D / D_gt serves every metric (this runs on every frame, three times
    # with online scoring): |s·D − D_gt| / D_gt = |s·r − 1|, and log z − log z* = log r.
    ratio = pv / gv
    r = np.sort(ratio)
    s_lsq = float(np.dot(pv, gv) / np.dot(pv, pv))  # argmin_s Σ(s·p − g)² ⇒ s = Σpg/Σp²
    s_med = median(gv) / median(pv)  # median scaling, Zhou et al. 2017 / Monodepth2
    n = r.size

    def pcd(scale: float) -> float:  # paper §IV-B: |s·D − D_gt|/D_gt < threshold, counted on the sorted ratios
        return 100.0 * count_within(r, scale, threshold) / n

    d = np.log(ratio)  # d_i = log z_i − log z_i* (paper §IV-D); sums in pixel order, as they always were
    return DepthStats(
        pcd_lsq=pcd(s_lsq),
        pcd_median=pcd(s_med),
        pcd_none=pcd(1.0),
        esi=float(np.std(d)),  # population std = sqrt(mean d² − (mean d)²), Eigen et al. 2014
        abs_rel=float(np.mean(np.abs(s_med * ratio - 1.0))),  # abs_rel after median scaling
        scale_lsq=s_lsq,
        scale_median=s_med,
        sum_pg=float(np.dot(pv, gv)),
        sum_pp=float(np.dot(pv, pv)),
        n_valid=int(n),
        sketch=ratio_sketch(np.log(r), presorted=True) if sketch else None,
    )


def sequence_lsq_scale(sum_pg: DepthLike, sum_pp: DepthLike) -> float:
    """One least-squares scale for a sequence from the frames' ``Σ D·D_gt`` and ``Σ D²`` (NaN if none)."""
    pg, pp = _as_array(sum_pg), _as_array(sum_pp)
    ok = np.isfinite(pg) & np.isfinite(pp)
    den = float(pp[ok].sum())
    return float(pg[ok].sum() / den) if den > 0 else float("nan")  # argmin_s Σ_frames Σ (s·p − g)²


def pooled_mean(values: DepthLike, n_valid: DepthLike) -> float:
    """Pixel-pooled mean of per-frame percentages: ``Σ v·n / Σ n`` over frames with a finite value."""
    v, n = _as_array(values), _as_array(n_valid)
    ok = np.isfinite(v) & (n > 0)
    return float(np.dot(v[ok], n[ok]) / n[ok].sum()) if ok.any() else float("nan")


def depth_frame_metrics(
    pred: DepthLike, gt: DepthLike, max_depth: float = MAX_DEPTH, threshold: float = PCD_THRESHOLD
) -> dict[str, float | int]:
    """:func:`depth_stats` as a plain dict (keys = :class:`DepthStats` fields but ``sketch``) for ``per_frame.csv``."""
    out = asdict(depth_stats(pred, gt, max_depth, threshold))
    out.pop("sketch")
    return out


def running_mean(values: DepthLike) -> np.ndarray:
    """Mean over frames ``0..t`` for every ``t``, ignoring NaN (and inf) (the paper's accuracy-over-frames figure).

    Returns:
        ``(T,)`` float64; NaN until the first finite value.
    """
    v = _as_array(values).reshape(-1)
    ok = np.isfinite(v)
    total = np.cumsum(np.where(ok, v, 0.0))
    count = np.cumsum(ok)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)

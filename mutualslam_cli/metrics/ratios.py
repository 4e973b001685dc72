"""Order statistics of a frame's depth ratios ``r = D / D_gt`` (:mod:`~mutualslam_cli.metrics.depth`).

Every evaluated frame is scored up to three times (pre-trained, adapted, online), so these are made to
cost one sort: the exact median by one single-position partition, the PCD's pixel count by two bisections
of the sorted ratios, and the sketch of ``log r`` (:data:`SKETCH_POINTS` quantiles) that scores a frame
under a scale known only later (``seq_lsq``). Each gives numpy's own result to the bit.
"""

from __future__ import annotations

import bisect

import numpy as np

SKETCH_POINTS = 2049


def median(x: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array, to the bit, from one single-position partition (``np.median``'s
    two-position partition took ~7× longer on 300k values)."""
    h = x.size // 2
    a = np.partition(x, h)
    return float(a[h]) if x.size % 2 else float((a[:h].max() + a[h]) / 2)


def count_within(r_sorted: np.ndarray, scale: float, threshold: float) -> int:
    """``np.count_nonzero(np.abs(scale * r - 1) < threshold)`` over ascending ``r_sorted``, by two bisections:
    ``scale·r − 1`` is monotone in ``r`` for ``scale > 0`` (rounding included), so the pixels that pass are one
    run of the sorted array, found with the same float comparisons the direct count makes."""
    if not (np.isfinite(scale) and scale > 0):
        return int(np.count_nonzero(np.abs(scale * r_sorted - 1.0) < threshold))
    lo = bisect.bisect_left(r_sorted, True, key=lambda x: scale * x - 1.0 > -threshold)
    hi = bisect.bisect_left(r_sorted, True, key=lambda x: scale * x - 1.0 >= threshold)
    return max(0, hi - lo)


def ratio_sketch(log_r: np.ndarray, presorted: bool = False) -> np.ndarray:
    """``(SKETCH_POINTS,)`` float32 evenly spaced quantiles (0 to 1) of a frame's ``log(D / D_gt)``.

    ``np.quantile``'s linear method, to the bit, read off one sort: its partition around 2,049 positions
    took ~10× longer (the slowest part of a frame's evaluation). ``presorted``: ``log_r`` is the log of sorted
    ratios; it is sorted again only if the log's rounding broke the order somewhere."""
    x = np.asarray(log_r).ravel()  # its own dtype: numpy interpolates float32 values in float32 steps
    if not presorted or np.any(x[1:] < x[:-1]):
        x = np.sort(x)
    pos = (x.size - 1) * np.linspace(0.0, 1.0, SKETCH_POINTS)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, x.size - 1)
    t = pos - lo
    a, b = x[lo], x[hi]
    diff = b - a
    out = a + diff * t  # numpy's _lerp: from below for t < 0.5, from above otherwise
    upper = t >= 0.5
    out[upper] = b[upper] - diff[upper] * (1.0 - t[upper])
    return out.astype(np.float32)


def pcd_from_sketch(sketch: np.ndarray | None, scale: float, threshold: float) -> float:
    """PCD (%) of a frame under ``scale`` from its :func:`ratio_sketch`: the share of pixels with
    ``|s·r − 1| < threshold`` ⇔ ``log r ∈ (log((1 − t)/s), log((1 + t)/s))``, read off the sketch's
    piecewise-linear distribution function (≤ 0.1 points from the exact count). NaN without a sketch."""
    if sketch is None or not np.isfinite(scale) or scale <= 0:
        return float("nan")
    q = np.asarray(sketch, dtype=np.float64)
    cdf = np.linspace(0.0, 1.0, q.size)
    lo, hi = np.log((1.0 - threshold) / scale), np.log((1.0 + threshold) / scale)
    return float(100.0 * (np.interp(hi, q, cdf) - np.interp(lo, q, cdf)))

"""How the dense stage brings each model's depth into metres: the three scalings it can score.

Monocular depth has no metric scale; the dense stage (:mod:`~mutualslam_cli.stages.dense`) fuses each
model's depth times a factor (metres per network unit). The scalings differ only in that factor:

- ``sequence``: one factor per model and sequence, from the VO's sparse map (the median over the
  keyframes of each keyframe's ``median(z_vo / z_pred)``, times the Sim(3) scale to metres). Scores
  the shape *and* the frame-to-frame scale consistency of the prediction.
- ``frame``: each fused frame's own factor from the map points it observes (the same per-keyframe
  ratio, times the same metric scale); a frame without one (no map point, or not a keyframe: only
  keyframes observe map points) falls back to the ``sequence`` factor, and is counted. Removes the
  scale jitter the VO could see.
- ``gt``: each fused frame's factor ``median(D_gt / D)`` over its valid GT pixels (an **oracle**: GT
  depth is not available to a SLAM system); a frame without GT depth falls back to the ``sequence``
  factor, counted. The bound on the scale: what is left is the shape. (A bound on the scale error,
  not on the scores: the median ratio is not fitted to the surface, and a badly shaped prediction can
  score better at another scale.)

Everything here is plain numpy; the stage does the I/O.
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.metrics import depth as dm

#: The scalings, in the order the stage fuses and the report shows them.
SCALINGS = ("sequence", "frame", "gt")
#: Summary key prefix of each scaling's scores: ``<prefix><metric>.<model>``. The sequence scaling keeps
#: the original ``dense.<metric>.<model>`` keys.
PREFIX = {"sequence": "dense.", "frame": "dense.frame_scale.", "gt": "dense.gt_scale."}
#: What each scaling is, for captions and notes.
DESCRIPTION = {
    "sequence": "one VO scale per sequence",
    "frame": "per-frame VO scale (each frame's map points)",
    "gt": "per-frame GT scale (oracle)",
}


def gt_factor(pred: np.ndarray, gt: np.ndarray, max_depth: float = dm.MAX_DEPTH) -> float:
    """``median(D_gt / D)`` over the valid pixels of one frame (metres per network unit).

    Args:
        pred: ``(h, w)`` predicted depth, network units, at any resolution (bilinearly resized to
            ``gt``'s, as the depth evaluation does: :func:`~mutualslam_cli.metrics.depth.resize_to`).
        gt: ``(H, W)`` GT depth in metres (0 / non-finite: missing), undistorted like the frame.
        max_depth: GT depth above this (m) is left out (:func:`~mutualslam_cli.metrics.depth.valid_mask`).

    Returns:
        The factor; NaN when no pixel is valid.
    """
    g = np.asarray(gt, np.float64)
    p = dm.resize_to(pred, g.shape[:2])
    mask = dm.valid_mask(g, max_depth, p)
    if not mask.any():
        return float("nan")
    return float(np.median(g[mask] / p[mask]))


def with_fallback(own: np.ndarray, fallback: float | None) -> tuple[np.ndarray | None, int]:
    """Per-frame factors ``(N,)`` with each missing one (NaN, or ≤ 0) replaced by ``fallback``.

    Returns:
        ``(factors, n_fallback)``; ``factors`` is None when some frame needs the fallback and there is
        none (``fallback`` None).
    """
    own = np.asarray(own, np.float64).reshape(-1)
    missing = ~(np.isfinite(own) & (own > 0))
    n = int(missing.sum())
    if n and fallback is None:
        return None, n
    out = own.copy()
    out[missing] = fallback if n else 0.0
    return out, n


def log_spread(factors: np.ndarray) -> float:
    """Standard deviation of ``ln(factor)`` over the finite, positive factors ``(N,)`` (NaN with < 2):
    the frame-to-frame scale jitter (0.1 ≈ 10 %)."""
    f = np.asarray(factors, np.float64).reshape(-1)
    f = f[np.isfinite(f) & (f > 0)]
    return float(np.std(np.log(f))) if len(f) >= 2 else float("nan")


def median_factor(factors: np.ndarray) -> float:
    """Median of the finite, positive factors ``(N,)`` (NaN when none)."""
    f = np.asarray(factors, np.float64).reshape(-1)
    f = f[np.isfinite(f) & (f > 0)]
    return float(np.median(f)) if len(f) else float("nan")

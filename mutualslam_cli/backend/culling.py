"""Map-point culling with the adapted depth network before global BA (paper §III-C, DESIGN §6).

Each map point gets a *host* keyframe: of the keyframes observing it, the one whose depth
prediction validates best (lowest L_val, Eq. 9; the paper's Fig. 3). The point is kept iff
its depth in that keyframe agrees with the CNN's (Eq. 10):

    g(d_mp, d_CNN) = 1  if |d_mp − d_CNN| < γ·d_CNN  or  d_CNN > d_max,  else 0

``d_max`` bounds the CNN's *effective* range (like a depth sensor's), so far points are not
culled on the network's least reliable predictions. Depths are in map units (the adapted
network is supervised with the map's sparse depth, Eq. 7).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from mutualslam_cli.errors import ConfigError, ShapeError
from mutualslam_cli.geometry import project, se3_inv, transform
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.pixels import in_image

DepthLookup = Callable[[int, np.ndarray], np.ndarray]
"""``depth_at(kf_id, pixels)``: CNN depth (map units) of keyframe ``kf_id`` at ``(M, 2)``
undistorted pinhole pixels of the VO camera; NaN where there is no prediction."""


def correct(d_mp: np.ndarray, d_cnn: np.ndarray, gamma: float, d_max: float) -> np.ndarray:
    """Eq. 10, ``g(d_mp, d_CNN)``, elementwise.

    Args:
        d_mp: ``(P,)`` map-point depths in their host keyframe (map units).
        d_cnn: ``(P,)`` CNN depths at the same pixels (map units).
        gamma: relative tolerance γ (paper: 0.5).
        d_max: effective CNN range (paper: 1.5 map units).

    Returns:
        ``(P,)`` bool, ``True`` = keep. A NaN ``d_cnn`` (no prediction) is never ``True`` here;
        :func:`cull_map_points` decides what to do with such points.
    """
    d_mp, d_cnn = np.asarray(d_mp, float), np.asarray(d_cnn, float)
    if d_mp.shape != d_cnn.shape:
        raise ShapeError(f"d_mp {d_mp.shape} and d_cnn {d_cnn.shape}: expected equal shapes")
    with np.errstate(invalid="ignore"):
        return (np.abs(d_mp - d_cnn) < gamma * d_cnn) | (d_cnn > d_max)


def choose_hosts(observations: list[np.ndarray], fallback: np.ndarray,
                 val_loss: Mapping[int, float]) -> np.ndarray:
    """Host keyframe per point: the observing keyframe with the lowest L_val (paper Fig. 3).

    Keyframes without a finite L_val are never preferred; a point none of whose keyframes has
    one keeps its ``fallback`` (front-end) host. Ties go to the lower keyframe id.

    Args:
        observations: per point, the ``(P_i,)`` keyframe ids observing it.
        fallback: ``(P,)`` host to keep when no observing keyframe has an L_val.
        val_loss: ``{kf_id: L_val}``.

    Returns:
        ``(P,)`` int64 keyframe ids.
    """
    if len(observations) != len(fallback):
        raise ShapeError(f"{len(observations)} observation lists for {len(fallback)} points")
    out = np.asarray(fallback, np.int64).copy()
    for i, obs in enumerate(observations):
        best, best_loss = -1, np.inf
        for k in sorted(int(x) for x in obs):
            v = val_loss.get(k, np.nan)
            if np.isfinite(v) and v < best_loss:
                best, best_loss = k, v
        if best >= 0:
            out[i] = best
    return out


@dataclass
class CullResult:
    """Outcome of :func:`cull_map_points` (one row per map point).

    Attributes:
        keep: ``(P,)`` bool, points that pass Eq. 10 (or could not be judged).
        host: ``(P,)`` chosen host keyframe ids.
        d_mp, d_cnn: ``(P,)`` depths compared (map units; ``d_cnn`` NaN where unjudged).
        judged: ``(P,)`` bool, points the CNN had a prediction for.
    """

    keep: np.ndarray
    host: np.ndarray
    d_mp: np.ndarray
    d_cnn: np.ndarray
    judged: np.ndarray

    @property
    def n_before(self) -> int:
        return len(self.keep)

    @property
    def n_after(self) -> int:
        return int(self.keep.sum())


def cull_map_points(vo: VOResult, val_loss: Mapping[int, float], depth_at: DepthLookup,
                    gamma: float = 0.5, d_max: float = 1.5) -> CullResult:
    """Judge every map point of ``vo`` with the CNN depth of its best-validated keyframe.

    Args:
        vo: front-end output (poses, map points, pinhole camera).
        val_loss: ``{kf_id: L_val}`` of the current model (e.g. ``OnlineAdapter.per_keyframe_val_loss``).
        depth_at: CNN depth lookup (see :data:`DepthLookup`).
        gamma, d_max: Eq. 10 parameters.

    Returns:
        :class:`CullResult`. A point whose host pixel has no CNN depth (NaN) or falls outside
        the image is *kept* and marked unjudged: culling removes only points the network
        contradicts.
    """
    if not gamma > 0 or not d_max > 0:
        raise ConfigError(f"culling: gamma = {gamma!r}, d_max = {d_max!r}; expected both > 0")
    pts = vo.points
    n = len(pts)
    host = choose_hosts(pts.observations, pts.host, val_loss)
    d_mp = np.full(n, np.nan)
    d_cnn = np.full(n, np.nan)
    if n:
        pw = vo.points_world()
        K = vo.intrinsics.K()
        w, h = vo.intrinsics.width, vo.intrinsics.height
        for k in np.unique(host):
            m = np.flatnonzero(host == k)
            pc = transform(se3_inv(vo.keyframes[int(k)].pose), pw[m])
            pix, z = project(pc, K)
            inside = (z > 1e-9) & in_image(pix, w, h)
            d_mp[m] = z
            if inside.any():
                d = np.asarray(depth_at(int(k), pix[inside]), float)
                if d.shape != (int(inside.sum()),):
                    raise ShapeError(f"depth_at({int(k)}, …) returned shape {d.shape}; expected ({int(inside.sum())},)")
                d_cnn[m[inside]] = np.where(d > 0, d, np.nan)
    judged = np.isfinite(d_cnn) & np.isfinite(d_mp) & (d_mp > 0)
    keep = ~judged | correct(d_mp, d_cnn, gamma, d_max)
    return CullResult(keep=keep, host=host, d_mp=d_mp, d_cnn=d_cnn, judged=judged)


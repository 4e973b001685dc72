"""Faults injected into the front end's map on purpose (test knobs): ``vo.inject_outliers``.

Gross depth outliers put where they are known, to measure how well the back end's culling finds them
(:mod:`~mutualslam_cli.backend.culling`). :func:`inject_outliers` corrupts a map record (a
:class:`~mutualslam_cli.map.result.VOResult`); :func:`corrupt_depths` does the same to a
:class:`~mutualslam_cli.map.state.MapState`, for a finished front end (hindsight labels only: a live front
end would never see the change).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mutualslam_cli.errors import ConfigError
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.state import MapState

#: Depth factors of :func:`inject_outliers`: both break Eq. 10 with γ = 0.5 against the true depth.
OUTLIER_FACTORS = (2.0, 0.4)


def inject_outliers(vo: VOResult, fraction: float, seed: int) -> tuple[VOResult, np.ndarray]:
    """Gross depth outliers in a map, to measure culling against known outliers.

    ``round(fraction · P)`` points, drawn without replacement with ``seed``, get their depth in
    their host keyframe multiplied by 2 or 0.4 (each with probability ½): their inverse depth is
    divided by the factor. Hosts, pixels and observations are unchanged.

    Returns:
        ``(vo_with_outliers, ids)``: the map (``vo`` itself when there is nothing to inject) and
        the ``(n,)`` int64 ids (``vo.points.ids``) of the corrupted points.
    """
    if not 0 <= fraction < 1:
        raise ConfigError(f"inject_outliers: fraction must be in [0, 1), got {fraction}")
    P = len(vo.points)
    n = int(round(fraction * P))
    if n == 0:
        return vo, np.zeros(0, np.int64)
    rng = np.random.default_rng([seed, 0x0B1])
    idx = np.sort(rng.choice(P, n, replace=False))
    inv = vo.points.inv_depth.copy()
    inv[idx] /= rng.choice(OUTLIER_FACTORS, n)
    pts = replace(vo.points, inv_depth=inv)
    return replace(vo, points=pts, meta={**vo.meta, "injected_outliers": n}), vo.points.ids[idx].astype(np.int64)


def corrupt_depths(state: MapState, vo: VOResult, fraction: float, seed: int) -> np.ndarray:
    """:func:`inject_outliers` on ``state``'s map (``vo``: its snapshot, point ids = map ids): the chosen points'
    depths corrupted in the map and their world positions refreshed; returns their ids."""
    bad_vo, ids = inject_outliers(vo, fraction, seed)
    if len(ids):
        rows = np.searchsorted(vo.points.ids, ids)
        state.set_depths(ids, bad_vo.points.inv_depth[rows])
        state.refresh(ids)
    return ids

"""The network's view of the map's scale, keyframe by keyframe (:class:`ScaleCheck`): the ratio of the map's depth
to the network's over a keyframe's points, against its map unit's running median; read by the front end's network
parts (:mod:`~mutualslam_cli.vo.depth_prior`: depth seeds, the scale prior) and recorded in the run's summary.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mutualslam_cli.pixels import lookup_nearest

MIN_RATIO_POINTS = 20
"""Fewer points with a positive prediction in a keyframe: no ratio (no check, no seeds from it)."""

MIN_REL_SIGMA = 0.1
"""Floor of the network's relative depth deviation used for a seed's start."""

HELD_DEPTHS = 8
"""Keyframes whose network depth is held (the windowed BA's free keyframes need theirs)."""

DepthHint = Callable[[int], np.ndarray]
"""``hint(frame)`` → ``(h, w)`` network depth of that frame's undistorted image (the network's unit)."""


@dataclass
class KeyframeRatio:
    """A keyframe's scale check: ``ratio`` = median(z_map / d_net) over ``n`` points, ``rel_sigma`` the
    network's relative deviation around it, ``ref`` the unit's running median before it (NaN: none yet)."""

    kf: int
    ratio: float
    rel_sigma: float
    n: int
    ref: float

    @property
    def drift(self) -> float:
        """``ratio / ref``: the map's scale against the unit's so far, as the network sees it (NaN: no ref)."""
        return self.ratio / self.ref if np.isfinite(self.ref) and self.ref > 0 else float("nan")


def _ratios(z: np.ndarray, d: np.ndarray) -> tuple[float, float, int]:
    ok = np.isfinite(d) & (d > 0) & (z > 0)
    n = int(ok.sum())
    if n < MIN_RATIO_POINTS:
        return float("nan"), float("nan"), n
    lr = np.log(z[ok] / d[ok])
    med = float(np.median(lr))
    return float(np.exp(med)), max(1.4826 * float(np.median(np.abs(lr - med))), MIN_REL_SIGMA), n


@dataclass
class ScaleCheck:
    """The network's view of the map's scale, keyframe by keyframe (module docstring).

    Args:
        hint: the network's depth of a frame (:data:`DepthHint`).
        size: ``(W, H)`` of the front end's (undistorted pinhole) pixels.

    Attributes:
        checks: one :class:`KeyframeRatio` per keyframe with enough points.
        depths: the network depth of the newest :data:`HELD_DEPTHS` keyframes.
    """

    hint: DepthHint
    size: tuple[int, int]
    checks: list[KeyframeRatio] = field(default_factory=list)
    depths: dict[int, np.ndarray] = field(default_factory=dict)
    _unit_of: dict[int, int] = field(default_factory=dict)

    def keyframe(self, kf: int, frame: int, unit: int, uv: np.ndarray, z: np.ndarray) -> KeyframeRatio | None:
        """Keyframe ``kf`` (at ``frame``, in map unit ``unit``) with its tracked points at pixels ``uv`` ``(n, 2)``
        and map depths ``z`` ``(n,)``: its network depth is taken and held, its ratio checked and recorded."""
        d = self.hint(frame)
        self.depths[kf] = d
        for k in sorted(self.depths)[:-HELD_DEPTHS]:
            del self.depths[k]
        ratio, rel, n = _ratios(z, lookup_nearest(d, uv, self.size))
        if not np.isfinite(ratio):
            return None
        self._unit_of[kf] = unit
        ref = self.reference(unit)
        rec = KeyframeRatio(kf, ratio, rel, n, ref)
        self.checks.append(rec)
        return rec

    def reference(self, unit: int) -> float:
        """The running median of the ratios of the unit's keyframes so far (NaN: none)."""
        r = [c.ratio for c in self.checks if self._unit_of.get(c.kf) == unit]
        return float(np.median(r)) if r else float("nan")

    def seeds(self, rec: KeyframeRatio, px: np.ndarray, f_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth seeds' start for pixels ``px`` ``(n, 2)`` of keyframe ``rec.kf`` with unit bearings' ``z``
        components ``f_z``: ``(mu, sigma2)`` ``(n,)`` of inverse distance along the bearing (NaN where the
        network has no depth: those keep SVO's start)."""
        d = lookup_nearest(self.depths[rec.kf], px, self.size)
        z0 = rec.ratio * np.where(d > 0, d, np.nan)
        mu = f_z / z0
        return mu, (mu * rec.rel_sigma) ** 2

    def prior_rho(self, kf: int, px: np.ndarray, unit: int) -> np.ndarray:
        """Prior inverse depths ``(n,)`` (z⁻¹) of points hosted in keyframe ``kf`` at pixels ``px``: the
        network's depth in the unit's reference scale; NaN where unknown (no held depth, no reference)."""
        ref = self.reference(unit)
        if kf not in self.depths or not np.isfinite(ref):
            return np.full(len(px), np.nan)
        d = lookup_nearest(self.depths[kf], px, self.size)
        return np.where(d > 0, 1.0 / (ref * d), np.nan)

    def summary(self) -> dict[str, float | int | None]:
        """``checks``, and the drift ``ratio/ref`` over them: ``drift_max``, ``drift_min`` (None: no check)."""
        dr = np.array([c.drift for c in self.checks])
        dr = dr[np.isfinite(dr)]
        return {"checks": len(self.checks), "drift_max": float(dr.max()) if len(dr) else None,
                "drift_min": float(dr.min()) if len(dr) else None}

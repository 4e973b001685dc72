"""The adapted network in the front end (``vo.depth_seeds``, ``vo.scale_prior``; off = the paper's SVO).

The network's depth of a keyframe, ``d`` (as adapted up to that frame: causal), is in the network's own
unit; the map's depth ``z`` in the map's. Their ratio over the points a keyframe observes,
``r_k = median(z / d)``, is the keyframe's *scale check*: a map whose scale drifts while the network's
does not shows it as a drift of ``r_k`` against the unit's running median ``r_ref`` of the keyframes
before it (:class:`ScaleCheck`).

* **Depth seeds** (CNN-SVO, Loo et al., ICRA 2019, §III-B): a new seed in keyframe ``k`` starts at the
  network's depth in the map's unit, ``r_k · d(pixel)``, with the inverse-depth deviation of the
  network's relative error measured on that keyframe's own points, ``σ_ρ = ρ · σ_rel``
  (``σ_rel``: 1.4826 · MAD of ``log(z / (r_k d))``, at least :data:`MIN_REL_SIGMA`), instead of SVO's
  mean scene depth with a range that covers the whole scene. Only the seed's start changes: it still
  converges by the depth filter's triangulations.
* **Scale prior** (the windowed BA, :mod:`~mutualslam_cli.vo.local_ba`): each point hosted in a free
  keyframe of the window gets a log-depth prior ``log z − log(r_ref · d)``, weighted so that a keyframe's
  points together weigh as one measurement of its scale with the network's per-keyframe uncertainty
  (:data:`PRIOR_SIGMA_LOG`, :data:`PRIOR_PIXELS`): the network's scale noise, large per keyframe, is not
  multiplied by the number of points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.vo.frontend_base import FrontEndBase

MIN_RATIO_POINTS = 20
"""Fewer points with a positive prediction in a keyframe: no ratio (no check, no seeds from it)."""

MIN_REL_SIGMA = 0.1
"""Floor of the network's relative depth deviation used for a seed's start."""

PRIOR_SIGMA_LOG = 0.3
"""Standard deviation of a keyframe's network scale in log (``vo.scale_prior``): the pre-trained network's
per-keyframe ratio to GT spreads by 0.21 in log on RedKitchen, about twice the map's drift there."""

PRIOR_PIXELS = 10.0
"""A keyframe whose points sit :data:`PRIOR_SIGMA_LOG` off the network's scale pays as one reprojection residual
of this many pixels: each of its ``n`` points' priors carries ``1/√n`` of that weight. Chosen on RedKitchen's 300
frames played forward-back-forward without map reuse (ATE 5.28 cm without a prior; 5.15, 4.93, 4.74, 4.43 at
1, 10, 30, 100 px; with map reuse 2.41 → 2.45 at 10 px, 2.94 at 30: kept weak)."""

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


class NetworkMixin(FrontEndBase):
    """Methods of the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) that ask the network: its
    :attr:`scale` (:class:`ScaleCheck`, ``None`` until :meth:`use_network`) and the windowed BA's prior."""

    def use_network(self, hint: DepthHint) -> None:
        """From now on ask the network (``hint``: its depth of a frame, as adapted up to then) at each keyframe:
        the scale check, and with ``vo.depth_seeds`` / ``vo.scale_prior`` the seeds' start and the windowed BA's
        prior (:mod:`~mutualslam_cli.vo.depth_prior`)."""
        self.scale = ScaleCheck(hint, (self.intr.width, self.intr.height))
        if self.cfg.scale_prior:
            self.mapper.prior_of = self._prior_rho
            self.mapper.prior_w = PRIOR_PIXELS * (1.0 / self.f) / PRIOR_SIGMA_LOG  # a keyframe's, over its points

    def _prior_rho(self, pids: np.ndarray) -> np.ndarray:
        """Prior inverse depths ``(P,)`` of points ``pids`` from their hosts' network depth (NaN: none)."""
        assert self.scale is not None  # the windowed BA's prior_of only after use_network
        m, out = self.state_map.map, np.full(len(pids), np.nan)
        host = np.array([m.host[p] for p in pids.tolist()], np.int64)
        unit = self.state_map.unit(self.st.segment)
        for h in set(host.tolist()) & set(self.scale.depths):
            sel = np.flatnonzero(host == h)
            out[sel] = self.scale.prior_rho(h, np.array([m.px_h[p] for p in pids[sel].tolist()]), unit)
        return out

    def _check_scale(self, kf: int, i: int) -> KeyframeRatio | None:
        """The network's scale check of keyframe ``kf`` (frame ``i``) on its tracked points (a network given)."""
        if self.scale is None:
            return None
        tr = self.st.tracks
        pm = np.flatnonzero(tr.pid >= 0)
        Xc = self.state_map.map.Xw[tr.pid[pm]] @ self.st.T_cw[:3, :3].T + self.st.T_cw[:3, 3]
        return self.scale.keyframe(kf, i, self.state_map.unit(self.st.segment), tr.px[pm], Xc[:, 2])

"""The adapted network in the front end (``vo.depth_seeds``, ``vo.scale_prior``; off = the paper's SVO).

The network's depth of a keyframe, ``d`` (as adapted up to that frame: causal), is in the network's own
unit; the map's depth ``z`` in the map's. Their ratio over the points a keyframe observes,
``r_k = median(z / d)``, is the keyframe's *scale check*: a map whose scale drifts while the network's
does not shows it as a drift of ``r_k`` against the unit's running median ``r_ref`` of the keyframes
before it (:class:`~mutualslam_cli.vo.scale_check.ScaleCheck`).

* **Depth seeds** (CNN-SVO, Loo et al., ICRA 2019, §III-B): a new seed in keyframe ``k`` starts at the
  network's depth in the map's unit, ``r_k · d(pixel)``, with the inverse-depth deviation of the
  network's relative error measured on that keyframe's own points, ``σ_ρ = ρ · σ_rel``
  (``σ_rel``: 1.4826 · MAD of ``log(z / (r_k d))``, at least
  :data:`~mutualslam_cli.vo.scale_check.MIN_REL_SIGMA`), instead of SVO's
  mean scene depth with a range that covers the whole scene. Only the seed's start changes: it still
  converges by the depth filter's triangulations.
* **Scale prior** (the windowed BA, :mod:`~mutualslam_cli.vo.local_ba`): each point hosted in a free
  keyframe of the window gets a log-depth prior ``log z − log(r_ref · d)``, weighted so that a keyframe's
  points together weigh as one measurement of its scale with the network's per-keyframe uncertainty
  (:data:`PRIOR_SIGMA_LOG`, :data:`PRIOR_PIXELS`): the network's scale noise, large per keyframe, is not
  multiplied by the number of points.
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.vo.frontend_base import FrontEndBase
from mutualslam_cli.vo.scale_check import DepthHint, KeyframeRatio, ScaleCheck

PRIOR_SIGMA_LOG = 0.3
"""Standard deviation of a keyframe's network scale in log (``vo.scale_prior``): the pre-trained network's
per-keyframe ratio to GT spreads by 0.21 in log on RedKitchen, about twice the map's drift there."""

PRIOR_PIXELS = 10.0
"""A keyframe whose points sit :data:`PRIOR_SIGMA_LOG` off the network's scale pays as one reprojection residual
of this many pixels: each of its ``n`` points' priors carries ``1/√n`` of that weight. Chosen on RedKitchen's 300
frames played forward-back-forward without map reuse (ATE 5.28 cm without a prior; 5.15, 4.93, 4.74, 4.43 at
1, 10, 30, 100 px; with map reuse 2.41 → 2.45 at 10 px, 2.94 at 30: kept weak)."""

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

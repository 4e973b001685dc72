"""Schemes without replay: ``recent`` (Table 3 (a)) and ``ewc`` (Fig. 6 method 3)."""

from __future__ import annotations

import numpy as np

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.schemes.base import Scheme


class Recent(Scheme):
    """``recent``: the two most recent training keyframes (paper Table 3 (a)).

    The paper (§IV-B) says Luo et al. adapt on the most recent keyframes only; ``luo`` adds
    their stereo-pair selection (:mod:`~mutualslam_cli.adapt.schemes.luo`).
    """

    name = "recent"

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        ids = [k for k in buffer.recent(2) if k <= newest]
        return ids if newest in ids else [newest]


class RecentEWC(Recent):
    """``ewc``: the recent batch with EWC (paper Fig. 6, method 3)."""

    name = "ewc"
    regularizer = "ewc"

"""``comoda``: the CoMoDa-style end-to-end baseline (:mod:`mutualslam_cli.adapt.comoda`).

It trains on every frame with its own pose network, not on keyframes, so a run gives it to the
pipeline's comoda stage instead of the keyframe loop; this entry
makes ``--scheme comoda`` a valid name and checks its ``comoda_*`` settings before any work.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.schemes.base import Scheme
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.config.checks import check_config
from mutualslam_cli.errors import ConfigError


class Comoda(Scheme):
    """``comoda``: frame-driven (no keyframe batches); settings ``AdaptConfig.comoda_*``.

    Raises:
        ConfigError: a ``comoda_*`` setting out of range.
    """

    name = "comoda"
    frame_driven: ClassVar[bool] = True

    def __init__(self, cfg: AdaptConfig | None = None) -> None:
        super().__init__(cfg)
        check_config(self.cfg, "adapt")

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        raise ConfigError("scheme 'comoda' trains on frames, not keyframes: run it with mslam run "
                          "(the pipeline's comoda stage), not with a keyframe adapter")

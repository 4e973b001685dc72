"""Schemes with experience replay: newest keyframe + one uniformly sampled older one (Alg. 2)."""

from __future__ import annotations

import numpy as np

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.schemes.base import Scheme


class Replay(Scheme):
    """``replay``: K_i and K_j, j ~ U{stored training keyframes older than i} (Table 3 (b)).

    Before any older keyframe has a stored photometric neighbour the batch is ``[i]`` alone.
    """

    name = "replay"

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        j = buffer.sample_older(newest, rng)  # Alg. 2 line 6: K_{j ~ {0..i-1}}
        return [newest] if j is None else [newest, j]


class ReplayEWC(Replay):
    """``replay+ewc``: the paper's scheme (Table 3 (c), Alg. 2)."""

    name = "replay+ewc"
    regularizer = "ewc"


class ReplayMAS(Replay):
    """``replay+mas``: replay with MAS (Appendix B, λ = 0.5)."""

    name = "replay+mas"
    regularizer = "mas"


class ReplaySI(Replay):
    """``replay+si``: replay with SI (Appendix B, λ = 1.0)."""

    name = "replay+si"
    regularizer = "si"

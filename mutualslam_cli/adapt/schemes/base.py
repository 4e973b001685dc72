"""A scheme = which keyframes form a training batch, their photometric sources and an optional regulariser (DESIGN §5).

The batch is a list of training keyframe ids, newest first; the photometric sources of each are
:meth:`Scheme.sources`: the time-adjacent training keyframes
(:meth:`~mutualslam_cli.adapt.buffer.KeyframeBuffer.neighbours`) unless a scheme says otherwise
(``luo``: simulated stereo partners). Loss terms are averaged over the
batch (paper §III-B: "averaged across the most recent keyframe and a randomly selected old one").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.regularizers import Regularizer, make_regularizer
from mutualslam_cli.config import AdaptConfig


class Scheme:
    """Base scheme: trains on nothing and has no regulariser.

    Subclasses set :attr:`name`, :attr:`regularizer` (``"ewc" | "mas" | "si" | None``) and
    override :meth:`select` (and :meth:`sources` to choose other photometric sources).

    Args:
        cfg: the adaptation settings, for schemes with constants of their own (default: the
            :class:`AdaptConfig` defaults).
    """

    name: ClassVar[str] = "base"
    regularizer: ClassVar[str | None] = None
    trains: ClassVar[bool] = True

    def __init__(self, cfg: AdaptConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else AdaptConfig()

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        """Training keyframe ids of the batch for newest keyframe ``newest`` (newest first)."""
        raise NotImplementedError

    def sources(self, buffer: KeyframeBuffer, target: int) -> list[int]:
        """Photometric sources of training keyframe ``target``: its stored neighbours s ∈ {i−1, i+1} (Eq. 3)."""
        return buffer.neighbours(target)

    def make_regularizer(self, model: nn.Module, cfg: AdaptConfig,
                         predict: Callable[[torch.Tensor], torch.Tensor] | None = None,
                         mode: str = "prox") -> Regularizer | None:
        """The scheme's regulariser for ``model`` (None if it has none); ``mode``: ``"prox" | "penalty"``."""
        return make_regularizer(self.regularizer, model, cfg, predict, mode) if self.regularizer else None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


class NoTraining(Scheme):
    """``none``: the pre-trained model is kept (Algorithm 1 still validates)."""

    name = "none"
    trains = False

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        return []

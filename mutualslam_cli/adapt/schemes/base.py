"""A scheme = which keyframes form a training batch + an optional regulariser (DESIGN §5).

The batch is a list of training keyframe ids, newest first; the photometric sources of each are
:meth:`~mutualslam_cli.adapt.buffer.KeyframeBuffer.neighbours`. Loss terms are averaged over the
batch (paper §III-B: "averaged across the most recent keyframe and a randomly selected old one").
"""

from __future__ import annotations

from typing import Callable, ClassVar

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.regularizers import Regularizer, make_regularizer
from mutualslam_cli.config import AdaptConfig


class Scheme:
    """Base scheme: trains on nothing and has no regulariser.

    Subclasses set :attr:`name`, :attr:`regularizer` (``"ewc" | "mas" | "si" | None``) and
    override :meth:`select`.
    """

    name: ClassVar[str] = "base"
    regularizer: ClassVar[str | None] = None
    trains: ClassVar[bool] = True

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        """Training keyframe ids of the batch for newest keyframe ``newest`` (newest first)."""
        raise NotImplementedError

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

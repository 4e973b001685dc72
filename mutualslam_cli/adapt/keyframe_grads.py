"""EWC's per-keyframe gradients for the online adapter: which of three ways a batch's are taken (paper Eq. 2).

EWC's Fisher needs, at the end of a batch, each keyframe's gradient of its own L_train
(:mod:`~mutualslam_cli.adapt.regularizers`). In the order they are tried:

1. with ``adapt.fisher_at: last_step`` only (the default, ``end``, is the paper's point: the parameters the batch
   reached), **from the batch's last optimiser step** (:class:`~mutualslam_cli.adapt.sample_grads.StepCapture`): the
   step's own passes are split by keyframe, nothing is run again; taken when the batch had ≥ 2 steps (after a
   single step its passes ran at θ*, before the batch was learnt: the gradients would measure the new
   keyframe's misfit, not curvature) and every keyframe has a sparse point (each image then counts in each
   term's mean, so the split is exact). The gradients are those at the last step's start, one Adam step before
   the parameters the batch reached;
2. **one batched pass** at the parameters reached (:func:`~mutualslam_cli.adapt.sample_grads.per_sample_grads`);
3. **one keyframe at a time** (a network that module cannot split: a training-mode BatchNorm, a layer kind it
   does not cover).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from mutualslam_cli.adapt.batch import TrainingBatch
from mutualslam_cli.adapt.sample_grads import StepCapture, per_sample_grads, plan

#: ``(batch, depth (1, 1, H, W), b)`` → keyframe ``b``'s own L_train (0-d) from its depth and its slice of ``batch``.
OneLoss = Callable[[TrainingBatch, torch.Tensor, int], torch.Tensor]


class KeyframeGrads:
    """Per-keyframe gradients of L_train for EWC's Fisher (module docstring).

    Args:
        net: the network being adapted.
        params: its trainable parameters (the order of every gradient list).
        predict: ``(B, 3, H, W)`` images → ``(B, 1, H, W)`` float32 depth, differentiable (the adapter's).
        one_loss: :data:`OneLoss`.
        from_last_step: take way 1 where it applies (``adapt.fisher_at == "last_step"``).
    """

    def __init__(self, net: nn.Module, params: list[torch.Tensor], predict: Callable[[torch.Tensor], torch.Tensor],
                 one_loss: OneLoss, from_last_step: bool = False) -> None:
        self.net, self.params, self.predict, self.one_loss = net, params, predict, one_loss
        self.from_last_step = from_last_step
        self._layers: list[nn.Module] | None = None  # plan(): None = not asked yet, [] = cannot be split
        self._capture: StepCapture | None = None
        self.from_step = 0  # batches whose gradients came from their last step (way 1)

    def layers(self) -> list[nn.Module]:
        """The layers whose per-keyframe gradients are split (``[]``: the network cannot be)."""
        if self._layers is None:
            self._layers = plan(self.net, self.params) or []
        return self._layers

    def step_capture(self) -> StepCapture | None:
        """What records an optimiser step's passes (``None`` without ``from_last_step`` or when the network cannot be
        split)."""
        if self._capture is None and self.from_last_step and self.layers():
            self._capture = StepCapture(self.layers())
        return self._capture

    def of_batch(self, batch: TrainingBatch, steps: int, scale: float | None = None) -> list[list[torch.Tensor]]:
        """Per keyframe of ``batch`` (which took ``steps`` optimiser steps), its gradient list; ``scale``: the fp16
        loss scale of a separate pass (its gradients are unscaled)."""
        capture = self._capture
        if capture is not None:
            full = steps >= 2 and bool((batch.mask & (batch.d > 0)).any(1).all())
            grads = capture.per_sample(self.params, len(batch.ids), full) if full else None
            capture.clear()  # activation-sized: not kept past the batch
            if grads is not None:
                self.from_step += 1
                return grads
        return self.at_current(batch, scale)

    def at_current(self, batch: TrainingBatch, scale: float | None = None) -> list[list[torch.Tensor]]:
        """Per keyframe, its gradient at the current parameters: one batched forward and backward pass split by
        keyframe (at most one optimiser step's work), else one pass of batch 1 per keyframe."""
        if self.layers():
            def losses() -> list[torch.Tensor]:
                depth = self.predict(batch.target)
                return [self.one_loss(batch, depth[b:b + 1], b) for b in range(len(batch.ids))]

            grads = per_sample_grads(self.layers(), self.params, losses, scale)
            if grads is not None:
                return grads
            self._layers, self._capture = [], None  # a layer it cannot split: one keyframe at a time from now on
        out = []
        for b in range(len(batch.ids)):
            loss = self.one_loss(batch, self.predict(batch.target[b:b + 1]), b)
            kf_grads = torch.autograd.grad(loss if scale is None else loss * scale, self.params, allow_unused=True)
            out.append([torch.zeros_like(p) if g is None else g.detach() if scale is None else g.detach() / scale
                        for p, g in zip(self.params, kf_grads)])
        return out

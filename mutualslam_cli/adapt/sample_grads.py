"""Per-keyframe gradients of a batch from one forward and one backward pass (EWC's Fisher, paper Eq. 2).

EWC's empirical Fisher needs, at the end of a batch, each keyframe's own gradient ``∂L_k/∂θ`` at the
parameters the batch reached (:mod:`~mutualslam_cli.adapt.regularizers`). Taken one keyframe at a time
that is ``B`` forward/backward passes of batch 1 — on a GPU or several CPU threads each pass is as slow as
one of batch ``B`` (launches, barriers), so the Fisher cost up to ``B`` optimiser steps. Here instead:

1. one forward pass of the whole batch; forward hooks keep each trainable convolution's and BatchNorm's
   input ``x`` and output ``y`` (the output is handed on as a copy, so the in-place ReLU/ELU after it does
   not touch the kept one);
2. one backward pass of ``Σ_k L_k`` (each keyframe's own loss, computed on its slice of the batch) taken
   with respect to those outputs only: gradients flow through the activations, never into the
   weights, and not below the first trainable layer (frozen encoder stages cost nothing);
3. per keyframe ``k`` and layer, the parameter gradient from ``x_k`` and ``g_k = ∂L_k/∂y_k`` (the other
   keyframes' losses do not depend on ``y_k``: BatchNorm runs in eval mode, so samples never mix):
   convolution ``∂L_k/∂W = conv2d_weight(x_k, g_k)``, ``∂L_k/∂b = Σ_hw g_k``; BatchNorm (eval)
   ``∂L_k/∂γ = Σ_hw g_k·x̂_k`` with ``x̂ = (x − μ_run)/√(σ²_run + ε)``, ``∂L_k/∂β = Σ_hw g_k``.

The arithmetic is that of one step's backward split by keyframe, so the Fisher costs at most one step
(no optimiser, no proximal step). It is the same quantity as the one-at-a-time loop up to float rounding
(``tests/adapt/test_sample_grads.py``). Not covered — the caller then takes the loop: a BatchNorm in
training mode or a convolution with a non-zero padding mode (:func:`plan` says ``None``), or another kind
of trainable layer that the loss reaches (:func:`per_sample_grads` says ``None``; trainable parameters the
forward pass never uses, as the encoder's ``fc``, get zeros as in the loop).

**From the batch's last step** (:class:`StepCapture`, what :class:`~mutualslam_cli.adapt.online.OnlineAdapter`
does for EWC with ``adapt.fisher_at: last_step`` when a batch took ≥ 2 steps): the optimiser step's own
forward and backward passes already hold ``x`` and ``∂L/∂y`` of every covered layer, so the Fisher needs only
part 3 above: the passes of 1. and 2. are not run again. The step's loss is the mean over the batch's images
of each term (:mod:`~mutualslam_cli.adapt.losses`), so ``B · ∂L/∂y_k = ∂L_k/∂y_k`` whenever every image counts
in every term's mean; an image without a sparse point does not (the sparse term then averages fewer images),
and the caller takes the separate pass (:meth:`StepCapture.per_sample` says ``None``; an image with no pixel
valid in any source would do the same to the photometric term: not checked, as positive depth between
neighbouring keyframes always leaves some). The one difference is where the gradients are taken: at the
parameters the last step started from, one Adam step before those the batch reached (README, "EWC's Fisher
from the last step", for its cost and its effect on PCD).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch
from torch import nn
from torch.nn.grad import conv2d_weight

#: Layer types whose parameters' per-keyframe gradients are computed here.
LAYERS = (nn.Conv2d, nn.BatchNorm2d)


def plan(net: nn.Module, params: list[torch.Tensor]) -> list[nn.Module] | None:
    """The covered layers owning some of ``params``; ``None`` when one of them cannot be split (module docstring)."""
    owner: dict[int, nn.Module] = {}
    for m in net.modules():
        if isinstance(m, LAYERS):
            for p in m.parameters(recurse=False):
                owner[id(p)] = m
    layers = list({id(owner[id(p)]): owner[id(p)] for p in params if id(p) in owner}.values())
    for m in layers:
        if isinstance(m, nn.BatchNorm2d) and (m.training or not m.track_running_stats):
            return None  # batch statistics couple the keyframes
        if isinstance(m, nn.Conv2d) and m.padding_mode != "zeros":
            return None
    return layers


def per_sample_grads(layers: list[nn.Module], params: list[torch.Tensor], losses: Callable[[], list[torch.Tensor]],
                     scale: float | None = None) -> list[list[torch.Tensor]] | None:
    """Each keyframe's gradient of its own loss, for ``params`` (module docstring).

    Args:
        layers: :func:`plan` of the network for ``params``.
        params: the trainable parameters, in the order the result lists them.
        losses: runs the batched forward pass and returns the ``B`` keyframes' own losses (0-d each, the
            k-th a function of the k-th slice of the batch only).
        scale: fp16 loss scale (the gradients are taken of ``scale · Σ L_k`` and divided by it).

    Returns:
        ``B`` lists of gradients shaped like ``params`` (float32 like them; zeros where a layer was not run);
        ``None`` when the loss reaches a parameter outside ``layers`` (its per-keyframe parts are unknown).
    """
    kept: list[tuple[nn.Module, torch.Tensor, torch.Tensor]] = []

    def keep(module: nn.Module, args: tuple[torch.Tensor, ...], out: torch.Tensor) -> torch.Tensor:
        kept.append((module, args[0].detach(), out))
        return out.clone()  # what follows may work in place (ReLU, ELU): the kept output stays as it was

    handles = [m.register_forward_hook(keep) for m in layers]
    try:
        per_kf = losses()
    finally:
        for h in handles:
            h.remove()
    total = torch.stack([loss.float() for loss in per_kf]).sum()
    outs = [y for _, _, y in kept]
    covered = {id(p) for m in layers for p in m.parameters(recurse=False)}
    others = [p for p in params if id(p) not in covered]
    found = torch.autograd.grad(total if scale is None else total * scale, outs + others, allow_unused=True)
    if any(g is not None for g in found[len(outs):]):
        return None
    gouts = found[:len(outs)]
    return _split([(m, x, g) for (m, x, _), g in zip(kept, gouts)], params, len(per_kf), scale)


def _split(kept: list[tuple[nn.Module, torch.Tensor, torch.Tensor | None]], params: list[torch.Tensor], n: int,
           scale: float | None) -> list[list[torch.Tensor]]:
    """Part 3 of the module docstring: ``n`` per-keyframe gradient lists from each layer's ``(layer, x, g)``
    (``g``: the output gradient, ``None`` where the loss did not reach the layer; divided by ``scale``)."""
    index = {id(p): i for i, p in enumerate(params)}
    grads = [[torch.zeros_like(p) for p in params] for _ in range(n)]
    for m, x, g in kept:
        if g is None:
            continue
        g = g if scale is None else g / scale
        for k in range(n):
            for name, value in _layer_grads(m, x[k:k + 1], g[k:k + 1]).items():
                p = getattr(m, name)
                if id(p) in index:
                    grads[k][index[id(p)]].add_(value.to(p.dtype))
    return grads


class StepCapture:
    """Each covered layer's input and output gradient from one optimiser step's passes (module docstring,
    "From the batch's last step").

    Args:
        layers: :func:`plan` of the network for the trainable parameters.
    """

    def __init__(self, layers: list[nn.Module]) -> None:
        self.layers = layers
        self._covered = {id(p) for m in layers for p in m.parameters(recurse=False)}
        self._kept: list[tuple[nn.Module, torch.Tensor, list[torch.Tensor]]] = []
        self._reached_other = True  # until after_backward() says otherwise
        self.scale: float | None = None

    @contextlib.contextmanager
    def recording(self) -> Iterator[None]:
        """Around the step's forward pass: keeps each layer's input, and hooks its output for the gradient
        the step's backward pass will give it (received as it was before any in-place operation after it)."""
        self._kept, self._reached_other = [], True

        def keep(module: nn.Module, args: tuple[torch.Tensor, ...], out: torch.Tensor) -> None:
            got: list[torch.Tensor] = []
            if out.requires_grad:
                out.register_hook(got.append)
            self._kept.append((module, args[0].detach(), got))

        handles = [m.register_forward_hook(keep) for m in self.layers]
        try:
            yield
        finally:
            for h in handles:
                h.remove()

    def per_sample(self, params: list[torch.Tensor], n: int,
                   every_image_counts: bool = True) -> list[list[torch.Tensor]] | None:
        """Each of the ``n`` keyframes' gradient of its own loss, from the step's passes of ``B · L`` (``L``:
        the step's mean loss, taken at the loss scale :meth:`after_backward` was given).

        Returns ``None`` (the caller takes the separate pass) when nothing was recorded, when not every image
        counts in every term's mean (``every_image_counts``), or when the step's backward pass reached a
        trainable parameter outside the covered layers (its per-keyframe parts are unknown).
        """
        if not self._kept or not every_image_counts or self._reached_other:
            return None
        kept = [(m, x, got[0] if got else None) for m, x, got in self._kept]
        self._kept = []
        return _split(kept, params, n, (1.0 if self.scale is None else self.scale) / n)  # B · ∂L/∂y_k = ∂L_k/∂y_k

    def after_backward(self, params: list[torch.Tensor], scale: float | None = None) -> None:
        """Right after the step's backward pass of its loss (before any penalty's), with its fp16 loss
        ``scale``: notes whether it reached a trainable parameter outside the covered layers (the encoder's
        unused ``fc`` is not reached)."""
        self._reached_other = any(p.grad is not None and id(p) not in self._covered for p in params)
        self.scale = scale

    def clear(self) -> None:
        """Drop what was recorded (the inputs and gradients of a whole pass: activation-sized)."""
        self._kept = []


def _layer_grads(m: nn.Module, x: torch.Tensor, g: torch.Tensor) -> dict[str, torch.Tensor]:
    """``{parameter name: ∂L/∂parameter}`` of layer ``m`` from its input ``x`` and output gradient ``g`` (batch 1)."""
    out: dict[str, torch.Tensor] = {}
    if isinstance(m, nn.Conv2d):
        if m.weight.requires_grad:
            out["weight"] = conv2d_weight(x.to(g.dtype), m.weight.shape, g, m.stride, m.padding, m.dilation,
                                          m.groups)
        if m.bias is not None and m.bias.requires_grad:
            out["bias"] = g.float().sum((0, 2, 3))
    else:  # BatchNorm2d in eval mode: y = γ·x̂ + β with the running statistics
        assert isinstance(m, nn.BatchNorm2d)  # plan() keeps only LAYERS
        assert m.running_mean is not None  # plan() refuses a BatchNorm without running statistics
        assert m.running_var is not None
        g32 = g.float()
        if m.weight is not None and m.weight.requires_grad:
            xhat = (x.float() - m.running_mean[None, :, None, None]) * torch.rsqrt(m.running_var + m.eps)[None, :, None,
                                                                                                           None]
            out["weight"] = (g32 * xhat).sum((0, 2, 3))
        if m.bias is not None and m.bias.requires_grad:
            out["bias"] = g32.sum((0, 2, 3))
    return out

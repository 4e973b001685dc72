"""Keeping online fine-tuning inside what its labels can support: the map's units met without being learnt
(:class:`ScaleAlignment`, ``adapt.scale``), the encoder's share of the rate, a trust region on each step, and a
weight average that predicts while training goes on.

The paper trains every weight with one Adam rate (1e-3). Adam moves each weight by about ``lr`` per step whatever
the weight's size, so the same rate is a 1 % nudge to one layer and a 20 % rewrite of another, and a batch of one
or two keyframes has nothing to say about most of them. All three settings are off in ``configs/paper.yaml``
(the paper's method, unchanged); ``configs/default.yaml`` uses the trust region (README "Adapting without picking
a rate", which also gives what the other two did on the shared windows):

- ``adapt.encoder_lr``: the encoder's rate as a share of ``adapt.lr`` (two Adam parameter groups);
- ``adapt.trust``: after each Adam step, a parameter tensor whose update ``Δ`` is longer than ``trust·‖θ‖`` is
  moved only that far along it (``θ ← θ_old + Δ · trust‖θ_old‖/‖Δ‖``), a per-tensor trust region as in LARS/LAMB
  (You et al. 2017, 2020) applied to the step Adam proposes; Adam's moments are left as they are;
- ``adapt.average``: Polyak/EMA weight averaging (as a "mean teacher", Tarvainen & Valpola 2017): the network
  everything else reads — L_val, culling, the evaluation, the saved model — is, between batches,
  ``avg ← a·avg + (1 − a)·θ`` updated after each batch, while the optimiser keeps its own θ and trains on from it.
"""

from __future__ import annotations

import torch
from torch import nn

from mutualslam_cli.adapt.losses import label_scale


def param_groups(net: nn.Module, params: list[torch.Tensor], lr: float, encoder_lr: float) -> list[dict]:
    """Adam parameter groups: the encoder's trainable ``params`` at ``lr·encoder_lr``, the rest at ``lr``
    (one group when ``encoder_lr`` is 1)."""
    if encoder_lr == 1.0:
        return [{"params": params, "lr": lr}]
    enc = {id(p) for n, p in net.named_parameters() if n.startswith("encoder.")}
    groups = [{"params": [p for p in params if id(p) in enc], "lr": lr * encoder_lr},
              {"params": [p for p in params if id(p) not in enc], "lr": lr}]
    return [g for g in groups if g["params"]]


class TrustRegion:
    """Bounds each parameter tensor's step to ``radius·‖θ‖`` (module docstring). Use: ``before()`` ahead of the
    optimiser's step, ``after()`` behind it.

    Args:
        params: the trained tensors. radius: the bound, a share of each tensor's norm (> 0).
    """

    def __init__(self, params: list[torch.Tensor], radius: float) -> None:
        self.params, self.radius = params, float(radius)
        self._old: list[torch.Tensor] | None = None
        self.clipped: list[float] = []  # per step: the share of tensors whose step was cut

    @torch.no_grad()
    def before(self) -> None:
        """Remember θ before the step."""
        if self._old is None:
            self._old = [p.detach().clone() for p in self.params]
        else:
            torch._foreach_copy_(self._old, [p.detach() for p in self.params])

    @torch.no_grad()
    def after(self) -> None:
        """Cut each tensor's step back to the trust radius where it is longer."""
        assert self._old is not None, "TrustRegion.after() without before()"
        ps = [p.detach() for p in self.params]
        delta = torch._foreach_sub(ps, self._old)
        step = torch.stack(torch._foreach_norm(delta))
        size = torch.stack(torch._foreach_norm(self._old))
        factor = torch.clamp(self.radius * size / step.clamp_min(1e-30), max=1.0)
        self.clipped.append(float((factor < 1.0).float().mean()))
        cut = (factor < 1.0).nonzero().flatten().tolist()
        if not cut:
            return
        f = factor.tolist()
        moved = [delta[i] for i in cut]  # θ_old + f·Δ, in place in Δ's buffers
        torch._foreach_mul_(moved, [f[i] for i in cut])
        torch._foreach_add_(moved, [self._old[i] for i in cut])
        torch._foreach_copy_([ps[i] for i in cut], moved)


class WeightAverage:
    """The predicting network as an average of the trained one's weights after each batch (module docstring).

    The network's parameters hold the average between batches; :meth:`to_trained` puts the optimiser's own
    weights back before a batch's first step, :meth:`to_average` folds them in after its last.

    Args:
        params: the trained tensors (the network's own, as the optimiser holds them). decay: ``a`` in [0, 1).
    """

    def __init__(self, params: list[torch.Tensor], decay: float) -> None:
        self.params, self.decay = params, float(decay)
        self.average = [p.detach().clone() for p in params]
        self.trained = [p.detach().clone() for p in params]
        self.holds_average = True

    @torch.no_grad()
    def to_trained(self) -> None:
        """Before a batch: the optimiser's weights into the network."""
        if self.holds_average:
            torch._foreach_copy_([p.detach() for p in self.params], self.trained)
            self.holds_average = False

    @torch.no_grad()
    def to_average(self) -> None:
        """After a batch: keep the trained weights, fold them into the average, and predict with the average."""
        if self.holds_average:
            return
        ps = [p.detach() for p in self.params]
        torch._foreach_copy_(self.trained, ps)
        torch._foreach_lerp_(self.average, self.trained, 1.0 - self.decay)
        torch._foreach_copy_(ps, self.average)
        self.holds_average = True


class ScaleAlignment:
    """``adapt.scale``: how a batch's predicted depth meets the map's units before the losses
    (:func:`~mutualslam_cli.adapt.losses.label_scale`).

    ``learn``: as it is (the paper); ``align``: each image scaled to its map points; ``align_batch``: the batch by
    one factor; ``calibrate``: by the first trained keyframe's factor while that batch lasts, then as it is. The
    factor of a batch's newest image on its first step is folded into the network's ``unit`` at the batch's end,
    so what reads the network's depth gets map units.
    """

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self._factor: float | None = None  # the newest keyframe's map units per network unit, until end_batch
        self._calibrated = False

    def apply(self, depth: torch.Tensor, uv: torch.Tensor, d: torch.Tensor, mask: torch.Tensor,
              newest: bool = False) -> torch.Tensor:
        """``depth`` ``(B, 1, H, W)`` scaled as the mode asks; ``newest``: a batch's first step."""
        if self.mode == "learn":
            return depth
        if self.mode == "calibrate":
            if newest and not self._calibrated:
                self._factor = float(label_scale(depth[:1], uv[:1], d[:1], mask[:1])[0].detach())
                self._calibrated = True
            return depth if self._factor is None else depth * self._factor
        s = label_scale(depth, uv, d, mask, pooled=self.mode == "align_batch")
        if newest:
            self._factor = float(s[0].detach())
        return depth * s.view(-1, 1, 1, 1)

    @torch.no_grad()
    def end_batch(self, net: nn.Module) -> None:
        """Fold the batch's factor into ``net.unit`` (a network without one keeps its units)."""
        unit = getattr(net, "unit", None)
        if self._factor is not None and isinstance(unit, torch.Tensor):
            unit.mul_(self._factor)
        self._factor = None

"""What online fine-tuning does to the network, keyframe by keyframe: ``keyframes.csv``'s ``health_*`` columns.

Training lowers its own losses while the depth it predicts can still go wrong where no loss looks: pixels far
beyond the scene (the sigmoid disparity driven to 0 in texture-poor or occluded regions), a disparity range that
collapses, a scale that drifts away from the map's, weights that wander from the pre-trained ones. One
:class:`HealthMonitor` per adapter measures these on every trained keyframe, from tensors the step computes anyway
(the batch's first forward pass and gradients) plus, at the batch's end, the distance of the weights from where
the run started:

- ``health_far``: share of the newest keyframe's pixels whose predicted depth is more than 3× its median depth
  (outliers that a per-frame least-squares scale chases, ``lsq`` PCD, while a median scale ignores them);
- ``health_disp_range``: 95th / 5th percentile of its predicted disparity (``1/depth``): how much structure the
  map holds (1 = a flat wall);
- ``health_label_scale``: median over the keyframe's map points of ``D_sparse / D``: the map's units per unit of
  predicted depth (the sparse loss pulls it to 1), and ``health_label_spread`` the median ``|log|`` of that ratio
  about its median (how well the predicted depth's shape follows the map's);
- ``health_grad_enc``, ``health_grad_dec``: L2 norm of ∂L_train/∂θ over the encoder's and the decoder's
  parameters on the batch's first step;
- ``health_drift_enc``, ``health_drift_dec``: ``‖θ − θ₀‖ / ‖θ₀‖`` of each part after the batch, θ₀ the weights the
  adapter started from.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from mutualslam_cli.adapt.losses import sample_depth

#: A pixel deeper than this many times its frame's median depth counts in ``health_far``.
FAR_FACTOR = 3.0


def _group(name: str) -> str:
    return "enc" if name.startswith("encoder.") else "dec"


class HealthMonitor:
    """Per-keyframe health figures of an adapting network (module docstring).

    Args:
        net: the network being trained; its trainable parameters at construction are θ₀.
    """

    def __init__(self, net: nn.Module) -> None:
        named = [(n, p) for n, p in net.named_parameters() if p.requires_grad]
        self.params = {g: [p for n, p in named if _group(n) == g] for g in ("enc", "dec")}
        self.start = {g: [p.detach().clone() for p in ps] for g, ps in self.params.items()}
        self.start_norm = {g: _norm(ps) for g, ps in self.start.items()}

    @torch.no_grad()
    def of_prediction(self, depth: torch.Tensor, uv: torch.Tensor, d: torch.Tensor,
                      mask: torch.Tensor) -> dict[str, float]:
        """Figures of one keyframe's predicted depth.

        Args:
            depth: ``(1, 1, H, W)`` predicted depth. uv: ``(1, M, 2)`` its map points' pixels at that size.
            d: ``(1, M)`` their depths (map units). mask: ``(1, M)`` valid entries.

        Returns:
            ``{"far", "disp_range", "label_scale", "label_spread"}`` (NaN scale figures without map points).
        """
        z = depth.detach().float().flatten()
        med = z.median()
        disp = 1.0 / z.clamp_min(1e-6)
        lo, hi = torch.quantile(disp, torch.tensor([0.05, 0.95], device=disp.device)).tolist()
        out = {"far": float((z > FAR_FACTOR * med).float().mean()), "disp_range": hi / max(lo, 1e-12),
               "label_scale": math.nan, "label_spread": math.nan}
        m = mask.bool() & (d > 0)
        if bool(m.any()):
            pred = sample_depth(depth.detach().float(), uv.float())[m]
            ratio = d.float()[m] / pred.clamp_min(1e-6)
            scale = ratio.median()
            out["label_scale"] = float(scale)
            out["label_spread"] = float((ratio / scale).log().abs().median())
        return out

    @torch.no_grad()
    def of_gradients(self) -> dict[str, float]:
        """``{"grad_enc", "grad_dec"}``: the parameters' current ``.grad`` norms (0 where none)."""
        return {f"grad_{g}": _norm([p.grad for p in ps if p.grad is not None]) for g, ps in self.params.items()}

    @torch.no_grad()
    def of_weights(self) -> dict[str, float]:
        """``{"drift_enc", "drift_dec"}``: ``‖θ − θ₀‖ / ‖θ₀‖`` of each part now."""
        out = {}
        for g, ps in self.params.items():
            diff = torch._foreach_sub([p.detach() for p in ps], self.start[g]) if ps else []
            out[f"drift_{g}"] = _norm(diff) / max(self.start_norm[g], 1e-12)
        return out


def _norm(tensors: Sequence[torch.Tensor]) -> float:
    """L2 norm of the concatenation of ``tensors`` (0 for none)."""
    if not tensors:
        return 0.0
    return float(torch.linalg.vector_norm(torch.stack(torch._foreach_norm([t.float() for t in tensors]))))

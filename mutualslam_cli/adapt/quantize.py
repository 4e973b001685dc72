"""Post-training int8 quantisation of the depth network for OpenVINO (CPUs without bf16).

Most users' CPUs have AVX2 but no bf16 (DESIGN §10). ``net.runtime: openvino-int8`` runs the frozen
network in int8 through OpenVINO there (not ``auto``'s choice: it moves an adapted model's PCD by 1–18 points,
:mod:`~mutualslam_cli.adapt.inference`): every convolution's input gets a per-tensor asymmetric
``uint8`` fake-quantiser whose range is calibrated on a few frames, and its weights a
per-output-channel symmetric ``int8`` one (``scale_c = max|W_c| / 127``). ``openvino.convert_model``
turns both into ``FakeQuantize`` operations and OpenVINO's low-precision transformations run
those convolutions on int8 kernels.

Convolutions listed in :data:`KEEP_FP32` stay fp32, chosen by measurement on an adapted model
(icl_lr_kt2, replay+ewc; 16 frames; error = mean / p99 of |log D − log D_fp32| after per-frame
median alignment; OpenVINO bf16 for comparison: 0.10 % / 0.43 %):

- every convolution int8: 1.5 % / 9.3 % — and adapted PCD on icl_lr_kt2 fell 1.5 points;
- the first convolution (raw normalised RGB) and the full-resolution decoder (upconv 0 and the
  scale-0 disparity head: 16 channels, where int8 saves nothing and adds reorders) kept: the same;
- one layer at a time showed why: the decoder's convolutions whose input is an ELU output with a
  long tail (a per-tensor range up to 40–100 for values mostly in [−1, 2]) lose most; keeping
  decoder modules 2, 4, 5 and 7 too brings it to 0.19 % / 1.2 % (tum_fr1_xyz 0.25 % / 0.95 %).
  Percentile ranges instead of min/max did not help (0.9999: 1.0 %, 0.99: 7 %).

So the encoder (all but its first layer) and the decoder's low-resolution blocks run int8. Speed
here (AVX512 with VNNI, 640×192, 2 threads): 52 ms against PyTorch fp32 ~110 ms and OpenVINO bf16
45 ms; on AVX2 it is to be measured (``make bench`` names the flags).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from mutualslam_cli.adapt.depthnet import predictor
from mutualslam_cli.errors import ShapeError

#: A forward pre-hook: the module and its positional inputs.
_PreHook = Callable[[nn.Module, tuple[torch.Tensor, ...]], None]

#: Convolutions (module-name prefixes of :class:`~mutualslam_cli.adapt.depthnet.DepthNet`) kept in fp32:
#: the encoder's first layer; the decoder's upconv (3, 0), (2, 0), (2, 1), (1, 1) (modules 2, 4, 5, 7),
#: full-resolution blocks upconv (0, 0), (0, 1) (8, 9) and scale-0 disparity head (10).
KEEP_FP32 = ("encoder.encoder.conv1",) + tuple(f"decoder.decoder.{i}." for i in (2, 4, 5, 7, 8, 9, 10))


def calibrate(net: nn.Module, images: torch.Tensor) -> dict[str, tuple[float, float]]:
    """Range of every convolution's input over ``images``.

    Args:
        net: a depth network with ``predict`` (eval mode is set for the pass and restored).
        images: ``(N, 3, H, W)`` float32 in [0, 1], the calibration frames.

    Returns:
        ``{conv module name: (min, max)}`` for the convolutions the forward pass runs.
    """
    if images.ndim != 4 or images.shape[0] == 0:
        raise ShapeError(f"calibrate: expected (N ≥ 1, 3, H, W) images, got {tuple(images.shape)}")
    ranges: dict[str, tuple[float, float]] = {}

    def hook(name: str) -> _PreHook:
        def record(_m: nn.Module, inputs: tuple[torch.Tensor, ...]) -> None:
            lo, hi = float(inputs[0].min()), float(inputs[0].max())
            old = ranges.get(name, (lo, hi))
            ranges[name] = (min(old[0], lo), max(old[1], hi))
        return record

    handles = [m.register_forward_pre_hook(hook(n)) for n, m in net.named_modules() if isinstance(m, nn.Conv2d)]
    was_training = net.training
    try:
        net.eval()
        with torch.no_grad():
            for i in range(images.shape[0]):  # one frame at a time: memory flat in N
                predictor(net)(images[i:i + 1].float())
    finally:
        net.train(was_training)
        for h in handles:
            h.remove()
    return ranges


class _QuantConv(nn.Module):
    """A convolution with fake-quantised input (uint8, per tensor) and weights (int8, per channel)."""

    w_scale: torch.Tensor  # buffers, registered in __init__
    w_zero: torch.Tensor

    def __init__(self, conv: nn.Conv2d, lo: float, hi: float):
        super().__init__()
        self.conv = conv
        lo, hi = min(lo, 0.0), max(hi, 0.0)  # zero must be exact (padding, ReLU)
        self.scale = max(hi - lo, 1e-8) / 255.0
        self.zero_point = int(round(-lo / self.scale))
        w = conv.weight.detach()
        self.register_buffer("w_scale", (w.abs().amax((1, 2, 3)) / 127.0).clamp_min(1e-12))
        self.register_buffer("w_zero", torch.zeros(w.shape[0], dtype=torch.int32, device=w.device))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.conv
        xq = torch.fake_quantize_per_tensor_affine(x, self.scale, self.zero_point, 0, 255)
        wq = torch.fake_quantize_per_channel_affine(c.weight, self.w_scale, self.w_zero, 0, -128, 127)
        return F.conv2d(xq, wq, c.bias, c.stride, c.padding, c.dilation, c.groups)


def fake_quantized(net: nn.Module, ranges: dict[str, tuple[float, float]],
                   keep_fp32: tuple[str, ...] = KEEP_FP32) -> nn.Module:
    """A copy of ``net`` (eval mode, no gradients) whose convolutions are fake-quantised.

    Args:
        net: the depth network (not modified).
        ranges: :func:`calibrate`'s input ranges; convolutions without one stay fp32.
        keep_fp32: module-name prefixes left in fp32.

    Returns:
        The copy, ready for ``openvino.convert_model`` (in PyTorch it simulates the int8 rounding).
    """
    q = copy.deepcopy(net).eval().requires_grad_(False)
    for name, module in list(q.named_modules()):
        for child_name, child in list(module.named_children()):
            full = f"{name}.{child_name}" if name else child_name
            if isinstance(child, nn.Conv2d) and full in ranges and not full.startswith(keep_fp32):
                setattr(module, child_name, _QuantConv(child, *ranges[full]))
    return q

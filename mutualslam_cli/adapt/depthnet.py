"""The depth network wrapper (Monodepth2 ResNet-18 + decoder) and its fast path.

Fast path (DESIGN §10): mixed precision for the network and channels-last memory format; on the CPU
bf16 autocast, gated on a CPU that really runs bf16 (AVX512-BF16 or AMX); on CUDA bf16 or fp16
autocast (:mod:`mutualslam_cli.device`). Losses stay in fp32 (:mod:`mutualslam_cli.adapt.losses`
casts its inputs). The network's device is where its parameters are (:func:`prepare` moves them);
:func:`predict_depth` sends its input there and brings the depth back to the CPU.

**Where precision breaks the adaptation** (issue 46, measured on an AMX Xeon, replay+ewc, the shared
windows). Master weights, Adam's moments, the regularisers' importance and the losses are fp32 throughout.
What bf16 changed was the trained model: (1) the decoder's in-place ELU zeroed gradients
(:class:`~mutualslam_cli.adapt.networks.depth_decoder.ConvBlock`, fixed: out of place); (2) with the encoder's
forward and backward in bf16 the adapted model ended 6.3 PCD points (lsq) away from fp32's on icl_lr_kt2
(47.3 vs 41.0) and 2.5 on tum_fr1_xyz — by a systematic change, not noise: fp32 with ×(1 + 0.03·N(0, 1))
noise on every gradient entry, or the learning rate moved by 1e-5, stayed within 0.8 of fp32, while
bf16 in any part of the encoder (conv1 + layer1 only, or layers 2–4 only) moved it by 7–10 points. With the
encoder in fp32 and the rest in bf16: 40.5 vs 41.0 and 41.5 vs 42.6. So by default the encoder trains in
fp32 inside the fast path (its gradients are taken with autocast off; predictions without gradients stay
all-bf16), the decoder in bf16: a step costs 422 ms against 309 all-bf16 and 583 fp32 (one interleaved
probe, 2 threads). ``net.fast_train: all`` keeps the encoder in bf16 too (the fastest, not fp32's model).
"""

from __future__ import annotations

import contextlib
import functools
import logging
from collections.abc import Callable, Iterable, Iterator
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt.networks import DepthDecoder, ResnetEncoder
from mutualslam_cli.device import autocast, module_device
from mutualslam_cli.errors import ConfigError, ShapeError

log = logging.getLogger(__name__)


def disp_to_depth(disp: torch.Tensor, min_depth: float, max_depth: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Convert the network's sigmoid output to depth (Monodepth2, Godard et al. 2019, ``disp_to_depth``).

    ``scaled = 1/max_depth + (1/min_depth − 1/max_depth)·disp``, ``depth = 1/scaled``.

    Args:
        disp: sigmoid output in [0, 1], any shape.
        min_depth: depth at ``disp = 1`` (metres / map units).
        max_depth: depth at ``disp = 0``.

    Returns:
        ``(scaled_disp, depth)``, both the shape of ``disp``.
    """
    min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
    scaled = min_disp + (max_disp - min_disp) * disp
    return scaled, 1.0 / scaled


class DepthNet(nn.Module):
    """Monodepth2 depth network: RGB in [0, 1] → sigmoid disparity → depth.

    The decoder always owns the four ``dispconv`` heads so that released Monodepth2 files
    load key-for-key; ``scales`` only selects which disparities :meth:`forward_scales`
    computes (default scale 0 only: no multi-scale cost).

    Args:
        min_depth: ``disp_to_depth`` minimum (Monodepth2: 0.1).
        max_depth: ``disp_to_depth`` maximum (Monodepth2: 100).
        scales: output scales of :meth:`forward_scales`.
        num_layers: ResNet depth (18 for the released models).
    """

    #: The size the loaded weights were trained at (:func:`~mutualslam_cli.adapt.weights.load_depthnet` sets them).
    feed_height: int | None
    feed_width: int | None
    unit: torch.Tensor

    def __init__(self, min_depth: float = 0.1, max_depth: float = 100.0, scales: Iterable[int] = (0,),
                 num_layers: int = 18):
        super().__init__()
        if not 0 < min_depth < max_depth:
            raise ConfigError(f"DepthNet: need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.scales = tuple(scales)
        if any(s not in range(4) for s in self.scales):
            raise ConfigError(f"DepthNet: scales must be in 0..3, got {self.scales}")
        with torch.device("cpu"):  # built on the CPU (where weights are loaded); :func:`prepare` moves it
            self.encoder = ResnetEncoder(num_layers)
            self.decoder = DepthDecoder(self.encoder.num_ch_enc, scales=range(4))
        # map units per unit of the network's depth (adapt.scale = align keeps it; 1 otherwise): a constant, not a
        # weight, and not saved with them
        self.register_buffer("unit", torch.ones((), device="cpu"), persistent=False)
        self.channels_last = False
        self.bf16_encoder = False  # :func:`prepare`: encoder gradients under mixed precision too (module docstring)

    def _check(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ShapeError(f"DepthNet: expected input (B, 3, H, W), got {tuple(x.shape)}")
        if x.shape[2] % 32 or x.shape[3] % 32 or min(x.shape[2:]) < 64:
            raise ShapeError(f"DepthNet: H and W must be multiples of 32 and ≥ 64, got {tuple(x.shape[2:])}")
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def forward_scales(self, x: torch.Tensor, scales: Iterable[int] | None = None) -> dict[int, torch.Tensor]:
        """Sigmoid disparities ``{s: (B, 1, H/2**s, W/2**s)}`` float32 for ``scales`` (default ``self.scales``)."""
        x = self._check(x)
        out = self.decoder(self._encode(x), self.scales if scales is None else scales)
        return {s: d.float().contiguous() for s, d in out.items()}

    def _encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The encoder's five feature maps; in full precision inside a mixed-precision region when gradients are
        taken and :attr:`bf16_encoder` is off (module docstring: where precision breaks the adaptation)."""
        dev = x.device.type
        if not self.bf16_encoder and torch.is_grad_enabled() and torch.is_autocast_enabled(dev):
            with torch.autocast(dev, enabled=False):
                return self.encoder(x.float())
        return self.encoder(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Sigmoid disparity at scale 0.

        Args:
            x: ``(B, 3, H, W)`` RGB in [0, 1]; H, W multiples of 32, ≥ 64 (reflection padding
                at stride 32 needs ≥ 2 cells).

        Returns:
            ``(B, 1, H, W)`` float32 in (0, 1) (float32 even under bf16 autocast).
        """
        return self.forward_scales(x, (0,))[0]

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        """Differentiable depth ``(B, 1, H, W)`` = ``disp_to_depth(forward(x))[1]`` times :attr:`unit`."""
        return disp_to_depth(self.forward(x), self.min_depth, self.max_depth)[1] * self.unit


@functools.lru_cache(maxsize=1)
def fast_path_supported() -> bool:
    """True when this CPU runs bf16 natively (AVX512-BF16 / AMX) and a bf16 matmul works.

    Checks oneDNN availability, its bf16 support flag and that a real bf16 matmul and a
    small autocast convolution agree with fp32 to bf16 precision. Cached.
    """
    try:
        if not torch.backends.mkldnn.is_available():
            return False
        probe = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
        if probe is not None and not probe():
            return False
        cpu = torch.device("cpu")  # a probe of this CPU's kernels
        g = torch.Generator(device=cpu).manual_seed(0)
        a, b = torch.randn(64, 64, generator=g, device=cpu), torch.randn(64, 64, generator=g, device=cpu)
        ref = a @ b
        got = (a.bfloat16() @ b.bfloat16()).float()
        if not torch.isfinite(got).all() or (got - ref).abs().max() > 0.05 * ref.abs().max():
            return False
        conv = nn.Conv2d(3, 4, 3, device=cpu)
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            y = conv(torch.randn(1, 3, 8, 8, generator=g, device=cpu))
        return y.dtype == torch.bfloat16
    except Exception as exc:  # any failure means "not usable"
        log.info("bf16 fast path unavailable: %s", exc)
        return False


def resolve_fast(mode: str | bool) -> bool:
    """``NetConfig.fast`` (``auto`` | ``on`` | ``off`` or a bool) → whether to use the fast path."""
    if isinstance(mode, bool):
        return mode
    if mode == "auto":
        return fast_path_supported()
    if mode in ("on", "off"):
        return mode == "on"
    raise ConfigError(f"net.fast: expected auto, on or off, got {mode!r}")


@contextlib.contextmanager
def fast_context(enabled: bool, device: torch.device | str = "cpu") -> Iterator[None]:
    """Mixed precision on ``device`` when ``enabled`` (CPU: bf16; CUDA: bf16 or fp16,
    :func:`mutualslam_cli.device.autocast`), else nothing.

    Use it around the network's forward pass only; the losses run in fp32 regardless.
    """
    with autocast(torch.device(device), enabled):
        yield


def prepare(net: DepthNet, fast: bool, channels_last: bool | None = None,
            device: torch.device | str | None = None, bf16_encoder: bool = False) -> DepthNet:
    """Put ``net`` on ``device`` (default: where it is) in the memory format of the chosen path (in place;
    returns ``net``).

    Args:
        net: the network.
        fast: the mixed-precision fast path will be used (see :func:`fast_context`).
        channels_last: channels-last weights and inputs (oneDNN's and the tensor cores' preferred layout;
            also ~1.3× faster in fp32 on this CPU, mostly through max-pool); default: ``fast``.
        device: where the network runs (:mod:`mutualslam_cli.device`).
        bf16_encoder: take the encoder's gradients under mixed precision too (``net.fast_train: all``); default:
            the encoder trains in fp32 inside the fast path and only predicts in mixed precision (module docstring).
    """
    cl = bool(fast) if channels_last is None else bool(channels_last)
    if device is not None:
        net.to(torch.device(device))
    # torch's stubs lack Module.to(memory_format=), which it has at run time
    net.to(memory_format=torch.channels_last if cl else torch.contiguous_format)  # type: ignore[call-overload]
    net.channels_last = cl
    if isinstance(net, DepthNet):
        net.bf16_encoder = bool(bf16_encoder)
    return net


def _to_batch(images: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor:
    """``images`` as a ``(B, 3, H, W)`` float batch in [0, 1] on ``device`` (moved before the conversion)."""
    t = images if isinstance(images, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(images))
    t = t.to(device, non_blocking=True)
    if t.dim() == 3 and t.shape[-1] == 3:  # (H, W, 3) image
        t = t.permute(2, 0, 1)[None]
    elif t.dim() == 4 and t.shape[-1] == 3 and t.shape[1] != 3:  # (B, H, W, 3)
        t = t.permute(0, 3, 1, 2)
    if t.dim() != 4 or t.shape[1] != 3:
        raise ShapeError(f"predict_depth: expected (B, 3, H, W), (B, H, W, 3) or (H, W, 3), got {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        return (t.float() / 255.0).contiguous()
    return t.float().contiguous()


def predict_depth(net: nn.Module, images: np.ndarray | torch.Tensor, fast: bool = False) -> np.ndarray:
    """Inference helper: depth maps as numpy, no gradient, eval mode restored afterwards.

    Args:
        net: a :class:`DepthNet` or any module with its ``predict`` (its H×W must be multiples of 32; the
            caller resizes); it runs where its parameters are, the images are sent there (as uint8 when given
            so: 4× less to transfer).
        images: ``(B, 3, H, W)`` / ``(B, H, W, 3)`` / ``(H, W, 3)``, uint8 (0–255) or float in [0, 1].
        fast: mixed precision (see :func:`fast_context`).

    Returns:
        ``(B, H, W)`` float32 depth in the network's units, on the CPU.
    """
    device = module_device(net)
    x = _to_batch(images, device)
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad(), fast_context(fast, device):
            depth = predictor(net)(x)
    finally:
        net.train(was_training)
    return depth[:, 0].float().cpu().numpy()


def make_adam(params: Iterable[torch.Tensor] | Iterable[dict[str, Any]], lr: float = 1e-3,
              **kwargs: Any) -> torch.optim.Adam:
    """Adam with the fused kernel (CPU or CUDA, where the parameters are) when available (≈4× faster step
    for the 15 M parameters on the CPU). ``params``: tensors, or parameter groups (dicts with their own ``lr``).

    Same update rule as ``torch.optim.Adam``; falls back to the default implementation.
    """
    groups: list[Any] = list(params)
    try:
        return torch.optim.Adam(groups, lr=lr, fused=True, **kwargs)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(groups, lr=lr, **kwargs)


def predictor(net: nn.Module) -> Callable[[torch.Tensor], torch.Tensor]:
    """``net.predict``: ``(B, 3, H, W)`` RGB in [0, 1] → ``(B, 1, H, W)`` depth, of a :class:`DepthNet` or any
    module with that method (typed: ``nn.Module`` attribute lookup gives a tensor or a module)."""
    return cast(Callable[[torch.Tensor], torch.Tensor], net.predict)


#: The encoder's stages in forward order (:class:`~mutualslam_cli.adapt.networks.resnet_encoder.ResnetEncoder`).
ENCODER_STAGES = (("conv1", "bn1"), ("layer1",), ("layer2",), ("layer3",), ("layer4",))


def freeze_encoder_stages(net: DepthNet, n: int) -> int:
    """Stop training the first ``n`` encoder stages (``requires_grad = False``); returns the parameters frozen.

    Autograd then does not backpropagate into those stages at all (the input needs no gradient either),
    which saves their backward pass — the costliest part of a step, at the highest resolution."""
    frozen = 0
    for stage in ENCODER_STAGES[:n]:
        for name in stage:
            for p in getattr(net.encoder.encoder, name).parameters():
                p.requires_grad_(False)
                frozen += p.numel()
    return frozen

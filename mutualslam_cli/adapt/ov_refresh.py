"""An OpenVINO depth predictor that takes new weights without a new conversion (online scores, DESIGN §10).

The online scores (:mod:`~mutualslam_cli.online.scores`) predict with the model of each frame's time, so
the network changes between every two keyframes. :func:`~mutualslam_cli.adapt.inference.openvino_predictor`
converts the network from scratch (``openvino.convert_model``: 1.9 s for Monodepth2-R18 at 640×192 on one
AMD EPYC core), far more than the frames of one model save. Here the network is converted *once* and every
later model only replaces the converted graph's weight constants and recompiles:

1. the encoder's BatchNorms (eval mode: a per-channel affine map) are folded into the convolutions before
   them, in PyTorch (:func:`folded_tensors`), so that every weight constant of the converted graph is one
   tensor of that folded network, byte for byte (the converter would fold them itself, into constants that
   match nothing of the module);
2. the folded copy is converted with a distinct seeded random tag in every weight (equal weights, such as the
   zero biases of a fresh network, could not be told apart, and the converter could drop a zero bias), and
   each ``f32`` constant is matched to the tensor whose tag it holds; every tensor the forward pass uses must
   match exactly one constant, else :class:`RefreshablePredictor` refuses (:class:`NotRefreshable`) and the
   caller keeps the torch path;
3. :meth:`RefreshablePredictor.refresh` folds the current network again, swaps the constants for the new
   tensors and compiles (the compiled model copies the weights into its own layout).

Measured on AMD EPYC with AVX512-BF16 (no AMX), 1 thread, loaded host, 640×192: refresh (fold 37 ms +
compile 171 ms) ≈ 0.2 s; 6 frames 406–437 ms through OpenVINO bf16 against 638–731 ms through PyTorch bf16
autocast. Mean relative depth change against PyTorch fp32 with the same new weights: 0.29 % (OpenVINO bf16)
against 0.73 % (PyTorch bf16 autocast); :data:`BF16_REL_TOL` is the bound the tests hold it to.
"""

from __future__ import annotations

import copy
import time
import warnings
from typing import Any

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt.depthnet import predictor
from mutualslam_cli.adapt.inference import _Predict, _without_telemetry, compile_for_cpu, openvino_precision
from mutualslam_cli.errors import NotRefreshable

CPU = torch.device("cpu")  # OpenVINO converts and runs on the CPU

#: Mean relative depth change ``mean |D − D_fp32| / D_fp32`` a bf16 prediction may have against PyTorch fp32
#: with the same weights (measured 0.29 % OpenVINO bf16, 0.73 % PyTorch bf16 autocast on a pre-trained model).
BF16_REL_TOL = 0.01


def _bn_pairs(net: nn.Module) -> list[tuple[str, str]]:
    """``(conv name, BatchNorm name)`` of every BatchNorm2d of ``net``, each after the convolution it follows
    (ResNet naming: ``…bnK`` after ``…convK``, ``…downsample.1`` after ``…downsample.0``)."""
    mods = dict(net.named_modules())
    pairs = []
    for name, m in mods.items():
        if not isinstance(m, nn.BatchNorm2d):
            continue
        head, _, leaf = name.rpartition(".")
        conv = f"{head}.0" if leaf == "1" and head.endswith("downsample") else \
            (f"{head}." if head else "") + leaf.replace("bn", "conv", 1)
        if not isinstance(mods.get(conv), nn.Conv2d):
            raise NotRefreshable(f"BatchNorm {name} follows no convolution named {conv}")
        pairs.append((conv, name))
    return pairs


def folded_tensors(net: nn.Module) -> dict[str, torch.Tensor]:
    """Every convolution's weight and bias with the BatchNorm after it folded in (eval-mode statistics).

    ``W' = W·γ/√(σ² + ε)`` per output channel, ``b' = (b − μ)·γ/√(σ² + ε) + β``; convolutions without a
    BatchNorm keep theirs. Returns ``{conv name + ".weight" | ".bias": float32 tensor}`` (contiguous, CPU)."""
    mods = dict(net.named_modules())
    bn_of = {conv: mods[bn] for conv, bn in _bn_pairs(net)}
    out: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        for name, m in mods.items():
            if not isinstance(m, nn.Conv2d):
                continue
            w = m.weight.detach().float().cpu()
            b = m.bias.detach().float().cpu() if m.bias is not None else None
            bn = bn_of.get(name)
            if bn is not None:
                scale = bn.weight.detach().float().cpu() * torch.rsqrt(bn.running_var.float().cpu() + bn.eps)
                w = w * scale[:, None, None, None]
                shift = bn.bias.detach().float().cpu()
                b = ((b if b is not None else 0.0) - bn.running_mean.float().cpu()) * scale + shift
            out[f"{name}.weight"] = w.contiguous()
            if b is not None:
                out[f"{name}.bias"] = b.contiguous()
    return out


def _folded_copy(net: nn.Module) -> nn.Module:
    """A CPU copy of ``net`` (eval mode) whose BatchNorms are folded into their convolutions (identity there)."""
    tensors = folded_tensors(net)
    q = copy.deepcopy(net).cpu().float().eval().requires_grad_(False)
    # torch's stubs lack Module.to(memory_format=), which it has at run time
    q.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload]
    mods = dict(q.named_modules())
    for conv, bn in _bn_pairs(q):
        c = mods[conv]
        if c.bias is None:
            c.bias = nn.Parameter(torch.zeros(c.out_channels, device=c.weight.device), requires_grad=False)
        head, _, leaf = bn.rpartition(".")
        setattr(mods[head] if head else q, leaf, nn.Identity())
    with torch.no_grad():
        for name, t in tensors.items():
            mod, _, attr = name.rpartition(".")
            getattr(mods[mod], attr).copy_(t)
    return q


class RefreshablePredictor:
    """OpenVINO prediction of a network whose weights change (module docstring).

    Args:
        net: a :class:`~mutualslam_cli.adapt.depthnet.DepthNet` (any device; its weights at construction
            are compiled: call :meth:`refresh` with each later model).
        width, height: network input size in pixels.
        threads: inference threads (default: torch's setting).

    Raises:
        NotRefreshable: a weight the forward pass uses has no constant of its own in the converted graph.
    """

    def __init__(self, net: nn.Module, width: int, height: int, threads: int | None = None) -> None:
        import openvino as ov

        self.threads = int(threads or torch.get_num_threads())
        self.precision = openvino_precision(int8=False)
        q = _folded_copy(net)
        used = _used_tensors(q, height, width)
        mods = dict(q.named_modules())
        g = torch.Generator(device=CPU).manual_seed(0)
        tags: dict[bytes, str] = {}
        with torch.no_grad():  # a distinct random tag in every weight: equal weights (zero biases) stay apart
            for name in sorted(used):
                mod, _, attr = name.rpartition(".")
                t = getattr(mods[mod], attr, None)
                if t is None:
                    continue
                t.copy_(torch.randn(t.shape, generator=g, device=CPU))
                tags[t.detach().contiguous().numpy().tobytes()] = name
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torch.jit.TracerWarning)
            _without_telemetry()
            self.model = ov.convert_model(_Predict(q), example_input=torch.rand(1, 3, height, width, device=CPU))
        self._slots: list[tuple[Any, str]] = []  # (openvino constant node, folded tensor name)
        seen: dict[str, int] = {}
        for op in self.model.get_ops():
            if op.get_type_name() != "Constant" or op.get_element_type() != ov.Type.f32:
                continue
            tag = tags.get(np.ascontiguousarray(op.get_data()).tobytes())
            if tag is not None:
                seen[tag] = seen.get(tag, 0) + 1
                self._slots.append((op, tag))
        bad = sorted(n for n in tags.values() if seen.get(n) != 1)
        if bad:
            raise NotRefreshable(f"{len(bad)} weights without exactly one constant in the converted graph: {bad[:4]}")
        self.refresh_s: list[float] = []
        self.refresh(net)  # the real weights (the first compilation)
        self.refresh_s.clear()

    def refresh(self, net: nn.Module) -> None:
        """Compile ``net``'s current weights (same architecture as at construction) in place of the old ones."""
        from openvino import opset13

        t = time.perf_counter()
        tensors = folded_tensors(net)
        slots = []
        for op, name in self._slots:
            new = opset13.constant(tensors[name].numpy().reshape(tuple(op.get_output_shape(0))), dtype=np.float32)
            for target in list(op.output(0).get_target_inputs()):
                target.replace_source_output(new.output(0))
            slots.append((new, name))
        self._slots = slots
        self._compiled = compile_for_cpu(self.model, self.threads, self.precision)
        self.refresh_s.append(time.perf_counter() - t)

    def __call__(self, x: torch.Tensor) -> np.ndarray:
        """``(B, 3, height, width)`` float32 in [0, 1] → ``(B, height, width)`` float32 depth (one frame a pass)."""
        x = x.detach().float().cpu()
        out = [self._compiled(x[i:i + 1].contiguous().numpy())[0] for i in range(len(x))]
        return np.concatenate(out)[:, 0].astype(np.float32)


def _used_tensors(net: nn.Module, height: int, width: int) -> set[str]:
    """Names (``conv.weight``/``conv.bias``) of the convolutions one forward pass of ``net.predict`` runs
    (Monodepth2's decoder owns disparity heads that scale 0 never uses)."""
    ran: set[str] = set()
    names = {id(m): n for n, m in net.named_modules()}
    handles = [m.register_forward_pre_hook(lambda mod, _x: ran.add(names[id(mod)]))
               for m in net.modules() if isinstance(m, nn.Conv2d)]
    try:
        with torch.no_grad():
            predictor(net)(torch.zeros(1, 3, height, width, device=CPU))
    finally:
        for h in handles:
            h.remove()
    return {f"{n}.{p}" for n in ran for p in ("weight", "bias")}

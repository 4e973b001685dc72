"""Depth prediction for evaluation through OpenVINO, where it beats PyTorch (DESIGN §10).

The frozen network of an evaluation (the pre-trained or the final adapted model) is converted
once (``openvino.convert_model``, ~2.5 s for Monodepth2-R18 at 640×192) and compiled for the CPU
with bf16 inference precision where the CPU runs bf16, else fp32. Measured on AMD EPYC with
AVX512-BF16 (2 threads, interleaved medians, 1 frame): PyTorch fp32 127 ms, PyTorch bf16 +
channels-last 64 ms, OpenVINO fp32 83 ms, **OpenVINO bf16 40 ms**; mean relative depth change
against PyTorch fp32 0.28 % (bf16), 4e-6 (fp32). Training keeps PyTorch (the network changes at
every step, so there is nothing to convert once).

On CPUs without bf16 (most users' AVX2 machines) ``auto`` is OpenVINO in fp32: the same depth as PyTorch
fp32 (4e-8 relative), 100 ms a frame against 130 through PyTorch on an AVX2-only EPYC (2 threads). The int8
path (``net.runtime: openvino-int8``: the network fake-quantised after calibration on a few frames,
:mod:`mutualslam_cli.adapt.quantize`, its convolutions on int8 kernels; 72 ms there) was ``auto``'s choice
there until its error was measured on *adapted* models (its bound was set on pre-trained ones): the same
adapted model's PCD (lsq / median / first quarter) through int8 against fp32 moved by −6.2 / +2.9 / −18.0
points (AVX2-only, tum_fr1_xyz, replay+ewc, seed 0) and +0.9 / +2.2 / −1.8 (AVX512-BF16, the same window),
where OpenVINO fp32 and bf16 stay within 0.05. A speed-up that changes the table's figures is not one.

``net.runtime``: ``auto`` (OpenVINO when it is installed, the network runs on the CPU and ``net.fast``
is not ``off``: bf16 where the CPU has it, else fp32; on a CUDA device the torch path on the GPU),
``torch``, ``openvino`` (the same choice of precision) or ``openvino-int8`` (an error when
OpenVINO is not installed). ``net.fast: off`` with ``auto`` keeps
the exact fp32 eager PyTorch path.
"""

from __future__ import annotations

import copy
import functools
import logging
import os
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from mutualslam_cli.adapt.depthnet import fast_path_supported, predictor
from mutualslam_cli.adapt.quantize import calibrate, fake_quantized
from mutualslam_cli.device import module_device
from mutualslam_cli.errors import ConfigError

log = logging.getLogger(__name__)


@functools.lru_cache(maxsize=1)
def openvino_available() -> bool:
    """True when the ``openvino`` package imports."""
    try:
        import openvino  # noqa: F401
    except Exception:  # any import failure means "not usable"
        return False
    return True


RUNTIMES = ("auto", "torch", "openvino", "openvino-int8")


def resolve_runtime(runtime: str, fast_mode: str, device: torch.device | str = "cpu") -> str:
    """``net.runtime``, ``net.fast`` (``auto|on|off``) and the network's device → ``"torch"``, ``"openvino"`` or
    ``"openvino-int8"`` (OpenVINO is the CPU's fast path: ``auto`` on a CUDA device is ``torch``)."""
    if runtime not in RUNTIMES:
        raise ConfigError(f"net.runtime: expected one of {', '.join(RUNTIMES)}, got {runtime!r}")
    if runtime == "auto" and torch.device(device).type != "cpu":
        return "torch"
    if runtime == "torch" or (runtime == "auto" and (fast_mode == "off" or not openvino_available())):
        return "torch"
    if not openvino_available():
        raise ConfigError(f"net.runtime={runtime}: the openvino package is not installed (pip install openvino)")
    return "openvino" if runtime == "auto" else runtime  # bf16 or fp32 (module docstring: int8 only when asked)


class _Predict(torch.nn.Module):
    """``(B, 3, H, W)`` RGB in [0, 1] → ``(B, 1, H, W)`` depth: what is converted."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return predictor(self.net)(x)


def _without_telemetry() -> None:
    """Turn off the usage telemetry of OpenVINO's model converter (``ov.convert_model``), for this process.

    Without a consent file the converter counts as opted in: every conversion starts one
    ``multiprocessing`` process per event to post to Google Analytics. In a spawned grid worker each
    of those re-imports the worker's modules (torch included) and takes a core for seconds: the
    evaluation of a 4-job grid with 2 workers ran 3× slower than with 1. A batch tool should not
    phone home either. The converter then uses OpenVINO's own no-op stand-in, the one it falls back
    to when the telemetry package is absent.
    """
    from openvino.tools.ovc import convert_impl, telemetry_stub, telemetry_utils

    convert_impl.tm = telemetry_stub
    telemetry_utils.tm = telemetry_stub


def openvino_precision(int8: bool) -> str:
    """OpenVINO's inference precision hint: ``bf16`` where the CPU runs bf16, else ``f32`` (also for int8 models:
    the fake-quantised convolutions run int8 whatever the hint; the rest stays fp32)."""
    return "f32" if int8 or not fast_path_supported() else "bf16"


def compile_for_cpu(model: Any, threads: int, precision: str) -> Any:
    """Compile an ``openvino.Model`` for the CPU with ``threads`` inference threads and ``precision``
    (:func:`openvino_precision`), latency hint; returns the compiled model (callable on numpy inputs)."""
    import openvino as ov

    # OpenVINO pins its threads to cores by default, the same first cores in every process: two grid
    # workers with one thread each then share one core (measured, 640×192 bf16, two processes at once:
    # 158 ms each pinned, 77 ms unpinned, 78 ms alone). Pin only when this process may use every core.
    return ov.Core().compile_model(model, "CPU", {
        "INFERENCE_NUM_THREADS": threads, "ENABLE_CPU_PINNING": threads >= (os.cpu_count() or 1),
        "INFERENCE_PRECISION_HINT": precision, "PERFORMANCE_HINT": "LATENCY"})


def openvino_predictor(net: torch.nn.Module, width: int, height: int, threads: int | None = None,
                       calibration: torch.Tensor | None = None) -> Callable[[torch.Tensor], np.ndarray]:
    """Compile ``net`` (eval mode, its current weights) for the CPU.

    Args:
        net: a :class:`~mutualslam_cli.adapt.depthnet.DepthNet` (weights are copied at conversion:
            later changes to ``net`` are not seen; a network on another device is copied to the CPU first).
        width, height: network input size in pixels.
        threads: inference threads (default: torch's setting).
        calibration: ``(N, 3, height, width)`` frames in [0, 1]: quantise to int8 with activation
            ranges from them (:mod:`~mutualslam_cli.adapt.quantize`); ``None``: bf16 where the CPU
            has it, else fp32.

    Returns:
        ``f(x)``: ``(B, 3, height, width)`` float32 in [0, 1] → ``(B, height, width)`` float32 depth;
        ``f.compiled`` is the OpenVINO compiled model.
    """
    import openvino as ov

    if module_device(net).type != "cpu":  # OpenVINO runs on the CPU: convert a CPU copy
        net = copy.deepcopy(net).cpu()
    if calibration is not None:
        calibration = calibration.cpu()
        net = fake_quantized(net, calibrate(net, calibration))
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape checks are constant at a fixed size
            _without_telemetry()
            model = ov.convert_model(_Predict(net), example_input=torch.rand(1, 3, height, width, device="cpu"))
    finally:
        net.train(was_training)
    precision = openvino_precision(int8=calibration is not None)
    compiled = compile_for_cpu(model, int(threads or torch.get_num_threads()), precision)
    log.info("depth evaluation through OpenVINO (%s)", "int8" if calibration is not None else precision)

    def predict(x: torch.Tensor) -> np.ndarray:
        out = [compiled(x[i:i + 1].contiguous().numpy())[0] for i in range(len(x))]  # static batch 1
        return np.concatenate(out)[:, 0].astype(np.float32)

    predict.compiled = compiled  # type: ignore[attr-defined]  # for inspection (runtime precisions)
    return predict

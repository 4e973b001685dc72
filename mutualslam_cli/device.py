"""Where the depth network runs (``device: auto | cpu | cuda[:N]``) and in what precision.

One :class:`torch.device` is resolved per run (:func:`resolve_device`, in
:func:`~mutualslam_cli.pipeline.run_sequence`) and handed to every object that owns network tensors:
the network itself (prediction, fine-tuning, EWC/MAS/SI importance, L_val, culling's and bridges' depth,
online scoring, evaluation, CoMoDa, Luo, dense fusion's depth). The VO, BA and the metrics stay on the CPU
(numpy / OpenCV); only frames going in and depth maps coming out cross over.

**Precision** (``net.fast``): on the CPU, bf16 autocast where the CPU runs bf16 (AVX512-BF16, AMX;
:func:`~mutualslam_cli.adapt.depthnet.fast_path_supported`). On CUDA, ``auto`` turns mixed precision on
where the GPU has tensor cores (:func:`amp_supported`): bf16 autocast where the GPU has it (Ampere and
later), else fp16 with a gradient scaler (:func:`grad_scaler`). Losses stay fp32 on both
(:mod:`~mutualslam_cli.adapt.losses`).

The CPU-side OpenVINO runtime stays the CPU's fast path for evaluation; on CUDA the evaluation runs
the torch path on the GPU (:func:`~mutualslam_cli.adapt.inference.resolve_runtime`).

**Reproducibility on CUDA** (:func:`configure`, ``deterministic: true``, the default):
``cudnn.deterministic = True`` (cuDNN picks only deterministic algorithms: some convolution backward
kernels are slower; NVIDIA's notes and PyTorch's reproducibility page put it at a few to ~30 % of a step,
depending on the layer shapes — not measured here, no GPU was at hand) and ``cudnn.benchmark = False``
(no autotuning: autotuning times the candidate algorithms on the first call of each shape and may pick
another one in the next process, so two runs of one seed could differ). ``deterministic: false`` turns
autotuning on for speed. Seeds are set by the run (``torch.manual_seed`` seeds CUDA too). One op is
left that cuDNN's flag does not cover: L_sparse samples the depth map with ``grid_sample``, whose CUDA
backward adds into the depth's gradient with atomics, so two runs of one seed on one GPU may differ at
float rounding (``torch.use_deterministic_algorithms`` would refuse that op rather than fix it). Across
GPU kinds, driver or cuDNN versions results differ at float rounding too, as CPU kinds do — which is
why results name their device (:func:`describe_device`) and reports never average runs of different
devices.

**Grids** (:func:`gpu_slots`, :func:`claim_gpu`): ``mslam ablate -j N`` on a machine with several GPUs
gives each worker process one GPU of its own through ``CUDA_VISIBLE_DEVICES``; the Dask executor asks
for a ``GPU`` resource per job instead (:mod:`~mutualslam_cli.ablate`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
from collections.abc import Iterator, Mapping
from typing import Protocol

import torch

from mutualslam_cli.config.checks import check_device_spec
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.machine import cpu_info, memory_gb
from mutualslam_cli.types import Scalar

log = logging.getLogger(__name__)


def resolve_device(spec: str = "auto") -> torch.device:
    """``device`` setting → :class:`torch.device` (``auto``: ``cuda`` when ``torch.cuda.is_available()``).

    Raises:
        ConfigError: a malformed value, ``cuda`` without a usable GPU (a CPU-only torch build, no driver),
            or ``cuda:N`` beyond the GPUs this process sees.
    """
    check_device_spec(spec)
    if spec == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    dev = torch.device(spec)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "a CPU-only torch build" if torch.version.cuda is None else "no usable CUDA device or driver"
            raise ConfigError(f"device: {spec}: CUDA is not available here ({why}); use device=cpu or auto "
                              "(README: installing the CUDA build of torch)")
        n = torch.cuda.device_count()
        index = dev.index if dev.index is not None else torch.cuda.current_device()
        if index >= n:
            raise ConfigError(f"device: {spec}: this process sees {n} GPU(s) (CUDA_VISIBLE_DEVICES narrows them)")
        dev = torch.device("cuda", index)
    return dev


def module_device(net: torch.nn.Module) -> torch.device:
    """The device of a module's first parameter (CPU for a module without parameters)."""
    for p in net.parameters():
        return p.device
    return torch.device("cpu")


def amp_supported(device: torch.device) -> bool:
    """Mixed precision pays on ``device``: a CUDA GPU with tensor cores (compute capability ≥ 7.0; on older GPUs,
    the paper's GTX 1070 among them, fp16 arithmetic is slower than fp32). CPUs: :func:`fast_path_supported`."""
    return device.type == "cuda" and torch.cuda.get_device_capability(device) >= (7, 0)


def amp_dtype(device: torch.device) -> torch.dtype:
    """The autocast dtype of the mixed-precision path on ``device``: bf16 on the CPU and on GPUs that run it,
    else fp16 (which needs :func:`grad_scaler` in training)."""
    if device.type == "cuda" and not torch.cuda.is_bf16_supported():
        return torch.float16
    return torch.bfloat16


@contextlib.contextmanager
def autocast(device: torch.device, enabled: bool) -> Iterator[None]:
    """Mixed precision (:func:`amp_dtype`) around the network's forward pass on ``device`` when ``enabled``."""
    if enabled:
        with torch.autocast(device.type, dtype=amp_dtype(device)):
            yield
    else:
        yield


def grad_scaler(device: torch.device, enabled: bool) -> torch.amp.GradScaler | None:
    """A gradient scaler when training runs in fp16 (a CUDA GPU without bf16), else ``None`` (fp32, bf16)."""
    if enabled and device.type == "cuda" and amp_dtype(device) == torch.float16:
        return torch.amp.GradScaler(device.type)
    return None


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (CUDA is asynchronous: a timer must wait before it reads)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def configure(device: torch.device, deterministic: bool = True) -> dict[str, bool]:
    """Set the cuDNN flags of a run on ``device`` (module docstring); returns what was set (for the manifest)."""
    if device.type != "cuda":
        return {}
    torch.backends.cudnn.deterministic = bool(deterministic)
    torch.backends.cudnn.benchmark = not deterministic
    cudnn = torch.backends.cudnn
    return {"cudnn_deterministic": cudnn.deterministic, "cudnn_benchmark": cudnn.benchmark}


def describe_device(device: torch.device) -> dict[str, Scalar]:
    """What a result records about the device it came from: ``device`` (``cpu`` / ``cuda:0``), ``device_type``,
    ``device_name`` (GPU name or CPU model), ``device_memory_gb`` and, on CUDA, ``cuda_version``,
    ``cudnn_version``, ``compute_capability``."""
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        return {"device": str(device), "device_type": "cuda", "device_name": props.name,
                "device_memory_gb": round(props.total_memory / 1024**3, 2), "cuda_version": torch.version.cuda,
                "cudnn_version": torch.backends.cudnn.version(), "compute_capability": f"{props.major}.{props.minor}"}
    cpu = cpu_info()
    return {"device": "cpu", "device_type": "cpu", "device_name": cpu["cpu_model"] or "unknown CPU",
            "device_memory_gb": memory_gb(), "cpu_kind": cpu["cpu_kind"], "cuda_version": torch.version.cuda,
            "cudnn_version": None}


def device_label(info: Mapping[str, object]) -> str:
    """Short name of a device for tables and averaging keys: ``cuda · NVIDIA H100 80GB HBM3``, ``cpu · AVX2``."""
    if info.get("device_type") == "cuda":
        return f"cuda · {info.get('device_name')}"
    return f"cpu · {info.get('cpu_kind', 'unknown')}"


# ----------------------------------------------------------------------------- grids: one job per GPU


def visible_gpus() -> list[str]:
    """The GPUs this process may use, as ``CUDA_VISIBLE_DEVICES`` names them (indices or UUIDs); ``[]`` without
    CUDA. With ``CUDA_VISIBLE_DEVICES`` set, its entries (as many as CUDA counts), else ``0 … count − 1``."""
    if not torch.cuda.is_available():
        return []
    n = torch.cuda.device_count()
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    names = [x.strip() for x in env.split(",") if x.strip()] if env else [str(i) for i in range(n)]
    return names[:n]


def gpu_slots(spec: str, workers: int) -> list[str]:
    """``CUDA_VISIBLE_DEVICES`` of each of ``workers`` grid workers, or ``[]`` to leave their environment alone.

    A grid whose network runs on CUDA (``device`` ``auto`` or ``cuda``) with several workers places one job per
    GPU: worker k sees only GPU ``k mod n`` (more workers than GPUs share them round robin). An explicit
    ``cuda:N`` names one GPU for every job and is kept as it is; so are ``cpu`` and a single worker."""
    check_device_spec(spec)
    if workers <= 1 or spec not in ("auto", "cuda"):
        return []
    gpus = visible_gpus()
    return [gpus[k % len(gpus)] for k in range(workers)] if gpus else []


class Slots(Protocol):
    """The queue of ``CUDA_VISIBLE_DEVICES`` values a grid's workers take theirs from (a ``multiprocessing`` queue)."""

    def get(self, block: bool = True, timeout: float | None = None) -> str: ...


def claim_gpu(slots: Slots) -> None:
    """Grid worker initialiser: take one ``CUDA_VISIBLE_DEVICES`` value from the ``slots`` queue (before this
    process initialises CUDA, which reads it then); an empty queue leaves the environment alone. A blocking
    get with a timeout: ``get_nowait`` also fails while the other worker holds the queue's reader lock."""
    try:
        os.environ["CUDA_VISIBLE_DEVICES"] = slots.get(timeout=10)
    except queue.Empty:
        return

"""Micro-benchmarks of the depth network: prediction and one fine-tuning step (DESIGN §10).

Timings are medians of wall-clock milliseconds after warm-up; they depend on the load of
the machine, so treat them as indicative. ``device`` (default the CPU) says where the network runs:
the inputs are drawn on the CPU with a seeded generator and sent there, and a CUDA device is waited for
before each time is read (``make gpu-check`` runs these on the GPU). ``mslam bench finetune [--threads 1]``
prints :func:`compare` as JSON.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TypedDict

import torch

from mutualslam_cli.adapt.batch import TrainingBatch
from mutualslam_cli.adapt.comoda import ComodaAdapter
from mutualslam_cli.adapt.depthnet import DepthNet, fast_context, fast_path_supported, make_adam, prepare
from mutualslam_cli.adapt.inference import openvino_predictor
from mutualslam_cli.adapt.losses import label_scale, train_loss
from mutualslam_cli.adapt.networks.pose import PoseNet
from mutualslam_cli.adapt.stabilise import TrustRegion
from mutualslam_cli.allocator import retain_freed_memory
from mutualslam_cli.config import AdaptConfig, load_config
from mutualslam_cli.device import grad_scaler, module_device, synchronize
from mutualslam_cli.types import Info

CPU = torch.device("cpu")


class Timing(TypedDict):
    """A median wall time (ms) of ``times_ms`` (every repeat, ms) at ``threads`` torch threads."""

    ms: float
    times_ms: list[float]
    threads: int


class StepTiming(Timing):
    """:func:`bench_inference`'s and :func:`bench_finetune_step`'s: the timing, the path and the image size."""

    fast: bool
    width: int
    height: int
    bf16_supported: bool


class ComodaTiming(StepTiming):
    """:func:`bench_comoda_step`'s: also the targets per step."""

    batch: int


class OpenVinoTiming(Timing):
    """:func:`bench_inference_openvino`'s: also the conversion and compilation time (s)."""

    convert_s: float


def _setup(threads: int | None, seed: int) -> None:
    retain_freed_memory()  # as in `mslam run`
    if threads is not None:
        torch.set_num_threads(int(threads))
    torch.manual_seed(seed)


def _median_ms(fn: Callable[[], object], repeats: int, warmup: int,
               device: torch.device = CPU) -> tuple[float, list[float]]:
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        synchronize(device)  # CUDA runs ahead of the host
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times), times


def _rand(*shape: int, generator: torch.Generator | None = None, device: torch.device = CPU) -> torch.Tensor:
    """Uniform [0, 1) drawn on the CPU (the same numbers on every device), then sent to ``device``."""
    return torch.rand(*shape, generator=generator, device=CPU).to(device)


def bench_inference(width: int = 640, height: int = 192, repeats: int = 10, fast: bool = False,
                    threads: int | None = None, batch: int = 1, warmup: int = 2, seed: int = 0,
                    channels_last: bool | None = None, device: torch.device | str = CPU) -> StepTiming:
    """Median time of one depth prediction (eval mode, no grad) on ``device``.

    Returns:
        ``{"ms": median, "times_ms": [...], "fast": bool, "width", "height", "threads"}``.
    """
    _setup(threads, seed)
    device = torch.device(device)
    net = prepare(DepthNet().eval(), fast, channels_last, device=device)
    x = _rand(batch, 3, height, width, device=device)

    def step() -> None:
        with torch.no_grad(), fast_context(fast, device):
            net.predict(x)

    ms, times = _median_ms(step, repeats, warmup, device)
    return {"ms": ms, "times_ms": times, "fast": fast, "width": width, "height": height,
            "threads": torch.get_num_threads(), "bf16_supported": fast_path_supported()}


def bench_inference_openvino(width: int = 640, height: int = 192, repeats: int = 10, threads: int | None = None,
                             warmup: int = 2, seed: int = 0, int8: bool = False) -> OpenVinoTiming:
    """Median time of one depth prediction through the evaluation's OpenVINO runtime
    (:mod:`mutualslam_cli.adapt.inference`: bf16 where the CPU has it, else fp32; or int8 calibrated
    on 4 random frames, whose values do not change the speed), conversion timed apart.

    Returns:
        ``{"ms": median, "times_ms": [...], "convert_s": conversion + compilation, "threads"}``.
    """
    _setup(threads, seed)
    t0 = time.perf_counter()
    calib = _rand(4, 3, height, width) if int8 else None
    predict = openvino_predictor(DepthNet().eval(), width, height, threads, calibration=calib)
    convert_s = time.perf_counter() - t0
    x = _rand(1, 3, height, width)
    ms, times = _median_ms(lambda: predict(x), repeats, warmup)
    return {"ms": ms, "times_ms": times, "convert_s": convert_s, "threads": torch.get_num_threads()}


def make_step_batch(width: int, height: int, n_points: int = 500, seed: int = 0,
                    device: torch.device | str = CPU) -> TrainingBatch:
    """A realistic fine-tuning batch on ``device``: 2 targets (recent + replayed), 2 neighbours each, sparse points."""
    g = torch.Generator(device=CPU).manual_seed(seed)
    b, dev = 2, torch.device(device)
    K = torch.tensor([[0.58 * width, 0, width / 2 - 0.5], [0, 1.92 * height, height / 2 - 0.5], [0, 0, 1]],
                     device=dev)
    T1, T2 = torch.eye(4, device=dev), torch.eye(4, device=dev)
    T1[:3, 3] = torch.tensor([0.05, 0.0, 0.01], device=dev)
    T2[:3, 3] = torch.tensor([-0.05, 0.01, -0.01], device=dev)
    uv = _rand(b, n_points, 2, generator=g, device=dev) * torch.tensor([width - 1.0, height - 1.0], device=dev)
    return TrainingBatch(  # keyword order = the old dict's: the same random draws in the same order
        ids=list(range(b)),
        target=_rand(b, 3, height, width, generator=g, device=dev),
        sources=[_rand(b, 3, height, width, generator=g, device=dev) for _ in range(2)],
        K=K.expand(b, 3, 3).clone(),
        T_t2s=[T1.expand(b, 4, 4).clone(), T2.expand(b, 4, 4).clone()],
        uv=uv,
        d=0.5 + 2.0 * _rand(b, n_points, generator=g, device=dev),
        mask=torch.ones(b, n_points, dtype=torch.bool, device=dev),
    )


def finetune_step(net: DepthNet, opt: torch.optim.Optimizer, batch: TrainingBatch, fast: bool,
                  lambda_sparse: float = 0.1, lambda_smooth: float = 0.1,
                  scaler: torch.amp.GradScaler | None = None, trust: TrustRegion | None = None) -> dict[str, float]:
    """One Adam step of Eq. 8: network forward under :func:`fast_context` (on the network's device), loss in
    fp32; ``scaler``: fp16 loss scaling (a GPU without bf16); ``trust``: configs/default.yaml's step, the depth
    aligned to the batch's points (``adapt.scale: align_batch``) and the step held in this trust region."""
    opt.zero_grad(set_to_none=True)
    with fast_context(fast, module_device(net)):
        depth = net.predict(batch.target)
    if trust is not None:
        depth = depth * label_scale(depth, batch.uv, batch.d, batch.mask, pooled=True).view(-1, 1, 1, 1)
        trust.before()
    loss, parts = train_loss(depth, batch.target, batch.sources, batch.K, batch.T_t2s,
                             batch.uv, batch.d, batch.mask, lambda_sparse, lambda_smooth)
    if scaler is None:
        loss.backward()
        opt.step()
    else:
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    if trust is not None:
        trust.after()
    return parts


def bench_finetune_step(width: int = 640, height: int = 192, repeats: int = 5, fast: bool = False,
                        threads: int | None = None, warmup: int = 2, seed: int = 0,
                        train_mode: bool = True, channels_last: bool | None = None,
                        device: torch.device | str = CPU, trust: float = 0.0) -> StepTiming:
    """Median time of one fine-tuning step on 2 keyframes (recent + replayed) × 2 neighbours (``trust`` > 0: with
    configs/default.yaml's scale alignment and a trust region of that radius, :func:`finetune_step`).

    The work is that of the online loop: one batched forward of the 2 targets, 4 warps
    (each neighbour once), photometric + sparse + smoothness losses, backward, Adam step.

    Returns:
        ``{"ms": median, "times_ms": [...], "fast": bool, ...}``.
    """
    _setup(threads, seed)
    device = torch.device(device)
    net = prepare(DepthNet(), fast, channels_last, device=device).train(train_mode)
    opt = make_adam(net.parameters(), lr=1e-4)
    batch = make_step_batch(width, height, seed=seed, device=device)
    scaler = grad_scaler(device, fast)
    region = TrustRegion([p for p in net.parameters() if p.requires_grad], trust) if trust > 0 else None
    ms, times = _median_ms(lambda: finetune_step(net, opt, batch, fast, scaler=scaler, trust=region), repeats,
                           warmup, device)
    return {"ms": ms, "times_ms": times, "fast": fast, "width": width, "height": height,
            "threads": torch.get_num_threads(), "bf16_supported": fast_path_supported()}


def bench_comoda_step(width: int = 640, height: int = 192, repeats: int = 5, fast: bool = False,
                      threads: int | None = None, warmup: int = 2, seed: int = 0,
                      replay: int | None = None, device: torch.device | str = CPU) -> ComodaTiming:
    """Median time of one CoMoDa-style update step (scheme ``comoda``, :mod:`mutualslam_cli.adapt.comoda`).

    The work of one frame's update: the current triplet + ``replay`` replayed triplets (default
    ``AdaptConfig.comoda_replay_per_step`` = 3, so a batch of 4 targets), one depth forward of the 4
    targets, two pose-network forwards of 4 frame pairs each, 8 warps, auto-masked minimum
    reprojection + smoothness, backward through both networks, one Adam step. Random weights and
    images (the cost does not depend on them).

    Returns:
        ``{"ms": median, "times_ms": [...], "batch": targets per step, ...}``.
    """
    _setup(threads, seed)
    cfg = AdaptConfig(scheme="comoda")
    if replay is not None:
        cfg = replace(cfg, comoda_replay_per_step=int(replay))
    device = torch.device(device)
    net = prepare(DepthNet(), fast, device=device)
    K = torch.tensor([[0.58 * width, 0, width / 2], [0, 1.92 * height, height / 2], [0, 0, 1]], device=CPU)
    g = torch.Generator(device=CPU).manual_seed(seed)

    def triplet() -> torch.Tensor:  # frames stay on the CPU as the adapter keeps them
        return torch.randint(0, 256, (3, 3, height, width), generator=g, dtype=torch.uint8, device=CPU)

    # a replay bank (the default, source-domain replay) full from the first step on
    bank = torch.stack([triplet() for _ in range(max(1, cfg.comoda_replay_per_step))])
    adapter = ComodaAdapter(net, PoseNet(), cfg, K, seed=seed, fast=fast, replay_bank=(bank, K), device=device)
    current = triplet()
    ms, times = _median_ms(lambda: adapter.train_triplet(100, current), repeats, warmup, device)
    return {"ms": ms, "times_ms": times, "fast": fast, "width": width, "height": height,
            "batch": 1 + cfg.comoda_replay_per_step, "threads": torch.get_num_threads(),
            "bf16_supported": fast_path_supported()}


def compare(width: int = 640, height: int = 192, repeats: int = 5, threads: int | None = 1) -> Info:
    """fp32 (NCHW), fp32 + channels-last and the fast path side by side, plus bf16 accuracy.

    ``threads=1`` by default: on a shared 2-core machine two OpenMP threads competing with
    other processes are several times *slower* than one (measured; see the report).
    """
    variants = {"fp32": (False, False), "fp32_cl": (False, True), "fast": (True, True)}
    out: Info = {"threads": threads, "bf16_supported": fast_path_supported()}
    for name, (fast, cl) in variants.items():
        if fast and not fast_path_supported():
            continue
        out[f"inference_{name}_ms"] = bench_inference(width, height, 2 * repeats, fast, threads,
                                                      channels_last=cl)["ms"]
        out[f"finetune_{name}_ms"] = bench_finetune_step(width, height, repeats, fast, threads,
                                                         channels_last=cl)["ms"]
    trust = load_config().adapt.trust  # configs/default.yaml's step (scale alignment + trust region), `auto`'s path
    if trust > 0:
        fast = fast_path_supported()
        out[f"finetune_{'fast' if fast else 'fp32_cl'}_default_ms"] = bench_finetune_step(
            width, height, repeats, fast, threads, channels_last=True, trust=trust)["ms"]
    out["bf16_rel_depth_diff"] = bf16_depth_difference(width, height)
    return out


def bf16_depth_difference(width: int = 640, height: int = 192, net: DepthNet | None = None,
                          images: torch.Tensor | None = None) -> dict[str, float] | None:
    """Median and 99th-percentile of ``|D_bf16 − D_fp32| / D_fp32`` (None without bf16 support)."""
    if not fast_path_supported():
        return None
    torch.manual_seed(0)
    net = (net or DepthNet()).eval()
    x = images if images is not None else _rand(1, 3, height, width)
    with torch.no_grad():
        ref = prepare(net, False).predict(x)
        with fast_context(True):
            got = prepare(net, True).predict(x)
    prepare(net, False)
    rel = ((got - ref).abs() / ref).flatten()
    return {"median": float(rel.median()), "p99": float(torch.quantile(rel[:100000], 0.99)),
            "max": float(rel.max())}


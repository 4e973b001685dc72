"""Pre-training of the default depth network on the synthetic *source* domain (DESIGN §3, §5).

Stand-in for the paper's KITTI pre-training: a randomly initialised :class:`DepthNet` (no
ImageNet weights are available offline) is trained with dense supervision on the exact depth
of ``render_sequence(..., domain="source")`` sequences, then saved in the Monodepth2 format
(:func:`save_monodepth2`) with a ``pretrain.json`` record. The target-domain sequences
(``domain="target"``) are left for online adaptation.

Loss: the scale-invariant log loss of Eigen et al. (NeurIPS 2014, Eq. 4) per image,
``mean(g²) − λ·mean(g)²`` with ``g = log D − log D_gt`` and λ = 0.85 (the variance-focused
weighting of BTS, Lee et al. 2019); the 0.15 residual of the mean term keeps the absolute
scale anchored to metres.

Determinism: same seed, same thread count and same fast-path setting give the same weights.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TypedDict

import numpy as np
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, fast_context, make_adam, predict_depth, prepare, resolve_fast
from mutualslam_cli.adapt.weights import save_monodepth2
from mutualslam_cli.datasets.synthetic import iter_render
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.metrics.depth import percent_correct
from mutualslam_cli.types import Info

log = logging.getLogger(__name__)

Progress = Callable[[Info], None]  # called with {"step", "steps", "loss"}

#: Tiny configuration for smoke tests and ``mslam pretrain --quick`` (seconds, not minutes).
QUICK: dict[str, int] = dict(steps=3, width=128, height=64, batch_size=2, pool_size=4, n_frames=2, frame_stride=1,
                             refresh_every=1, log_every=1, warmup=1, checkpoint_every=0)


class LossPoint(TypedDict):
    """One point of a ``loss_curve``: after optimiser step ``step``, the mean ``loss`` since the last point, at
    ``t`` seconds of training."""

    step: int
    loss: float
    t: float


class PretrainEval(TypedDict):
    """Median-scaled PCD (%) per scene and ``mean`` (:func:`evaluate_pcd`): ``eval_target`` of the trained and a
    random-init net on target-domain frames, ``eval_source`` of the trained net on unseen source-domain frames."""

    eval_target: dict[str, dict[str, float]]
    eval_source: dict[str, float]


class _Settings(TypedDict):
    steps: int
    steps_requested: int
    seed: int
    width: int
    height: int
    batch_size: int
    crop: list[int] | None
    lr: float
    fast: bool
    threads: int
    scenes: list[str]
    render_seed_base: int
    n_sequences: int
    n_frames: int
    frame_stride: int
    n_train_frames: int
    pool_size: int
    refresh_every: int
    loss: str
    loss_curve: list[LossPoint]
    render_s: float
    train_s: float
    s_per_step: float
    complete: bool
    half: bool
    drop_fc: bool


class PretrainRecord(_Settings, total=False):
    """``pretrain.json``: the settings and how training went (``steps``: those done), then, once the run is over,
    :class:`PretrainEval`'s figures (with ``eval_frames``) and ``time_s``, the whole run's seconds."""

    eval_target: dict[str, dict[str, float]]
    eval_source: dict[str, float]
    time_s: float


@dataclass
class FramePool:
    """Rendered training frames kept in memory.

    Attributes:
        rgb: ``(N, H, W, 3)`` uint8.
        depth: ``(N, H, W)`` float16 metres (> 0).
    """

    rgb: np.ndarray
    depth: np.ndarray

    def __len__(self) -> int:
        return len(self.rgb)


def render_pool(scenes: Sequence[str], seeds: Sequence[int], n_frames: int, stride: int, width: int, height: int,
                domain: Literal["target", "source"] = "source") -> FramePool:
    """Render every ``stride``-th frame of ``n_frames`` for each (scene, seed) at ``width``×``height``."""
    rgbs, depths = [], []
    for scene in scenes:
        for seed in seeds:
            for i, rgb, depth, _ in iter_render(scene, n_frames, width, height, int(seed), domain):
                if i % stride == 0:
                    rgbs.append(rgb)
                    depths.append(depth.astype(np.float16))
    return FramePool(np.stack(rgbs), np.stack(depths))


class RefreshingPool:
    """A ring buffer of source-domain frames that keeps receiving freshly rendered sequences.

    Each synthetic seed is a new layout, texture set and camera path, so rendering new short
    sequences during training (instead of a fixed set) is what makes the net generalise
    (a fixed pool of 4 seeds per scene over-fitted: PCD 50–70 % on its frames, far less on
    a held-out seed). Sequence ``k`` uses scene ``scenes[k % len(scenes)]`` and render seed
    ``base_seed + k``; deterministic.
    """

    def __init__(self, size: int, scenes: Sequence[str], base_seed: int, n_frames: int, stride: int,
                 width: int, height: int):
        self.scenes, self.base_seed = tuple(scenes), int(base_seed)
        self.n_frames, self.stride, self.width, self.height = n_frames, stride, width, height
        self.per_seq = len(range(0, n_frames, stride))
        self.size = max(int(size), self.per_seq)
        self.rgb = np.zeros((self.size, height, width, 3), np.uint8)
        self.depth = np.ones((self.size, height, width), np.float16)
        self.filled, self.head, self.n_sequences = 0, 0, 0
        while self.filled < self.size:
            self.add_sequence()

    def add_sequence(self) -> None:
        """Render the next sequence and overwrite the oldest slots."""
        k = self.n_sequences
        seq = render_pool([self.scenes[k % len(self.scenes)]], [self.base_seed + k], self.n_frames, self.stride,
                          self.width, self.height, "source")
        for rgb, depth in zip(seq.rgb, seq.depth):
            self.rgb[self.head], self.depth[self.head] = rgb, depth
            self.head = (self.head + 1) % self.size
            self.filled = min(self.filled + 1, self.size)
        self.n_sequences += 1

    def __len__(self) -> int:
        return self.filled


def silog_loss(depth: torch.Tensor, gt: torch.Tensor, lam: float = 0.85) -> torch.Tensor:
    """Scale-invariant log loss (Eigen et al. 2014, Eq. 4), mean over images.

    Args:
        depth: ``(B, 1, H, W)`` predicted depth (> 0).
        gt: ``(B, 1, H, W)`` GT depth; pixels ≤ 0 are ignored.
        lam: weight of the mean term (0 = plain log-L2, 1 = fully scale invariant).
    """
    with torch.autocast("cpu", enabled=False):
        depth, gt = depth.float(), gt.float()
        m = gt > 0
        g = torch.where(m, torch.log(depth) - torch.log(gt.clamp_min(1e-6)), torch.zeros_like(depth))
        n = m.flatten(1).sum(1).clamp_min(1)
        mean_g = g.flatten(1).sum(1) / n
        mean_g2 = (g * g).flatten(1).sum(1) / n
        return (mean_g2 - lam * mean_g ** 2).mean()


def training_batch(pool: FramePool, idx: np.ndarray, rng: np.random.Generator, crop: tuple[int, int] | None,
           augment: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Images ``(B, 3, h, w)`` in [0, 1] and depth ``(B, 1, h, w)``, with crop / flip / colour jitter."""
    rgb = pool.rgb[idx].astype(np.float32) / 255.0
    depth = pool.depth[idx].astype(np.float32)
    if crop is not None:
        ch, cw = crop
        H, W = rgb.shape[1:3]
        ys = rng.integers(0, H - ch + 1, len(idx))
        xs = rng.integers(0, W - cw + 1, len(idx))
        rgb = np.stack([r[y:y + ch, x:x + cw] for r, y, x in zip(rgb, ys, xs)])
        depth = np.stack([d[y:y + ch, x:x + cw] for d, y, x in zip(depth, ys, xs)])
    if augment:
        flip = rng.random(len(idx)) < 0.5
        rgb[flip] = rgb[flip, :, ::-1]
        depth[flip] = depth[flip, :, ::-1]
        b = len(idx)
        gain = rng.uniform(0.8, 1.2, (b, 1, 1, 1)).astype(np.float32)        # brightness
        contrast = rng.uniform(0.8, 1.2, (b, 1, 1, 1)).astype(np.float32)
        colour = rng.uniform(0.9, 1.1, (b, 1, 1, 3)).astype(np.float32)
        mean = rgb.mean(axis=(1, 2, 3), keepdims=True)
        rgb = np.clip(((rgb - mean) * contrast + mean) * gain * colour, 0.0, 1.0)
    x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(0, 3, 1, 2).contiguous()
    d = torch.from_numpy(np.ascontiguousarray(depth))[:, None]
    return x, d


def _lr_at(step: int, steps: int, lr: float, warmup: int) -> float:
    """Linear warm-up, then cosine decay to lr/20."""
    if step < warmup:
        return lr * (step + 1) / warmup
    t = (step - warmup) / max(1, steps - warmup)
    return lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))


def pretrain(out_dir: Path, steps: int, width: int = 640, height: int = 192, batch_size: int = 4, seed: int = 0,
             progress: Progress | None = None, *, scenes: Sequence[str] = ("room", "planar", "far"),
             pool_size: int = 480, n_frames: int = 8, frame_stride: int = 2, refresh_every: int = 2,
             crop: tuple[int, int] | None = None,
             lr: float = 5e-4, warmup: int = 50, fast: str | bool = "auto", threads: int | None = None,
             augment: bool = True, half: bool = True, drop_fc: bool = False, max_minutes: float | None = None,
             checkpoint_every: int = 200, eval_frames: int = 0, log_every: int = 10) -> PretrainRecord:
    """Train a DepthNet from scratch on the synthetic source domain and save it.

    Args:
        out_dir: output folder: ``encoder.pth``, ``depth.pth`` (Monodepth2 format) and ``pretrain.json``.
        steps: optimiser steps (Adam).
        width, height: rendering and network resolution (multiples of 32, ≥ 64).
        batch_size: images per step.
        seed: seeds the initialisation, data order and augmentation; source sequences use
            render seeds ``seed·100000 + k``.
        progress: called after each step with ``{"step": k, "steps": steps, "loss": value}``.
        scenes: synthetic scenes rendered in the source domain.
        pool_size: frames held in memory (ring buffer; 0.6 MB each at 640×192).
        n_frames: frames rendered per sequence; frame_stride: keep every k-th of them.
        refresh_every: render one new sequence (new seed, next scene) every this many steps
            (0 = fixed pool).
        crop: train on random ``(h, w)`` crops (same pixel scale, cheaper steps), ``None`` = full frame.
        lr: peak Adam learning rate (linear warm-up of ``warmup`` steps, cosine decay to lr/20).
        fast: bf16 autocast + channels-last: ``auto`` | ``on`` | ``off`` or a bool.
        threads: ``torch.set_num_threads`` (``None`` keeps the current setting).
        augment: horizontal flip and mild brightness / contrast / colour jitter.
        half: store the weights as fp16 (the shipped default: 29.75 MB with ``encoder.fc``).
        drop_fc: omit the unused ``encoder.fc.*`` (−1 MB; the loader accepts its absence).
        max_minutes: stop early (and save) when training time exceeds this.
        checkpoint_every: also save every this many steps (so an interrupted run leaves weights).
        eval_frames: if > 0, report median-scaled PCD on that many target-domain frames per
            scene for the trained net and for a random-init net (stored in ``pretrain.json``).
        log_every: record the loss curve every this many steps (mean over the interval).

    Returns:
        The ``pretrain.json`` record (dict).
    """
    _check_settings(steps, batch_size, width, height, crop)
    if threads is not None:
        torch.set_num_threads(int(threads))
    use_fast = resolve_fast(fast)
    out_dir = Path(out_dir)
    t_start = time.perf_counter()

    pool = RefreshingPool(pool_size, scenes, seed * 100000, n_frames, frame_stride, width, height)
    t_render = time.perf_counter() - t_start
    log.info("pretrain: %d source frames rendered in %.1f s", len(pool), t_render)

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = prepare(DepthNet(), use_fast).train()
    opt = make_adam(net.parameters(), lr=lr)
    curve: list[LossPoint] = []
    acc, acc_n, done = 0.0, 0, 0
    t_train = time.perf_counter()
    def save(final: bool) -> PretrainRecord:
        save_monodepth2(net, out_dir, height, width, half=half, drop_fc=drop_fc)
        rec: PretrainRecord = {
            "steps": done, "steps_requested": steps, "seed": seed, "width": width, "height": height,
            "batch_size": batch_size, "crop": list(crop) if crop else None, "lr": lr, "fast": use_fast,
            "threads": torch.get_num_threads(), "scenes": list(scenes), "render_seed_base": seed * 100000,
            "n_sequences": pool.n_sequences, "n_frames": n_frames, "frame_stride": frame_stride,
            "n_train_frames": pool.n_sequences * pool.per_seq, "pool_size": pool.size,
            "refresh_every": refresh_every,
            "loss": "silog(lambda=0.85)", "loss_curve": curve, "render_s": round(t_render, 2),
            "train_s": round(time.perf_counter() - t_train, 2),
            "s_per_step": round((time.perf_counter() - t_train) / max(done, 1), 4),
            "complete": final, "half": half, "drop_fc": drop_fc,
        }
        (out_dir / "pretrain.json").write_text(json.dumps(rec, indent=1))
        return rec

    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = _lr_at(step, steps, lr, min(warmup, steps))
        idx = rng.integers(0, len(pool), batch_size)
        x, gt = training_batch(FramePool(pool.rgb, pool.depth), idx, rng, crop, augment)
        with fast_context(use_fast):
            depth = net.predict(x)
        loss = silog_loss(depth, gt)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        done = step + 1
        if refresh_every and done % refresh_every == 0 and done < steps:
            pool.add_sequence()
        value = float(loss.detach())
        acc, acc_n = acc + value, acc_n + 1
        if acc_n == log_every or done == steps:
            curve.append({"step": done, "loss": acc / acc_n, "t": round(time.perf_counter() - t_train, 2)})
            log.info("pretrain step %d/%d loss %.4f", done, steps, acc / acc_n)
            acc, acc_n = 0.0, 0
        if progress is not None:
            progress({"step": done, "steps": steps, "loss": value})
        if checkpoint_every and done % checkpoint_every == 0 and done < steps:
            save(final=False)
        if max_minutes is not None and time.perf_counter() - t_train > 60.0 * max_minutes:
            log.warning("pretrain: time budget of %.1f min reached after %d steps", max_minutes, done)
            break
    if acc_n:
        curve.append({"step": done, "loss": acc / acc_n, "t": round(time.perf_counter() - t_train, 2)})
    record = save(final=True)
    if eval_frames > 0:
        record.update(_evaluate(net.eval(), seed, width, height, eval_frames, scenes, use_fast))
        (out_dir / "pretrain.json").write_text(json.dumps(record, indent=1))
    record["time_s"] = round(time.perf_counter() - t_start, 2)
    (out_dir / "pretrain.json").write_text(json.dumps(record, indent=1))
    return record


def _check_settings(steps: int, batch_size: int, width: int, height: int, crop: tuple[int, int] | None) -> None:
    """:class:`ConfigError` for settings :func:`pretrain` cannot train with."""
    if steps < 1 or batch_size < 1:
        raise ConfigError(f"pretrain: steps and batch_size must be ≥ 1, got {steps}, {batch_size}")
    if width % 32 or height % 32 or min(width, height) < 64:
        raise ConfigError(f"pretrain: width/height must be multiples of 32 and ≥ 64, got {width}×{height}")
    if crop is not None and (crop[0] % 32 or crop[1] % 32 or min(crop) < 64 or crop[0] > height or crop[1] > width):
        raise ConfigError(f"pretrain: crop must be multiples of 32, ≥ 64 and inside {height}×{width}, got {crop}")


def _evaluate(net: DepthNet, seed: int, width: int, height: int, n_frames: int, scenes: Sequence[str],
              fast: bool) -> PretrainEval:
    """``eval_target`` (the trained and a random-init net on target-domain frames) and ``eval_source``
    (the trained net on unseen source-domain frames) of ``pretrain.json``."""
    torch.manual_seed(seed + 1)
    random_net = DepthNet().eval()
    return {
        "eval_target": {"pretrained": evaluate_pcd(net, width, height, n_frames, scenes, fast=fast),
                        "random_init": evaluate_pcd(random_net, width, height, n_frames, scenes, fast=fast)},
        "eval_source": evaluate_pcd(net, width, height, n_frames, scenes, fast=fast, domain="source",
                                    seeds=(seed * 100000 + 99999,)),
    }


def evaluate_pcd(net: DepthNet, width: int, height: int, n_frames: int,
                 scenes: Sequence[str] = ("room", "planar", "far"),
                 fast: bool = False, domain: Literal["target", "source"] = "target", seeds: Sequence[int] = (0,),
                 stride: int = 5) -> dict[str, float]:
    """Mean per-frame PCD (median scaling, DESIGN §7) on synthetic sequences, per scene and overall.

    Renders ``n_frames`` frames (every ``stride``-th of a longer path) of each scene/seed.
    """
    out: dict[str, float] = {}
    for scene in scenes:
        pool = render_pool([scene], seeds, n_frames * stride, stride, width, height, domain)
        pred = predict_depth(net, pool.rgb, fast=fast)
        out[scene] = float(np.mean([percent_correct(p, g.astype(np.float32), "median")
                                    for p, g in zip(pred, pool.depth)]))
    out["mean"] = float(np.mean([out[s] for s in scenes]))
    return out

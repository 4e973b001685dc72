"""Pre-training of the ``comoda`` pose network on the synthetic *source* domain (beside :mod:`.pretrain`).

Stand-in for the pose network CoMoDa starts from (Monodepth2's, trained on KITTI with the depth
network): a :class:`~mutualslam_cli.adapt.networks.pose.PoseNet` is trained with the *exact*
relative poses of consecutive frames of ``render_sequence(..., domain="source")`` sequences — the
same supervision-by-rendering as the default depth network (:mod:`.pretrain`), so translations are
in metres like its depth — and saved as Monodepth2's ``pose_encoder.pth`` + ``pose.pth``
(:func:`~mutualslam_cli.adapt.weights.save_pose`) with a ``pretrain_pose.json`` record. Written into
the default weights folder, it becomes scheme ``comoda``'s default pose network
(:func:`~mutualslam_cli.adapt.comoda_pose.make_pose_net`).

Loss per pair: ``‖t̂ − t‖₁ + ‖R̂ − R‖₁`` (entries of the rotation matrix; both ~1e-2 per frame at
30 Hz, so neither dominates), mean over the batch, ``T = T_{i→i+1} = T_wc(i+1)⁻¹ · T_wc(i)``.

No default file is shipped, because no run that fits this machine learnt anything that carries
to sequences it did not see. Measured with ``mslam pretrain --pose`` (held-out loss on 6 batches of
4 pairs from unseen render seeds; the identity transform scores 0.0192):

- 640×192, batch 4, lr 1e-4, one thread: 368 steps in 28 min, training loss 0.020 → 0.020,
  held-out 0.0208;
- 320×96, batch 8, lr 1e-3: 150 steps in 4 min, training loss 0.030 → 0.014 (it fits the seen
  batches), held-out 0.0195.

Relative motion between 30 Hz frames is a few millimetres and a fraction of a degree, so the
target is small next to what the network sees, and Monodepth2's pose network learns it over 20
epochs of KITTI (tens of thousands of steps) on a GPU. Until a longer run produces a useful file,
``comoda`` starts from the depth encoder's weights (conv1 repeated, halved) and a random decoder
whose 0.01 output scale starts it near the identity, with a warning. CoMoDa's own loss then trains
the pose network online.

Determinism: same seed and thread count give the same weights.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, cast

import numpy as np
import torch

from mutualslam_cli.adapt.networks import ResnetEncoder
from mutualslam_cli.adapt.networks.pose import PoseNet
from mutualslam_cli.adapt.weights import save_pose
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.synthetic import iter_render
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import Info

if TYPE_CHECKING:
    from mutualslam_cli.adapt.pretrain import LossPoint

log = logging.getLogger(__name__)


def pose_batch(scene: str, seed: int, n_pairs: int, width: int, height: int
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n_pairs`` consecutive-frame pairs of one rendered source-domain sequence.

    Returns:
        ``(first, second, T)``: ``(B, 3, H, W)`` float in [0, 1] twice and ``(B, 4, 4)`` float32
        ground-truth ``T_{first→second}``.
    """
    frames = list(iter_render(scene, n_pairs + 1, width, height, int(seed), "source"))
    rgb = torch.from_numpy(np.stack([f[1] for f in frames])).permute(0, 3, 1, 2).float() / 255.0
    poses = np.stack([f[3] for f in frames])
    T = np.stack([np.linalg.inv(poses[i + 1]) @ poses[i] for i in range(n_pairs)])
    return rgb[:-1], rgb[1:], torch.from_numpy(T).float()


def pose_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """``mean_b (‖t̂ − t‖₁ + ‖R̂ − R‖₁)`` of ``(B, 4, 4)`` transforms (module docstring)."""
    dt = (pred[:, :3, 3] - gt[:, :3, 3]).abs().sum(1)
    dr = (pred[:, :3, :3] - gt[:, :3, :3]).abs().sum((1, 2))
    return (dt + dr).mean()


class PosePretrainRecord(TypedDict):
    """``pretrain_pose.json``: the settings (``steps`` asked, ``steps_done``), the ``loss_curve`` (one point per step)
    and ``time_s``, the training's seconds."""

    steps: int
    steps_done: int
    max_minutes: float | None
    width: int
    height: int
    batch_size: int
    lr: float
    seed: int
    scenes: list[str]
    render_seed_base: int
    refresh: bool
    init_from_depth_encoder: bool
    half: bool
    loss: str
    loss_curve: list[LossPoint]
    time_s: float
    threads: int


def pretrain_pose(out_dir: Path, steps: int, width: int = 640, height: int = 192, batch_size: int = 4,
                  lr: float = 1e-4, seed: int = 0, scenes: Sequence[str] = ("room", "planar", "far"),
                  render_seed_base: int = 0, refresh: bool = True, init: torch.nn.Module | None = None,
                  max_minutes: float | None = None, threads: int | None = None, half: bool = False,
                  progress: Callable[[Info], None] | None = None) -> PosePretrainRecord:
    """Train a pose network on source-domain relative poses; write it in Monodepth2's format.

    Args:
        out_dir: folder for ``pose_encoder.pth``, ``pose.pth`` and ``pretrain_pose.json``.
        steps: Adam steps. width, height: network resolution. batch_size: pairs per step.
        lr: Adam learning rate. seed: torch seed (initialisation).
        scenes: synthetic scenes, cycled. render_seed_base: render seed of the first sequence.
        refresh: a new sequence (scene ``scenes[k % n]``, seed ``render_seed_base + k``) every step;
            False: the first one every step (tests).
        init: a depth network whose encoder initialises the pose encoder (conv1 repeated, halved).
        max_minutes: stop after the step that crosses this wall time and save (``None``: all steps).
        threads: ``torch.set_num_threads`` (``None`` keeps the current setting).
        half: store the weights as fp16 (half the size; loading converts back to fp32).
        progress: called with ``{"step", "steps", "loss"}``.

    Returns:
        The record written to ``pretrain_pose.json`` (settings, ``loss_curve``, ``time_s``).

    Raises:
        ConfigError: ``steps`` or ``batch_size`` < 1, or ``lr`` ≤ 0.
    """
    if steps < 1 or batch_size < 1 or lr <= 0:
        raise ConfigError(f"pretrain_pose: need steps ≥ 1, batch_size ≥ 1, lr > 0; got {steps}, {batch_size}, {lr}")
    if threads is not None:
        torch.set_num_threads(int(threads))
    torch.manual_seed(seed)
    net = PoseNet()
    if init is not None:
        net.encoder.init_from_single_image(cast(ResnetEncoder, init.encoder))  # a DepthNet's encoder
    net.train()  # BatchNorm in training mode, as Monodepth2 trains (statistics learnt from the source domain)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    curve: list[LossPoint] = []
    t0 = time.perf_counter()
    for step in range(steps):
        k = step if refresh else 0
        first, second, T = pose_batch(scenes[k % len(scenes)], render_seed_base + k, batch_size, width, height)
        opt.zero_grad(set_to_none=True)
        loss = pose_loss(net(first, second), T)
        loss.backward()
        opt.step()
        curve.append({"step": step + 1, "loss": float(loss.detach()), "t": round(time.perf_counter() - t0, 2)})
        if progress:
            progress({"step": step + 1, "steps": steps, "loss": curve[-1]["loss"]})
        if max_minutes is not None and time.perf_counter() - t0 > 60.0 * max_minutes:
            log.info("pose pre-training stopped after %d of %d steps (max %.1f min)", step + 1, steps, max_minutes)
            break
    save_pose(net.eval(), Path(out_dir), half=half)
    record: PosePretrainRecord = {"steps": steps, "steps_done": len(curve), "max_minutes": max_minutes,
              "width": width, "height": height, "batch_size": batch_size, "lr": lr, "seed": seed,
              "scenes": list(scenes), "render_seed_base": render_seed_base, "refresh": refresh,
              "init_from_depth_encoder": init is not None, "half": half, "loss": "L1(t) + L1(R)", "loss_curve": curve,
              "time_s": time.perf_counter() - t0, "threads": torch.get_num_threads()}
    atomic_write_text(Path(out_dir) / "pretrain_pose.json", json.dumps(record, indent=1))
    log.info("pose network pre-trained: %d steps, final loss %.4g, %s", steps, curve[-1]["loss"], out_dir)
    return record

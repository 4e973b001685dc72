"""A fine-tuning batch (Alg. 2): the scheme's keyframes, their photometric sources, relative poses, intrinsics
and padded sparse points, stacked and sent to the network's device; resampled to the training size.

Images come from the :class:`~mutualslam_cli.adapt.buffer.KeyframeBuffer` (kept on the CPU, sent as uint8);
poses and sparse points are read from the buffer's labels as they stand now (the online rule, DESIGN §5),
gathered on the CPU and sent once.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.geometry import se3_inv

if TYPE_CHECKING:  # the schemes import the regularisers, which the batch does not need at run time
    from mutualslam_cli.adapt.schemes.base import Scheme


@dataclass(frozen=True)
class TrainingBatch:
    """One fine-tuning batch of ``B`` target keyframes (newest first), on one device.

    Frozen: a resampled batch is a new record (:func:`resample_batch`); the tensors themselves are not
    copied and may still be written in place.

    Attributes:
        ids: the ``B`` target keyframe ids, newest first.
        target: ``(B, 3, H, W)`` float32 RGB of the targets in [0, 1].
        sources: per photometric source slot, ``(B, 3, H, W)`` float32 RGB in [0, 1] (an item with fewer
            sources repeats one of its own).
        T_t2s: per source slot, ``(B, 4, 4)`` float32 target → source camera transforms
            (``T_cw(src) · T_wc(tgt)``, translation in map units).
        K: ``(B, 3, 3)`` float32 intrinsics at the ``W × H`` of the images, in pixels.
        uv: ``(B, M, 2)`` float32 pixels ``(u, v)`` of the sparse map points, zero-padded to the longest.
        d: ``(B, M)`` float32 their depth in map units (D_sparse of Eq. 6), zero-padded.
        mask: ``(B, M)`` bool, True where ``uv``/``d`` hold a point (False on padding).
    """

    ids: list[int]
    target: torch.Tensor
    sources: list[torch.Tensor]
    T_t2s: list[torch.Tensor]
    K: torch.Tensor
    uv: torch.Tensor
    d: torch.Tensor
    mask: torch.Tensor


def make_batch(buffer: KeyframeBuffer, scheme: Scheme, ids: list[int],
               device: torch.device) -> TrainingBatch | None:
    """Targets ``ids`` (newest first) with their sources as ``scheme.sources`` chooses them, on ``device``.

    Returns:
        The :class:`TrainingBatch`; ``None`` when no target has a source (not trainable). Items with fewer
        sources than the others repeat one of theirs (the per-pixel minimum over identical warps is
        unchanged), so the batch stays one forward pass.
    """
    items = [(k, scheme.sources(buffer, k)) for k in ids]
    items = [(k, n) for k, n in items if n]  # no photometric source → not trainable
    if not items:
        return None
    samples = [buffer.get(k, device) for k, _ in items]
    n_src = max(len(n) for _, n in items)
    sources, T_t2s = [], []
    for slot in range(n_src):
        imgs, poses = [], []
        for tgt, (_, nb) in zip(samples, items):
            src = buffer.get(nb[min(slot, len(nb) - 1)], device)  # repeat a source when fewer
            imgs.append(src.image)
            poses.append(se3_inv(src.pose) @ tgt.pose)  # T_t2s = T_cw(src) · T_wc(tgt)
        sources.append(torch.stack(imgs))
        T_t2s.append(torch.as_tensor(np.stack(poses), dtype=torch.float32, device="cpu"))
    m = max(s.uv.shape[0] for s in samples)
    uv = torch.zeros(len(samples), m, 2, device="cpu")  # labels gathered on the CPU, sent once below
    d = torch.zeros(len(samples), m, device="cpu")
    mask = torch.zeros(len(samples), m, dtype=torch.bool, device="cpu")
    for b, s in enumerate(samples):
        n = s.uv.shape[0]
        uv[b, :n], d[b, :n], mask[b, :n] = s.uv, s.depth, True
    K = torch.stack([s.K.to(torch.float32) for s in samples])
    return TrainingBatch(ids=[k for k, _ in items], target=torch.stack([s.image for s in samples]), sources=sources,
                         T_t2s=[t.to(device) for t in T_t2s], K=K.to(device), uv=uv.to(device), d=d.to(device),
                         mask=mask.to(device))


def resample_batch(batch: TrainingBatch, width: int, height: int) -> TrainingBatch:
    """A training batch at ``width × height`` (0: unchanged): images area-resampled, ``K`` and the sparse
    pixels ``uv`` scaled with pixel centres kept (``c' = (c + 0.5)·s − 0.5``, as ``Intrinsics.scaled``)."""
    h0, w0 = batch.target.shape[-2:]
    width, height = width or w0, height or h0
    if (width, height) == (w0, h0):
        return batch

    def small(x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.interpolate(x, size=(height, width), mode="area")

    s = torch.tensor([width / w0, height / h0], device=batch.uv.device)
    K = batch.K.clone()
    K[:, :2, :] *= s[None, :, None]
    K[:, :2, 2] += 0.5 * s - 0.5
    return replace(batch, target=small(batch.target), sources=[small(x) for x in batch.sources], K=K,
                   uv=(batch.uv + 0.5) * s - 0.5)

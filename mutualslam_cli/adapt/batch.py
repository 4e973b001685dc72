"""A fine-tuning batch (Alg. 2): the scheme's keyframes, their photometric sources, relative poses, intrinsics
and padded sparse points, stacked and sent to the network's device; resampled to the training size.

Images come from the :class:`~mutualslam_cli.adapt.buffer.KeyframeBuffer` (kept on the CPU, sent as uint8);
poses and sparse points are read from the buffer's labels as they stand now (the online rule, DESIGN §5),
gathered on the CPU and sent once.
"""

from __future__ import annotations

import numpy as np
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.geometry import se3_inv


def make_batch(buffer: KeyframeBuffer, scheme: object, ids: list[int],
               device: torch.device) -> dict[str, object] | None:
    """Targets ``ids`` (newest first) with their sources as ``scheme.sources`` chooses them, on ``device``.

    Returns:
        ``{"ids", "target" (B, 3, H, W), "sources" [(B, 3, H, W)] per source slot, "T_t2s" [(B, 4, 4)],
        "K" (B, 3, 3), "uv" (B, M, 2), "d" (B, M), "mask" (B, M)}``; ``None`` when no target has a source
        (not trainable). Items with fewer sources than the others repeat one of theirs (the per-pixel
        minimum over identical warps is unchanged), so the batch stays one forward pass.
    """
    items = [(k, scheme.sources(buffer, k)) for k in ids]
    items = [(k, n) for k, n in items if n]  # no photometric source → not trainable
    if not items:
        return None
    samples = [buffer.get(k, device) for k, _ in items]
    n_src = max(len(n) for _, n in items)
    sources, T_t2s = [], []
    for s in range(n_src):
        imgs, poses = [], []
        for tgt, (_, nb) in zip(samples, items):
            src = buffer.get(nb[min(s, len(nb) - 1)], device)  # repeat a source when fewer
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
    return {"ids": [k for k, _ in items], "target": torch.stack([s.image for s in samples]), "sources": sources,
            "T_t2s": [t.to(device) for t in T_t2s], "K": K.to(device), "uv": uv.to(device), "d": d.to(device),
            "mask": mask.to(device)}


def resample_batch(batch: dict[str, object], width: int, height: int) -> dict[str, object]:
    """A training batch at ``width × height`` (0: unchanged): images area-resampled, ``K`` and the sparse
    pixels ``uv`` scaled with pixel centres kept (``c' = (c + 0.5)·s − 0.5``, as ``Intrinsics.scaled``)."""
    h0, w0 = batch["target"].shape[-2:]
    width, height = width or w0, height or h0
    if (width, height) == (w0, h0):
        return batch

    def small(x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.interpolate(x, size=(height, width), mode="area")

    s = torch.tensor([width / w0, height / h0], device=batch["uv"].device)
    K = batch["K"].clone()
    K[:, :2, :] *= s[None, :, None]
    K[:, :2, 2] += 0.5 * s - 0.5
    return {**batch, "target": small(batch["target"]), "sources": [small(x) for x in batch["sources"]], "K": K,
            "uv": (batch["uv"] + 0.5) * s - 0.5}

"""Scheme ``comoda``'s replay from the distant past: frame triplets of the pre-training (source) domain.

CoMoDa replays samples of the network's *training set* (KITTI), drawn from a list fixed before the
run, beside the current test triplet: that is its "experience from the distant past" against
forgetting, not a memory of the test video. Our networks are pre-trained on the synthetic source
domain (:mod:`mutualslam_cli.adapt.pretrain`), which can be rendered again at will, so the same
setting carries over indoors: :func:`source_triplets` renders a fixed bank of consecutive-frame
triplets ``(t−1, t, t+1)`` of that domain, one per source-domain sequence, with the scenes and render
seeds the depth network's pre-training uses (sequence ``k``: scene ``scenes[k % 3]``, render seed
``k``). Frames are rendered directly at network resolution, so their intrinsics are the synthetic
camera's at that size (a different camera from the test sequence's: every replayed sample carries
its own ``K``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.datasets.synthetic import iter_render, synthetic_intrinsics
from mutualslam_cli.errors import ConfigError

log = logging.getLogger(__name__)

#: Source-domain scenes, in the order the depth network's pre-training cycles them.
SOURCE_SCENES = ("room", "planar", "far")


def source_triplets(n: int, width: int, height: int, scenes: Sequence[str] = SOURCE_SCENES,
                    seed_base: int = 0, cache_dir: Path | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` source-domain frame triplets for replay.

    Args:
        n: number of triplets (one per rendered sequence, its frames 0, 1, 2 at 30 Hz).
        width, height: network resolution in pixels (frames are rendered at this size).
        scenes: synthetic scenes, cycled. seed_base: render seed of the first sequence.
        cache_dir: keep the bank here as ``.npy`` (uint8, read without pickle) and reuse it: each
            sequence's scene is built anew (~0.5 s of textures), so 200 triplets take ~90 s to render
            and every comoda run of a grid would repeat them. An unreadable file is re-rendered.

    Returns:
        ``(triplets, K)``: ``(n, 3, 3, height, width)`` uint8 RGB, frame axis (t−1, t, t+1) first,
        and ``(3, 3)`` float32 intrinsics of those frames in pixels.

    Raises:
        ConfigError: ``n`` < 1.
    """
    if n < 1:
        raise ConfigError(f"comoda source replay: need at least 1 triplet, got {n}")
    K = torch.as_tensor(synthetic_intrinsics(width, height).K(), dtype=torch.float32, device="cpu")
    path = (Path(cache_dir) / f"bank-{n}x{width}x{height}-{'-'.join(scenes)}-{seed_base}.npy"
            if cache_dir is not None else None)
    if path is not None and path.is_file():
        try:
            bank = np.load(path, allow_pickle=False)
            if bank.shape == (n, 3, 3, height, width) and bank.dtype == np.uint8:
                return torch.from_numpy(bank), K
        except (OSError, ValueError) as e:
            log.warning("%s: unreadable (%s); rendering the bank again", path, e)
    out = torch.empty((n, 3, 3, height, width), dtype=torch.uint8, device="cpu")  # the bank stays on the CPU
    for k in range(n):
        frames = [f[1] for f in iter_render(scenes[k % len(scenes)], 3, width, height, seed_base + k, "source")]
        out[k] = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, out.numpy(), allow_pickle=False)
    return out, K

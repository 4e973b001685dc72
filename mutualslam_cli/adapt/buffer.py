"""Keyframe store for online adaptation: training/validation keyframes, neighbours, replay.

What is stored (DESIGN §5, paper §III-A/B):

- Every keyframe's *metadata* (K, pose, sparse points) is kept for the whole run (a few KB
  each). With a :class:`LabelSource` (the pipeline's), pose and sparse points are read from the
  map *when they are used*, so a replayed keyframe trains on the map as it stands then — refined by
  BA, grown by later observations (paper §III-A: "the keyframe graph … is beneficial for improving
  the training loss") — and never on a later one (DESIGN §5). Without one, the values given at
  arrival are used, replaced by :meth:`KeyframeBuffer.update_poses` / :meth:`KeyframeBuffer.update_sparse`.
- Images are kept on the CPU at network resolution, as uint8 when that is lossless (images decoded
  from 8-bit files, the pipeline's case: 4× less memory), else as given; :meth:`KeyframeBuffer.get`
  sends one to the device that asks for it (as uint8: 4× less to transfer), where it becomes float.
  With ``capacity == 0`` every image is kept. With ``capacity = C > 0``:

  * training keyframes: the two most recent are always kept (the recent batch and the newest's
    photometric neighbour); older ones enter a *reservoir* of ``C − 2`` slots (Vitter's
    Algorithm R, seeded), so the replay candidates are a uniform sample of the whole past and
    never more than ``C``. A reservoir member keeps the images of its time-adjacent training
    keyframes alive (they are its photometric sources s ∈ {i−1, i+1}), so at most ``3·C``
    training images are held.
  * validation keyframes: their own reservoir of ``C`` slots.

Neighbours are the previous/next *training* keyframes in arrival order (validation keyframes
are never used for training, not even as photometric sources). Replay draws one stored
training keyframe older than the newest, uniformly, with the caller's ``numpy`` Generator.
"""

from __future__ import annotations

import logging
from bisect import bisect_left
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import torch

from mutualslam_cli.errors import ConfigError, KeyframeError
from mutualslam_cli.types import check_shape

log = logging.getLogger(__name__)


class LabelSource(Protocol):
    """Where a stored keyframe's pose and sparse depth are read at the time they are used (the online
    rule, DESIGN §5): the map as it stands then, not as it stood when the keyframe arrived."""

    def pose(self, kf_id: int) -> np.ndarray:
        """``(4, 4)`` ``T_wc`` of the keyframe now."""

    def sparse(self, kf_id: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``uv (M, 2)`` at network resolution and ``depth (M,)`` (map units) of its map points now."""


@dataclass
class KeyframeSample:
    """One keyframe as the adaptation loop sees it.

    Attributes:
        kf_id: keyframe id (increasing in arrival order).
        image: ``(3, H, W)`` float32 RGB in [0, 1] at network resolution.
        K: ``(3, 3)`` intrinsics at network resolution.
        pose: ``(4, 4)`` ``T_wc`` in the map frame (may be updated later by BA).
        uv: ``(M, 2)`` pixels ``(u, v)`` of the sparse map points at network resolution.
        depth: ``(M,)`` their depth in map units (D_sparse of Eq. 6).
        segment: the front end's tracking segment. Photometric sources come from the same segment
            only: across a re-initialisation the relative pose was not measured (a bridged segment
            is placed by an estimate, :mod:`~mutualslam_cli.backend.bridges`).
    """

    kf_id: int
    image: torch.Tensor
    K: torch.Tensor
    pose: np.ndarray
    uv: torch.Tensor
    depth: torch.Tensor
    segment: int = 0

    def validate(self) -> None:
        """Raise :class:`~mutualslam_cli.errors.ShapeError` on a malformed sample."""
        who = f"keyframe {self.kf_id}"
        check_shape(self.image, [3, "H", "W"], f"{who}: image")
        check_shape(self.K, [3, 3], f"{who}: K")
        check_shape(np.asarray(self.pose), [4, 4], f"{who}: pose")
        check_shape(self.uv, ["M", 2], f"{who}: uv")
        check_shape(self.depth, [self.uv.shape[0]], f"{who}: depth (one per uv row)")


class _Reservoir:
    """Algorithm R (Vitter 1985): a uniform sample of ``size`` items from a stream."""

    def __init__(self, size: int, rng: np.random.Generator) -> None:
        self.size = size
        self.items: list[int] = []
        self.seen = 0
        self._rng = rng

    def offer(self, item: int) -> int | None:
        """Offer one item; return the evicted item (or ``item`` itself if rejected), else None."""
        self.seen += 1
        if len(self.items) < self.size:
            self.items.append(item)
            return None
        j = int(self._rng.integers(0, self.seen))  # Algorithm R: keep with probability size/seen
        if j < self.size:
            out, self.items[j] = self.items[j], item
            return out
        return item


class KeyframeBuffer:
    """Stores keyframes for training, replay and validation.

    Args:
        capacity: 0 = keep every image; otherwise ≥ 3, the number of replayable training
            keyframes (and, separately, of validation keyframes) kept; see the module docstring.
        seed: seed of the eviction generator (replay sampling uses the caller's generator).

    Raises:
        ConfigError: ``capacity`` is negative or 1–2.
    """

    def __init__(self, capacity: int = 0, seed: int = 0, labels: LabelSource | None = None) -> None:
        if capacity < 0 or 0 < capacity < 3:
            raise ConfigError(f"adapt.replay_capacity must be 0 (unbounded) or >= 3, got {capacity}")
        self.capacity = capacity
        self.labels = labels
        self._meta: dict[int, KeyframeSample] = {}  # every keyframe, image dropped when evicted
        self._images: dict[int, torch.Tensor] = {}
        self._train: list[int] = []  # all training ids ever, arrival order
        self._val: list[int] = []  # all validation ids ever
        rng = np.random.default_rng(seed)
        self._train_res = _Reservoir(max(capacity - 2, 0), rng) if capacity else None
        self._val_res = _Reservoir(capacity, rng) if capacity else None

    # ------------------------------------------------------------------ adding
    def add(self, sample: KeyframeSample, training: bool) -> None:
        """Store a keyframe (training or validation); ids must increase.

        Raises:
            ShapeError: malformed sample.
            KeyframeError: ``kf_id`` not larger than every stored id.
        """
        sample.validate()
        if self._meta and sample.kf_id <= max(self._meta):
            raise KeyframeError(f"keyframe ids must increase: got {sample.kf_id} after {max(self._meta)}")
        # the image lives only in ``_images`` (compacted): the sample's float32 copy is 4x its size
        self._meta[sample.kf_id] = replace(sample, image=torch.empty(0, device="cpu"), K=sample.K.cpu(),
                                           pose=np.asarray(sample.pose, dtype=np.float64))
        self._images[sample.kf_id] = _compact(sample.image.cpu())
        if training:
            self._train.append(sample.kf_id)
            if self._train_res is not None and len(self._train) > 2:
                self._train_res.offer(self._train[-3])  # left the recent window of two
                self._collect()
        else:
            self._val.append(sample.kf_id)
            if self._val_res is not None:
                out = self._val_res.offer(sample.kf_id)
                if out is not None:
                    self._drop(out)

    def _collect(self) -> None:
        """Drop training images that neither the recent window nor a reservoir member needs."""
        assert self._train_res is not None
        keep = set(self._train[-2:])
        for k in self._train_res.items:
            keep.add(k)
            keep.update(self._adjacent(k))
        for k in self._train[:-2]:
            if k not in keep and k in self._images:
                self._drop(k)

    def _drop(self, kf_id: int) -> None:
        self._images.pop(kf_id, None)

    @property
    def nbytes(self) -> int:
        """Bytes of every tensor held: stored images and every keyframe's K, pixels and depths."""
        meta = sum(t.numel() * t.element_size() for m in self._meta.values() for t in (m.image, m.K, m.uv, m.depth))
        return meta + sum(t.numel() * t.element_size() for t in self._images.values())

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        """Number of keyframes whose image is stored."""
        return len(self._images)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._images

    def get(self, kf_id: int, device: torch.device | str | None = None) -> KeyframeSample:
        """The stored sample (with the latest pose and sparse points); its image on ``device`` (default the CPU),
        ``K``, ``uv`` and ``depth`` on the CPU.

        Raises:
            KeyframeError: unknown id or image evicted.
        """
        if kf_id not in self._images:
            raise KeyframeError(f"keyframe {kf_id} is not stored (unknown or evicted)")
        img = self._images[kf_id]
        if device is not None:
            img = img.to(device, non_blocking=True)
        meta = self._meta[kf_id]
        if self.labels is not None:  # the map as it stands now (DESIGN §5), not as it stood at arrival
            uv, d = self.labels.sparse(kf_id)
            meta = replace(meta, pose=self.labels.pose(kf_id), uv=uv, depth=d)
        return replace(meta, image=img.float().div_(255.0) if img.dtype == torch.uint8 else img)

    def pose(self, kf_id: int) -> np.ndarray:
        """A copy of the current ``(4, 4)`` ``T_wc`` of a known keyframe (its image stored or not), without its image.

        Raises:
            KeyframeError: unknown id.
        """
        if kf_id not in self._meta:
            raise KeyframeError(f"keyframe {kf_id} is unknown")
        return self.labels.pose(kf_id) if self.labels is not None else self._meta[kf_id].pose.copy()

    def segment(self, kf_id: int) -> int:
        """The tracking segment of a known keyframe (:attr:`KeyframeSample.segment`).

        Raises:
            KeyframeError: unknown id.
        """
        if kf_id not in self._meta:
            raise KeyframeError(f"keyframe {kf_id} is unknown")
        return self._meta[kf_id].segment

    @property
    def training_ids(self) -> list[int]:
        """Stored training keyframe ids, arrival order."""
        return [k for k in self._train if k in self._images]

    @property
    def validation_ids(self) -> list[int]:
        """Stored validation keyframe ids, arrival order."""
        return [k for k in self._val if k in self._images]

    @property
    def all_ids(self) -> list[int]:
        """Every stored keyframe id (training and validation), sorted."""
        return sorted(self._images)

    def is_training(self, kf_id: int) -> bool:
        i = bisect_left(self._train, kf_id)
        return i < len(self._train) and self._train[i] == kf_id

    def _adjacent(self, kf_id: int) -> list[int]:
        """Previous and next training ids in arrival order (stored or not)."""
        i = bisect_left(self._train, kf_id)
        if i >= len(self._train) or self._train[i] != kf_id:
            return []
        return [self._train[j] for j in (i - 1, i + 1) if 0 <= j < len(self._train)]

    def neighbours(self, kf_id: int) -> list[int]:
        """Stored photometric sources of training keyframe ``kf_id``: s ∈ {i−1, i+1} (Eq. 4), of its segment.

        Only *training* keyframes adjacent in time count; for the newest keyframe that is just
        the previous one. Empty for the first training keyframe or an unknown id.
        """
        seg = self._meta[kf_id].segment if kf_id in self._meta else None
        return [k for k in self._adjacent(kf_id) if k in self._images and self._meta[k].segment == seg]

    def recent(self, k: int) -> list[int]:
        """The ``k`` most recent training ids, newest first."""
        return list(reversed(self._train[-k:])) if k > 0 else []

    def replay_candidates(self, newest: int) -> list[int]:
        """Training ids older than ``newest`` that may be replayed, arrival order.

        ``capacity == 0``: every stored training keyframe with a stored neighbour. Otherwise the
        reservoir members and the recent window only (images kept merely as photometric sources
        of a reservoir member are not candidates, so replay stays uniform over the past).
        """
        pool = self.training_ids
        if self._train_res is not None:
            allowed = set(self._train_res.items) | set(self._train[-2:])
            pool = [k for k in pool if k in allowed]
        return [k for k in pool if k < newest and self.neighbours(k)]

    def sample_older(self, newest: int, rng: np.random.Generator) -> int | None:
        """One training keyframe older than ``newest``, uniform over :meth:`replay_candidates`.

        Paper Alg. 2: K_j, j ~ U{0, …, i−1}. Returns None when there is none.
        """
        cand = self.replay_candidates(newest)
        if not cand:
            return None
        return cand[int(rng.integers(0, len(cand)))]

    # ------------------------------------------------------------------ feedback from BA
    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """Replace ``T_wc`` of known keyframes (BA output); unknown ids are ignored.

        Returns:
            Number of keyframes updated.

        Raises:
            ShapeError: a pose is not 4×4.
        """
        n = 0
        for k, T in poses.items():
            if k in self._meta:
                T = np.asarray(T, dtype=np.float64)
                check_shape(T, [4, 4], f"update_poses: pose of keyframe {k}")
                self._meta[k] = replace(self._meta[k], pose=T)
                n += 1
        return n

    def update_sparse(self, points: Mapping[int, tuple[torch.Tensor, torch.Tensor]]) -> int:
        """Replace the sparse points ``(uv (M, 2), depth (M,))`` of known keyframes.

        Returns:
            Number of keyframes updated.

        Raises:
            ShapeError: malformed ``uv``/``depth``.
        """
        n = 0
        for k, (uv, d) in points.items():
            if k in self._meta:
                uv = torch.as_tensor(uv, dtype=torch.float32, device="cpu")
                d = torch.as_tensor(d, dtype=torch.float32, device="cpu")
                check_shape(uv, ["M", 2], f"update_sparse: uv of keyframe {k}")
                check_shape(d, [uv.shape[0]], f"update_sparse: depth of keyframe {k}")
                self._meta[k] = replace(self._meta[k], uv=uv, depth=d)
                n += 1
        return n


def _compact(image: torch.Tensor) -> torch.Tensor:
    """``image`` as uint8 when ``round(255·x)/255 == x`` exactly (lossless), else unchanged."""
    if image.dtype != torch.float32:
        return image
    q = (image * 255.0).round_().clamp_(0, 255).to(torch.uint8)
    return q if torch.equal(q.float().div_(255.0), image) else image

"""Grey images of old keyframes decoded again when asked, a few kept (:class:`KeyframeImages`): what map reuse and
relocalisation match old points from, with memory flat in the sequence's length.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import numpy as np

IMAGE_CACHE = 8
"""Decoded old keyframe images kept (least recently used dropped)."""


class KeyframeImages:
    """Grey images of old keyframes, decoded from the sequence on demand and kept in a small LRU.

    Args:
        load: ``load(frame)`` → ``(H, W)`` uint8 grey image of a frame (the sequence's ``load_gray``).
        size: images kept.
    """

    def __init__(self, load: Callable[[int], np.ndarray], size: int = IMAGE_CACHE) -> None:
        self.load, self.size = load, size
        self._lru: OrderedDict[int, np.ndarray] = OrderedDict()
        self.decoded = 0

    def get(self, frame: int) -> np.ndarray:
        """The grey image of ``frame``."""
        if frame in self._lru:
            self._lru.move_to_end(frame)
            return self._lru[frame]
        img = self.load(frame)
        self.decoded += 1
        self._lru[frame] = img
        while len(self._lru) > self.size:
            self._lru.popitem(last=False)
        return img

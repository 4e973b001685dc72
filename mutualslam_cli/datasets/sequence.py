"""The loaded-sequence type every loader returns and every stage reads frames from.

Frames are streamed: a :class:`Sequence` holds paths and GT poses, never decoded images,
so memory stays flat in sequence length.
"""

from __future__ import annotations

import logging
from collections.abc import Generator, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from mutualslam_cli.datasets.image_files import image_file_problem
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import FrameRef, Intrinsics, JSONObject, Trajectory

log = logging.getLogger(__name__)


#: Frames per second of ICL-NUIM's renderings, whose timestamps are frame numbers (Handa et al. 2014).
ICL_FPS = 30.0


class Association(TypedDict, total=False):
    """How a loader paired images: from which listing (``source``), the counts of each side and of the pairs, the
    largest time gap of a pair (s), and whether ``associations.txt`` lists depth first."""

    source: str
    rgb: int
    depth: int
    pairs: int
    max_dt: float
    depth_first: bool


class SequenceMeta(TypedDict, total=False):
    """:attr:`Sequence.meta`: the facts a loader decided, written into manifests. Each loader sets its own part:
    ``format`` always; TUM-layout folders ``association``, ``intrinsics_source``, ``gt_file`` and ``warnings``;
    ICL-NUIM ``depth_unit_m`` (metres per raw unit) and ``depth`` (what the raw values are); the fy sign's
    decision (:func:`~mutualslam_cli.datasets.fy_sign.apply_fy_sign`); a subset's ``stride``/``max_frames``/
    ``frames``; a converted recording's ``source.json``."""

    format: str
    association: Association
    gt_file: str | None
    intrinsics_source: str
    depth_unit_m: float
    depth: str
    fy_sign: int
    fy_sign_errors: dict[str, float] | None
    fy_sign_source: str
    subset: dict[str, int]
    recording: JSONObject
    warnings: list[str]


@dataclass
class Sequence:
    """An associated RGB-D sequence on disk.

    Attributes:
        name: short name (used in result paths).
        root: the sequence folder.
        intrinsics: camera at the stored image resolution (``dist`` set for raw fr1).
        depth_scale: raw depth units per metre; ``load_depth`` divides by it.
        frames: associated frames in time order.
        gt: full ground-truth trajectory as stored (not only at image times), or ``None``.
        meta: facts decided while loading (:class:`SequenceMeta`: ``format``, ``fy_sign`` …),
            written into manifests.
    """

    name: str
    root: Path
    intrinsics: Intrinsics
    depth_scale: float
    frames: list[FrameRef]
    gt: Trajectory | None = None
    meta: SequenceMeta = field(default_factory=lambda: SequenceMeta())

    def seconds(self, i: int) -> float:
        """Time of frame ``i`` in seconds: its timestamp, except ICL-NUIM's, which are frame numbers of a
        30 frames/s rendering (:data:`ICL_FPS`)."""
        t = float(self.frames[i].timestamp)
        return t / ICL_FPS if self.meta.get("format") in ("icl", "icl_loop") else t

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def has_gt_poses(self) -> bool:
        """True when at least one frame has a GT pose."""
        return any(f.pose is not None for f in self.frames)

    @property
    def has_depth(self) -> bool:
        """True when at least one frame has a depth image."""
        return any(f.depth_path is not None for f in self.frames)

    def gt_at_frames(self) -> Trajectory | None:
        """GT poses at the image times of the frames that have one, or ``None``."""
        idx = [i for i, f in enumerate(self.frames) if f.pose is not None]
        if not idx:
            return None
        return Trajectory(
            np.array([self.frames[i].timestamp for i in idx]),
            np.stack([self.frames[i].pose for i in idx]),  # type: ignore[misc]
        )

    def _read(self, i: int, flags: int) -> np.ndarray:
        """Frame ``i`` decoded with ``flags``, its file structure checked first (a truncated PNG is named, not
        decoded partially) and its size checked against the sequence's (the intrinsics')."""
        path = self.frames[i].rgb_path
        try:
            data = Path(path).read_bytes()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read image ({e.strerror})") from None
        problem = image_file_problem(Path(path), data)
        if problem:
            raise DatasetError(f"{path}: {problem}; expected a complete colour image file (mslam datasets check "
                               "finds every such file)")
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
        if img is None:
            raise DatasetError(f"{path}: cannot read image (expected a PNG/JPEG colour image)")
        w, h = self.intrinsics.width, self.intrinsics.height
        if w and h and img.shape[:2] != (h, w):  # else the front end fails deep inside OpenCV
            raise DatasetError(f"{path}: frame {i} is {img.shape[1]}×{img.shape[0]}, expected {w}×{h} like the "
                               "sequence's first frame; every frame must have one size (mslam datasets check "
                               "finds them all)")
        return img

    def load_rgb(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(H, W, 3)`` uint8 RGB; :class:`DatasetError` when it is not the sequence's size."""
        return cv2.cvtColor(self._read(i, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)

    def load_gray(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(H, W)`` uint8 grey; :class:`DatasetError` when it is not the sequence's size."""
        return self._read(i, cv2.IMREAD_GRAYSCALE)

    def load_depth(self, i: int) -> np.ndarray | None:
        """Frame ``i`` depth as ``(H, W)`` float32 metres (0 = invalid), or ``None``.

        Raises :class:`DatasetError` for a depth PNG that is not 16-bit single-channel.
        """
        path = self.frames[i].depth_path
        if path is None:
            return None
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"{path}: cannot read depth image (expected a 16-bit PNG)")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(
                f"{path}: depth image is {raw.dtype} with {1 if raw.ndim == 2 else raw.shape[2]} "
                f"channel(s); expected a 16-bit single-channel PNG ({self.depth_scale:g} = 1 m)"
            )
        return raw.astype(np.float32) / np.float32(self.depth_scale)

    def iter_frames(self, with_depth: bool = False) -> Iterator[tuple[FrameRef, np.ndarray, np.ndarray | None]]:
        """Yield ``(frame, rgb, depth_or_None)`` in order, one decoded frame at a time."""
        for i, f in enumerate(self.frames):
            yield f, self.load_rgb(i), (self.load_depth(i) if with_depth else None)


def grey_frames(seq: Sequence, start: int = 0) -> Generator[tuple[int, np.ndarray], None, None]:
    """``(i, grey image)`` for frames ``start…`` in order; frame i+1 is decoded on a second thread while
    the caller works on frame i."""
    n = len(seq)
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        nxt = pool.submit(seq.load_gray, start) if start < n else None
        for i in range(start, n):
            assert nxt is not None  # submitted before the loop (start < n) and at each turn below
            gray = nxt.result()
            if i + 1 < n:
                nxt = pool.submit(seq.load_gray, i + 1)
            yield i, gray
    finally:
        pool.shutdown(wait=True, cancel_futures=True)

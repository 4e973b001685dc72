"""Synthetic RGB-D sequences with exact z-depth and poses (DESIGN §3 "Synthetic").

Scenes are unions of axis-aligned boxes: an enclosing box seen from inside (the room) plus
boxes seen from outside (furniture, panels, pillars). Each frame is ray-cast analytically
(slab method, Kay & Kajiya 1986; :mod:`~mutualslam_cli.datasets.synthetic.raycast`): camera rays
``d = R_wc K⁻¹ [u, v, 1]ᵀ`` have unit camera z, so the ray parameter at the hit *is* the
z-depth. Texture coordinates come from the hit point and are sampled from a mip-mapped atlas
(:mod:`textures`) with ``cv2.remap``. This module owns the sequences: scene setup, camera
path, rendering frame by frame, and writing the TUM RGB-D layout.

World frame: z up; the camera follows a smooth handheld-like path (sums of low-frequency
sinusoids with seed-dependent phases), OpenCV camera axes (x right, y down, z forward).

Scenes (``target`` domain / ``source`` domain):

- ``room``: 4×3×2.6 m room with boxes and wall panels, camera at 1.45 m looking around /
  a larger 6.5–8 × 5–6.5 × 2.9–3.5 m room, more and taller furniture, camera at 1.05 m.
- ``planar``: one textured wall 1.3–1.7 m ahead, motion parallel to it (TUM
  ``nostructure_texture``-like) / wall 0.7–1.0 m ahead.
- ``far``: pillars and boxes 3–6 m ahead, back wall at 8 m (TUM ``structure_texture_far``-like)
  / objects at 6–10 m, back wall at 13 m, camera at 2 m.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.synthetic import scenes
from mutualslam_cli.datasets.synthetic.raycast import Renderer
from mutualslam_cli.datasets.synthetic.scenes import SCENES, SceneDef, camera_pose
from mutualslam_cli.datasets.synthetic.textures import STYLES, build_atlas, face_texture
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import Intrinsics, Trajectory, check_shape

log = logging.getLogger(__name__)

__all__ = [
    "SCENES",
    "SyntheticSequence",
    "bench_render",
    "iter_render",
    "render_sequence",
    "synthetic_intrinsics",
    "write_tum",
]

FPS = 30.0
DEPTH_SCALE = 5000.0
"""TUM depth PNG units per metre."""
_REF_PPM = 300.0
"""Nominal texel density (texels/m at 640×480) at which texture features have their base size."""
MAX_PNG_DEPTH = 13.1
"""Depths beyond this (metres) are written as 0 (invalid): 65535 / 5000 ≈ 13.107 m."""


@dataclass
class SyntheticSequence:
    """A rendered sequence held in memory.

    Attributes:
        rgb: ``(N, H, W, 3)`` uint8 RGB.
        depth: ``(N, H, W)`` float32 z-depth in metres, > 0 everywhere.
        poses: ``(N, 4, 4)`` float64 ``T_wc`` camera-to-world.
        timestamps: ``(N,)`` float64 seconds, ``i / 30``.
        intrinsics: pinhole, no distortion.
        scene, domain, seed: the arguments it was rendered with.
    """

    rgb: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    timestamps: np.ndarray
    intrinsics: Intrinsics
    scene: str
    domain: str
    seed: int

    def __len__(self) -> int:
        return len(self.timestamps)


def synthetic_intrinsics(width: int, height: int) -> Intrinsics:
    """The synthetic camera: 525 px focal length at 640×480 (TUM-like), principal point centred."""
    return Intrinsics(fx=525.0 * width / 640.0, fy=525.0 * height / 480.0,
                      cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width), height=int(height))


def _check_args(scene: str, n_frames: int, width: int, height: int, domain: str) -> None:
    if scene not in SCENES:
        raise ConfigError(f"unknown synthetic scene {scene!r}; valid scenes: {', '.join(SCENES)}")
    if domain not in ("target", "source"):
        raise ConfigError(f"unknown synthetic domain {domain!r}; expected 'target' or 'source'")
    if int(n_frames) < 1:
        raise ConfigError(f"n_frames must be ≥ 1, got {n_frames}")
    if int(width) < 8 or int(height) < 8 or int(width) > 4096 or int(height) > 4096:
        raise ConfigError(f"image size {width}×{height}: expected 8..4096 pixels per side")


@functools.lru_cache(maxsize=2)
def _setup(scene: str, width: int, height: int, seed: int, domain: str) -> tuple[SceneDef, Renderer]:
    """Scene layout, textures and renderer (cached: texture synthesis dominates setup)."""
    intr = synthetic_intrinsics(width, height)
    sdef = scenes.build_scene(scene, seed, domain)
    style = STYLES[domain]
    # Texel density follows the render resolution (capped: above 2× 640×480 textures magnify).
    res = min(intr.fx / 525.0, 2.0)
    tex_rng = np.random.default_rng(np.random.SeedSequence([seed, SCENES.index(scene), domain == "source", 7]))
    textures = []
    for f in range(len(sdef.face_axis)):
        ppm = sdef.face_ppm[f] * res
        # Feature sizes follow the nominal texel density (i.e. the typical viewing distance).
        fs = max(0.5, _REF_PPM / sdef.face_ppm[f])
        textures.append(face_texture(tex_rng, sdef.face_w[f], sdef.face_h[f], max(ppm, 4.0), style, fs))
    atlas = build_atlas(textures, sdef.face_amin, sdef.face_bmin,
                        np.array([max(p * res, 4.0) for p in sdef.face_ppm]), sdef.face_brightness)
    return sdef, Renderer(sdef, atlas, intr)


def iter_render(
    scene: str = "room", n_frames: int = 60, width: int = 640, height: int = 480, seed: int = 0,
    domain: Literal["target", "source"] = "target",
) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Render a sequence frame by frame (constant memory).

    Yields:
        ``(i, rgb, depth, pose)``: frame index, ``(H, W, 3)`` uint8 RGB, ``(H, W)`` float32
        z-depth in metres (> 0), ``(4, 4)`` float64 ``T_wc``. Frame ``i`` is at ``i / 30`` s.

    Raises:
        ConfigError: unknown scene or domain, or bad sizes.
    """
    _check_args(scene, n_frames, width, height, domain)
    sdef, renderer = _setup(scene, int(width), int(height), int(seed), domain)
    for i in range(int(n_frames)):
        T = camera_pose(sdef.path, i / FPS)
        rgb, depth = renderer.render(T)
        yield i, rgb, depth, T


def render_sequence(scene: str = "room", n_frames: int = 60, width: int = 640, height: int = 480, seed: int = 0,
                    domain: Literal["target", "source"] = "target") -> SyntheticSequence:
    """Render a whole sequence into memory (see :func:`iter_render` for the frames)."""
    _check_args(scene, n_frames, width, height, domain)
    n = int(n_frames)
    rgb = np.empty((n, height, width, 3), np.uint8)
    depth = np.empty((n, height, width), np.float32)
    poses = np.empty((n, 4, 4), np.float64)
    for i, c, d, T in iter_render(scene, n, width, height, seed, domain):
        rgb[i], depth[i], poses[i] = c, d, T
    return SyntheticSequence(rgb, depth, poses, np.arange(n, dtype=np.float64) / FPS,
                             synthetic_intrinsics(width, height), scene, domain, int(seed))


def _frames_of(seq: SyntheticSequence) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    for i in range(len(seq)):
        yield i, seq.rgb[i], seq.depth[i], seq.poses[i]


def write_tum(seq_or_iter: SyntheticSequence | Iterable[tuple[int, np.ndarray, np.ndarray, np.ndarray]], out: Path,
              *, scene: str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, domain: str | None = None, intrinsics: Intrinsics | None = None,
              fps: float = FPS, on_frame: Callable[[int], None] | None = None) -> Path:
    """Write a sequence in TUM RGB-D layout (streams an iterator of ``(i, rgb, depth, T_wc)``).

    Files: ``rgb/<t>.png`` (8-bit colour), ``depth/<t>.png`` (16-bit, metres × 5000, 0 where
    the depth is > 13.1 m or not finite/positive), ``rgb.txt``, ``depth.txt``,
    ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world) and
    ``intrinsics.txt`` (``fx fy cx cy width height``). Timestamps are ``i / fps`` with 6 decimals.

    Args:
        seq_or_iter: a :class:`SyntheticSequence`, or an iterable as yielded by :func:`iter_render`.
        out: output folder (created).
        scene, seed, domain: recorded in the file headers.
        width, height: image size; frames of another size raise :class:`ShapeError`.
        intrinsics: written to ``intrinsics.txt``; defaults to the sequence's, else
            :func:`synthetic_intrinsics` of ``width × height`` or of the first frame's size.
        on_frame: called with the frame index after each frame is written.

    Returns:
        ``out``.
    """
    out = Path(out)
    if isinstance(seq_or_iter, SyntheticSequence):
        intrinsics = intrinsics or seq_or_iter.intrinsics
        scene, seed, domain = seq_or_iter.scene, seq_or_iter.seed, seq_or_iter.domain
        frames: Iterable = _frames_of(seq_or_iter)
    else:
        frames = seq_or_iter
    if intrinsics is None and width is not None and height is not None:
        intrinsics = synthetic_intrinsics(int(width), int(height))
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    what = f"mslam synth scene={scene} domain={domain} seed={seed}"
    rgb_lines = ["# color images", f"# {what}", "# timestamp filename"]
    dep_lines = ["# depth maps", f"# {what}", "# timestamp filename"]
    gt_times: list[float] = []
    gt_poses: list[np.ndarray] = []
    n_written = 0
    for i, rgb, depth, T in frames:
        if intrinsics is None:
            intrinsics = synthetic_intrinsics(rgb.shape[1], rgb.shape[0])
        check_shape(rgb, [intrinsics.height, intrinsics.width, 3], f"write_tum frame {i} rgb")
        check_shape(depth, [intrinsics.height, intrinsics.width], f"write_tum frame {i} depth")
        check_shape(T, [4, 4], f"write_tum frame {i} pose")
        n_written += 1
        ts = f"{i / fps:.6f}"
        cv2.imwrite(str(out / "rgb" / f"{ts}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        d = np.where(np.isfinite(depth) & (depth > 0) & (depth <= MAX_PNG_DEPTH), depth, 0.0)
        cv2.imwrite(str(out / "depth" / f"{ts}.png"), np.round(d * DEPTH_SCALE).astype(np.uint16))
        rgb_lines.append(f"{ts} rgb/{ts}.png")
        dep_lines.append(f"{ts} depth/{ts}.png")
        gt_times.append(i / fps)
        gt_poses.append(T)
        if on_frame is not None:
            on_frame(i)
    if n_written == 0:
        raise ConfigError(f"write_tum {out}: no frames to write (expected ≥ 1 frame)")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", dep_lines)):
        (out / name).write_text("\n".join(lines) + "\n", encoding="utf-8")
    # A plain file like its neighbours (no temporary file, default mode): a stream, not a path.
    with open(out / "groundtruth.txt", "w", encoding="utf-8") as f:
        write_tum_trajectory(f, Trajectory(np.asarray(gt_times), np.stack(gt_poses)),
                             comments=("ground truth trajectory", what), time_format=".6f", value_format=".9f")
    k = intrinsics
    assert k is not None
    (out / "intrinsics.txt").write_text(f"{k.fx:.6f} {k.fy:.6f} {k.cx:.6f} {k.cy:.6f} {k.width} {k.height}\n",
                                        encoding="utf-8")
    log.info("wrote %d frames to %s", n_written, out)
    return out


def bench_render(width: int = 640, height: int = 480, n: int = 30, scene: str = "room") -> dict:
    """Rendering speed (texture synthesis excluded, reported separately as ``setup_s``).

    Returns:
        ``{"fps", "ms_per_frame", "cpu_ms_per_frame", "setup_s", "width", "height", "n", "scene"}``
        (``cpu_ms_per_frame`` is process CPU time, all threads: less sensitive to a busy machine).
    """
    t0 = time.perf_counter()
    _setup.cache_clear()
    sdef, renderer = _setup(scene, int(width), int(height), 12345, "target")
    setup = time.perf_counter() - t0
    poses = [camera_pose(sdef.path, i / FPS) for i in range(int(n))]
    renderer.render(poses[0])  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    for T in poses:
        renderer.render(T)
    dt = (time.perf_counter() - t0) / max(1, int(n))
    cpu = (time.process_time() - c0) / max(1, int(n))
    return {"fps": 1.0 / dt, "ms_per_frame": 1000.0 * dt, "cpu_ms_per_frame": 1000.0 * cpu, "setup_s": setup,
            "width": int(width), "height": int(height), "n": int(n), "scene": scene}

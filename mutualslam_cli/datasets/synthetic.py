"""Synthetic RGB-D sequences with exact z-depth and poses (DESIGN §3 "Synthetic").

Scenes are unions of axis-aligned boxes: an enclosing box seen from inside (the room) plus
boxes seen from outside (furniture, panels, pillars). Each frame is ray-cast analytically
(slab method, Kay & Kajiya 1986): camera rays ``d = R_wc K⁻¹ [u, v, 1]ᵀ`` have unit camera
z, so the ray parameter at the hit *is* the z-depth. Texture coordinates come from the hit
point and are sampled from a mip-mapped atlas (:mod:`textures`) with ``cv2.remap``.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Literal

import cv2
import numpy as np

from mutualslam_cli.datasets import scenes as _scenes
from mutualslam_cli.datasets.scenes import SCENES, SceneDef, camera_pose
from mutualslam_cli.datasets.textures import N_LEVELS, STYLES, Atlas, build_atlas, face_texture

assert N_LEVELS == 4, "_Renderer._shade blends mip levels 0..3"
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.geometry import rot_to_quat
from mutualslam_cli.types import Intrinsics, check_shape

log = logging.getLogger(__name__)

__all__ = ["SCENES", "SyntheticSequence", "render_sequence", "iter_render", "write_tum", "bench_render",
           "synthetic_intrinsics"]

FPS = 30.0
DEPTH_SCALE = 5000.0
"""TUM depth PNG units per metre."""
_BOX_EDGES = [(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit]
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


class _Renderer:
    """Ray-caster of one scene at one resolution (precomputed rays, atlas)."""

    def __init__(self, scene: SceneDef, atlas: Atlas, intr: Intrinsics) -> None:
        self.scene, self.atlas, self.intr = scene, atlas, intr
        W, H = intr.width, intr.height
        self.xn = ((np.arange(W, dtype=np.float64) - intr.cx) / intr.fx).astype(np.float32)
        self.yn = ((np.arange(H, dtype=np.float64) - intr.cy) / intr.fy).astype(np.float32)
        # |K⁻¹[u, v, 1]| per pixel (rotation-invariant): ray length per unit z-depth.
        self.rnorm = np.sqrt(1.0 + self.xn[None, :] ** 2 + self.yn[:, None] ** 2).astype(np.float32)
        self.f_pix = float(np.sqrt(abs(intr.fx * intr.fy)))
        # Per-face lookup tables for cv2.LUT (face id is uint8 → ≤ 256 faces, 42 boxes).
        F = len(scene.face_axis)
        if F > 256:
            raise ConfigError(f"synthetic scene has {F} faces; at most 256 are supported")
        self.a_idx = np.array([(1, 0, 0)[k] for k in scene.face_axis])  # in-plane axes per face
        self.b_idx = np.array([(2, 2, 1)[k] for k in scene.face_axis])
        self.lut = {}
        for name, val, dt in (("axis", scene.face_axis, np.uint8), ("scale", atlas.scale, np.float32),
                              ("ox", atlas.ox + np.float32(0.5), np.float32),
                              ("oy", atlas.oy + np.float32(0.5), np.float32)):
            t = np.zeros((1, 256), dt)
            t[0, :F] = val
            self.lut[name] = t

    def _rays(self, R: np.ndarray) -> list[np.ndarray]:
        """World ray directions (3 × ``(H, W)`` float32), camera z component = 1."""
        out = []
        for k in range(3):
            row = (R[k, 0] * self.xn).astype(np.float32)[None, :]
            col = (R[k, 1] * self.yn + R[k, 2]).astype(np.float32)[:, None]
            out.append(row + col)
        return out

    def render(self, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame: ``(H, W, 3)`` uint8 RGB and ``(H, W)`` float32 z-depth (metres)."""
        R, o = T_wc[:3, :3], T_wc[:3, 3]
        d = self._rays(R)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = [np.float32(1.0) / dk for dk in d]
            depth, fid = self._enclosure(o, inv)
            for b in range(1, len(self.scene.boxes)):
                self._box(b, T_wc, o, inv, depth, fid)
        return self._shade(o, d, depth, fid), depth

    def _enclosure(self, o: np.ndarray, inv: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Exit of the rays from the enclosing box (camera inside): depth and face id."""
        lo, hi = self.scene.boxes[0].lo, self.scene.boxes[0].hi
        ts, sides = [], []
        for k in range(3):
            # Camera inside: hi − o > 0 > lo − o, so the exit is the positive one of the two.
            t = np.maximum(np.float32(hi[k] - o[k]) * inv[k], np.float32(lo[k] - o[k]) * inv[k])
            ts.append(t)
            sides.append((inv[k] > 0).view(np.uint8))
        depth = np.minimum(np.minimum(ts[0], ts[1]), ts[2])
        m0 = ts[0] == depth
        m1 = ts[1] == depth
        fid = np.where(m0, sides[0], np.where(m1, sides[1] + np.uint8(2), sides[2] + np.uint8(4)))
        return depth, fid

    def _roi(self, b: int, T_wc: np.ndarray) -> tuple[slice, slice] | None:
        """Image rows/cols that box ``b`` can cover (its projected corners' bounding box)."""
        box = self.scene.boxes[b]
        corners = np.array([[x, y, z] for x in (box.lo[0], box.hi[0]) for y in (box.lo[1], box.hi[1])
                            for z in (box.lo[2], box.hi[2])])
        pc = (corners - T_wc[:3, 3]) @ T_wc[:3, :3]
        zn = 1e-3
        front = pc[:, 2] >= zn
        if not front.any():
            return None
        pts = [pc[front]]
        if not front.all():
            # Clip the box by the plane z = zn: add where its edges cross it (corners i, j
            # differ in one coordinate bit). The hull of the projections bounds the image.
            for i, j in _BOX_EDGES:
                if front[i] != front[j]:
                    a_, b_ = pc[i], pc[j]
                    pts.append((a_ + (zn - a_[2]) / (b_[2] - a_[2]) * (b_ - a_))[None])
        pv = np.concatenate(pts)
        H, W = self.intr.height, self.intr.width
        u = self.intr.fx * pv[:, 0] / pv[:, 2] + self.intr.cx
        v = self.intr.fy * pv[:, 1] / pv[:, 2] + self.intr.cy
        u, v = np.clip(u, -2.0, W + 2.0), np.clip(v, -2.0, H + 2.0)
        c0, c1 = max(0, int(np.floor(u.min())) - 1), min(W, int(np.ceil(u.max())) + 2)
        r0, r1 = max(0, int(np.floor(v.min())) - 1), min(H, int(np.ceil(v.max())) + 2)
        if c0 >= c1 or r0 >= r1:
            return None
        return slice(r0, r1), slice(c0, c1)

    def _box(self, b: int, T_wc: np.ndarray, o: np.ndarray, inv: list[np.ndarray],
             depth: np.ndarray, fid: np.ndarray) -> None:
        """Z-buffer the entry points of the rays into box ``b`` (seen from outside)."""
        roi = self._roi(b, T_wc)
        if roi is None:
            return
        box = self.scene.boxes[b]
        tn, tf, sides = [], None, []
        for k in range(3):
            ik = inv[k][roi]
            t1 = np.float32(box.lo[k] - o[k]) * ik
            t2 = np.float32(box.hi[k] - o[k]) * ik
            tn.append(np.minimum(t1, t2))
            far = np.maximum(t1, t2)
            tf = far if tf is None else np.minimum(tf, far)
            sides.append((ik < 0).view(np.uint8))  # entering through the hi face when moving towards −axis
        tnear = np.maximum(np.maximum(tn[0], tn[1]), tn[2])
        hit = (tnear < tf) & (tnear > 1e-4) & (tnear < depth[roi])
        if not hit.any():
            return
        m0, m1 = tn[0] == tnear, tn[1] == tnear
        base = np.uint8(6 * b)
        local = np.where(m0, sides[0] + base,
                         np.where(m1, sides[1] + (base + np.uint8(2)), sides[2] + (base + np.uint8(4))))
        np.copyto(depth[roi], tnear, where=hit)
        np.copyto(fid[roi], local, where=hit)

    def _shade(self, o: np.ndarray, d: list[np.ndarray], depth: np.ndarray, fid: np.ndarray) -> np.ndarray:
        """Trilinear atlas lookup at the hit points: ``(H, W, 3)`` uint8."""
        at, lut = self.atlas, self.lut
        axis = cv2.LUT(fid, lut["axis"])
        ax0, ax2 = axis == 0, axis == 2
        # In-plane coordinates (a, b): x-faces (y, z), y-faces (x, z), z-faces (x, y).
        # Level-0 texel (+0.5) of the hit o + depth·d: (o_a + depth·d_a)·scale + ox + 0.5, with the
        # per-face constant o_a·scale + ox + 0.5 folded into a per-frame lookup table.
        F = len(self.a_idx)
        cx, cy = np.zeros((1, 256), np.float32), np.zeros((1, 256), np.float32)
        cx[0, :F] = o[self.a_idx] * at.scale + lut["ox"][0, :F]
        cy[0, :F] = o[self.b_idx] * at.scale + lut["oy"][0, :F]
        sc = cv2.LUT(fid, lut["scale"])
        x0 = np.where(ax0, d[1], d[0])
        x0 *= depth
        x0 *= sc
        x0 += cv2.LUT(fid, cx)
        y0 = np.where(ax2, d[1], d[2])
        y0 *= depth
        y0 *= sc
        y0 += cv2.LUT(fid, cy)
        # Texel footprint (texels per pixel): a pixel spans depth / (|d|·f) metres across the
        # ray; on the surface that is stretched by 1/cosθ (cosθ = |d_axis| / |d|) along one
        # axis; isotropic estimate = geometric mean → depth·scale / (f·sqrt(|d|·|d_axis|)).
        dn = np.abs(np.where(ax0, d[0], np.where(ax2, d[2], d[1])))
        dn *= self.rnorm
        np.maximum(dn, np.float32(1e-6), out=dn)
        foot = depth * sc
        foot /= np.sqrt(dn, out=dn)
        foot *= np.float32(1.0 / self.f_pix)
        # Mip level l0 ∈ {0, 1, 2} and its scale s0 = 2^-l0; blend weight linear in the
        # footprint between levels l0 and l0 + 1 (Williams 1983, trilinear filtering).
        s0 = np.float32(1.0) - np.float32(0.5) * (foot >= 2) - np.float32(0.25) * (foot >= 4)
        frac = foot * s0
        frac -= 1.0
        np.clip(frac, 0.0, 1.0, out=frac)
        # Level-0 texel → level-l texel: x_l = (x0 + 0.5)·2^-l − 0.5 + origin_l.
        xa = x0 * s0
        ya = y0 * s0
        W0, H0 = np.float32(at.w0), np.float32(at.h0)
        xb = xa * np.float32(0.5)
        xb += W0 - np.float32(0.5)
        yb = ya * np.float32(0.5)
        yb += H0 * (np.float32(1.0) - s0) - np.float32(0.5)
        xa += W0 * (s0 < 1) - np.float32(0.5)
        ya += np.maximum(H0 * (np.float32(1.0) - 2 * s0), 0) - np.float32(0.5)
        img_a = cv2.remap(at.image, xa, ya, cv2.INTER_LINEAR)
        img_b = cv2.remap(at.image, xb, yb, cv2.INTER_LINEAR)
        out = cv2.blendLinear(img_a, img_b, np.float32(1.0) - frac, frac)
        return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB)


@functools.lru_cache(maxsize=2)
def _setup(scene: str, width: int, height: int, seed: int, domain: str) -> tuple[SceneDef, _Renderer]:
    """Scene layout, textures and renderer (cached: texture synthesis dominates setup)."""
    intr = synthetic_intrinsics(width, height)
    sdef = _scenes.build_scene(scene, seed, domain)
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
    return sdef, _Renderer(sdef, atlas, intr)


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
    gt_lines = ["# ground truth trajectory", f"# {what}", "# timestamp tx ty tz qx qy qz qw"]
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
        q = rot_to_quat(T[:3, :3])
        t = T[:3, 3]
        gt_lines.append(f"{ts} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
        if on_frame is not None:
            on_frame(i)
    if n_written == 0:
        raise ConfigError(f"write_tum {out}: no frames to write (expected ≥ 1 frame)")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", dep_lines), ("groundtruth.txt", gt_lines)):
        (out / name).write_text("\n".join(lines) + "\n", encoding="utf-8")
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

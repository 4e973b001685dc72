"""Layouts and camera paths of the synthetic scenes (geometry only; see :mod:`.sequences`).

A scene is a list of axis-aligned boxes in a z-up world: box 0 encloses everything and is
seen from inside, the others are seen from outside. Face ``f = 6·box + 2·axis + side``
(``side`` 0 = the ``lo`` face, 1 = the ``hi`` face); a face normal to ``axis`` is textured in
the in-plane coordinates ``(a, b)``: x-faces ``(y, z)``, y-faces ``(x, z)``, z-faces ``(x, y)``.

The camera path is a sum of low-frequency sinusoids per channel (x, y, z, yaw, pitch, roll)
with seed-dependent phases and frequencies, plus a slow yaw drift in the room so a long
sequence looks all around.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

SCENES = ("room", "planar", "far")
_INPLANE = ((1, 2), (0, 2), (0, 1))
_LIGHT = np.array([0.5, 0.3, 0.8]) / np.linalg.norm([0.5, 0.3, 0.8])
_HIDDEN_PPM = 8.0
"""Texel density of faces the camera path never sees (keeps the atlas small)."""


@dataclass(frozen=True)
class Box:
    """Axis-aligned box ``lo``–``hi`` (metres) with a texel density per face (6 values)."""

    lo: np.ndarray
    hi: np.ndarray
    ppm: tuple[float, ...]


@dataclass(frozen=True)
class PathSpec:
    """Camera path channels ``(x, y, z, yaw, pitch, roll)``: ``base + rate·t + Σ amp·sin(2π·freq·t + phase)``.

    Attributes:
        base, rate: ``(6,)`` metres / radians and per second.
        amp, freq, phase: ``(6, J)`` sinusoid amplitudes, frequencies (Hz) and phases (rad).
    """

    base: np.ndarray
    rate: np.ndarray
    amp: np.ndarray
    freq: np.ndarray
    phase: np.ndarray


@dataclass
class SceneDef:
    """Boxes, camera path and per-face texture metadata of one scene instance."""

    boxes: list[Box]
    path: PathSpec
    face_axis: np.ndarray = field(init=False)
    face_w: np.ndarray = field(init=False)
    face_h: np.ndarray = field(init=False)
    face_amin: np.ndarray = field(init=False)
    face_bmin: np.ndarray = field(init=False)
    face_ppm: np.ndarray = field(init=False)
    face_brightness: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        axis, w, h, amin, bmin, ppm, bright = [], [], [], [], [], [], []
        for b, box in enumerate(self.boxes):
            for k in range(3):
                a, c = _INPLANE[k]
                for side in (0, 1):
                    axis.append(k)
                    w.append(box.hi[a] - box.lo[a])
                    h.append(box.hi[c] - box.lo[c])
                    amin.append(box.lo[a])
                    bmin.append(box.lo[c])
                    ppm.append(box.ppm[2 * k + side])
                    # Outward normal of a box face; the enclosure is seen from inside (flip).
                    sign = (1.0 if side else -1.0) * (-1.0 if b == 0 else 1.0)
                    # Lambertian shading with a fixed directional light + ambient.
                    bright.append(0.72 + 0.28 * max(0.0, sign * _LIGHT[k]))
        self.face_axis = np.array(axis, np.uint8)
        self.face_w, self.face_h = np.array(w), np.array(h)
        self.face_amin, self.face_bmin = np.array(amin), np.array(bmin)
        self.face_ppm, self.face_brightness = np.array(ppm), np.array(bright)


def camera_pose(path: PathSpec, t: float) -> np.ndarray:
    """``T_wc`` (4×4 float64) at time ``t`` seconds: OpenCV camera axes, yaw about world z."""
    v = path.base + path.rate * t + np.sum(path.amp * np.sin(2 * np.pi * path.freq * t + path.phase), axis=1)
    x, y, z, yaw, pitch, roll = v
    fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.stack([right, down, fwd], axis=1) @ np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (x, y, z)
    return T


XY = tuple[float, float] | np.ndarray
"""A point of the floor plan ``(x, y)`` in metres: a pair or a ``(2,)`` array."""


def _path(rng: np.random.Generator, base: ArrayLike, rate: ArrayLike, amp: ArrayLike, freq: ArrayLike) -> PathSpec:
    """Jitter frequencies by ±15 % and draw phases uniformly (seed-dependent path): ``base``, ``rate`` ``(6,)``,
    ``amp``, ``freq`` ``(6, 2)`` as :class:`PathSpec` holds them."""
    amp, freq = np.asarray(amp, float), np.asarray(freq, float)
    freq = freq * rng.uniform(0.85, 1.15, freq.shape)
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    return PathSpec(np.asarray(base, float), np.asarray(rate, float), amp, freq, phase)


def _reach(path: PathSpec) -> np.ndarray:
    """Largest |offset| of x, y, z from ``base`` over all time (sum of amplitudes)."""
    return np.abs(path.amp[:3]).sum(axis=1)


def _place(rng: np.random.Generator, boxes: list[Box], n: int, region_lo: XY, region_hi: XY,
           size_lo: tuple[float, float, float], size_hi: tuple[float, float, float], keepout_lo: XY, keepout_hi: XY,
           ppm: float, z0: float = 0.0) -> None:
    """Append up to ``n`` floor-standing boxes inside ``region`` (xy), avoiding the camera
    keep-out rectangle and each other (rejection sampling). Corners in metres; sizes ``(x, y, z)``."""
    placed: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(400):
        if len(placed) == n:
            break
        size = rng.uniform(size_lo, size_hi)
        lo_xy = rng.uniform(region_lo, np.asarray(region_hi) - size[:2])
        hi_xy = lo_xy + size[:2]
        if np.all(lo_xy < keepout_hi) and np.all(hi_xy > keepout_lo):
            continue
        if any(np.all(lo_xy < h + 0.05) and np.all(hi_xy > lo - 0.05) for lo, h in placed):
            continue
        placed.append((lo_xy, hi_xy))
        lo = np.array([lo_xy[0], lo_xy[1], z0])
        hi = np.array([hi_xy[0], hi_xy[1], z0 + size[2]])
        boxes.append(Box(lo, hi, (ppm,) * 4 + (_HIDDEN_PPM, ppm)))  # bottom face never seen


def _panels(rng: np.random.Generator, boxes: list[Box], n: int, room_hi: np.ndarray, ppm: float) -> None:
    """Append ``n`` thin panels (3–12 cm deep) hung on the room walls at 0.6–2.3 m."""
    for _ in range(n):
        wall = rng.integers(0, 4)  # 0: x=0, 1: x=max, 2: y=0, 3: y=max
        k = 0 if wall < 2 else 1
        other = 1 - k
        depth = rng.uniform(0.03, 0.12)
        width = rng.uniform(0.4, 1.2)
        height = rng.uniform(0.3, 0.9)
        lo, hi = np.zeros(3), np.zeros(3)
        lo[k], hi[k] = (0.0, depth) if wall % 2 == 0 else (room_hi[k] - depth, room_hi[k])
        lo[other] = rng.uniform(0.1, room_hi[other] - width - 0.1)
        hi[other] = lo[other] + width
        lo[2] = rng.uniform(0.6, min(2.3, room_hi[2] - height - 0.1))
        hi[2] = lo[2] + height
        boxes.append(Box(lo, hi, (ppm,) * 6))


def _room(rng: np.random.Generator, source: bool) -> SceneDef:
    if source:
        dims = np.array([rng.uniform(6.5, 8.0), rng.uniform(5.0, 6.5), rng.uniform(2.9, 3.5)])
        cam_z, ppm, n_boxes, n_panels, txy = 1.05, 220.0, 7, 4, (0.5, 0.4)
        size_lo, size_hi = (0.3, 0.3, 0.3), (1.2, 1.2, 2.2)
    else:
        dims = np.array([4.0, 3.0, 2.6])
        cam_z, ppm, n_boxes, n_panels, txy = 1.45, 300.0, 4, 3, (0.3, 0.22)
        size_lo, size_hi = (0.3, 0.3, 0.3), (0.8, 0.8, 1.3)
    c = dims / 2
    path = _path(
        rng,
        base=[c[0], c[1], cam_z, rng.uniform(0, 2 * np.pi), -0.12, 0.0],
        rate=[0, 0, 0, 0.15 * rng.choice([-1.0, 1.0]), 0, 0],
        amp=[[txy[0], 0.08], [txy[1], 0.06], [0.05, 0.02], [0.5, 0.08], [0.08, 0.03], [0.03, 0.01]],
        freq=[[0.11, 0.37], [0.09, 0.31], [0.15, 0.5], [0.05, 0.25], [0.07, 0.3], [0.06, 0.4]],
    )
    reach = _reach(path)[:2] + 0.5
    boxes = [Box(np.zeros(3), dims, (ppm,) * 6)]
    _place(rng, boxes, n_boxes, (0.0, 0.0), dims[:2], size_lo, size_hi, c[:2] - reach, c[:2] + reach, ppm)
    _panels(rng, boxes, n_panels, dims, ppm)
    return SceneDef(boxes, path)


def _planar(rng: np.random.Generator, source: bool) -> SceneDef:
    if source:
        dist, ppm, half = rng.uniform(0.7, 1.0), 600.0, (2.0, 1.7)
        amp_xz, amp_y = (0.3, 0.18), 0.06
    else:
        dist, ppm, half = rng.uniform(1.3, 1.7), 350.0, (3.0, 2.5)
        amp_xz, amp_y = (0.35, 0.2), 0.1
    path = _path(
        rng,
        base=[0, 0, 0, np.pi / 2, 0, 0],
        rate=np.zeros(6),
        amp=[[amp_xz[0], 0.1], [amp_y, 0.03], [amp_xz[1], 0.05], [0.05, 0.015], [0.04, 0.01], [0.02, 0.01]],
        freq=[[0.12, 0.35], [0.08, 0.3], [0.1, 0.3], [0.1, 0.4], [0.09, 0.35], [0.07, 0.3]],
    )
    h = _HIDDEN_PPM
    # Only the far y-face (the wall) is ever in view.
    wall = Box(np.array([-half[0], -3.0, -half[1]]), np.array([half[0], dist, half[1]]), (h, h, h, ppm, h, h))
    return SceneDef([wall], path)


def _far(rng: np.random.Generator, source: bool) -> SceneDef:
    if source:
        lo, hi = np.array([-12.0, -2.0, 0.0]), np.array([12.0, 12.5, 7.0])
        cam_z, pitch, ppm, n, ry = 2.0, 0.0, 70.0, 6, (6.0, 10.0)
        size_lo, size_hi = (0.6, 0.6, 1.0), (2.2, 2.2, 5.0)
    else:
        lo, hi = np.array([-8.0, -2.0, 0.0]), np.array([8.0, 8.0, 5.0])
        cam_z, pitch, ppm, n, ry = 1.5, 0.08, 110.0, 5, (3.0, 6.5)
        size_lo, size_hi = (0.4, 0.4, 0.8), (1.5, 1.5, 3.5)
    path = _path(
        rng,
        base=[0, 0, cam_z, np.pi / 2, pitch, 0],
        rate=np.zeros(6),
        amp=[[0.4, 0.1], [0.15, 0.05], [0.08, 0.03], [0.08, 0.02], [0.04, 0.01], [0.02, 0.01]],
        freq=[[0.1, 0.33], [0.08, 0.3], [0.12, 0.4], [0.07, 0.3], [0.09, 0.35], [0.07, 0.3]],
    )
    encl = Box(lo, hi, (ppm, ppm, _HIDDEN_PPM, ppm, ppm, ppm))  # the wall behind the camera is never seen
    boxes = [encl]
    xr = 0.6 * hi[0]
    _place(rng, boxes, n, (-xr, ry[0]), (xr, ry[1]), size_lo, size_hi, (-100.0, -100.0), (-99.0, -99.0), ppm)
    return SceneDef(boxes, path)


def build_scene(scene: str, seed: int, domain: str) -> SceneDef:
    """The layout and camera path of ``scene`` for ``seed`` and ``domain`` (deterministic)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), SCENES.index(scene), int(domain == "source")]))
    return {"room": _room, "planar": _planar, "far": _far}[scene](rng, domain == "source")

"""Procedural textures and the mip-mapped texture atlas of the synthetic scenes.

Texture content is defined in metres on the face (positions and sizes of blobs, rectangles,
lines, checker patches and glyphs are drawn from the RNG in metric units) and rasterised at a
texel density ``ppm`` (texels per metre), so the same seed gives the same pattern at any
render resolution. Patterns are high-contrast and multi-scale (not a repeating checkerboard)
so that KLT / Shi–Tomasi find many distinct corners, and lightly anti-aliased.

All faces of a scene are packed into one atlas image with a mip pyramid beside it (levels
made by 2×2 box averaging, Williams 1983 "Pyramidal parametrics"), so a frame is textured by
two ``cv2.remap`` calls (trilinear filtering: bilinear within a level, linear across levels).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

N_LEVELS = 4
"""Mip levels 0..3 (level l has 2^-l of the texel density)."""
_ALIGN = 1 << (N_LEVELS - 1)
_PAD = 16
"""Texels of reflected border around each face (≥ 2 texels at the coarsest level)."""


@dataclass(frozen=True)
class TextureStyle:
    """Statistics of one domain's textures (all sizes in metres, densities per m²).

    Attributes:
        palette: ``(P, 3)`` RGB colours in 0..255 used for shapes and backgrounds.
        noise_cells: blob sizes of the background value noise, one per octave.
        noise_contrast: gain applied to the background noise around 0.5.
        rect_density: rectangles per m²; ``rect_size``: (min, max) side, log-uniform.
        line_density: line segments per m²; ``line_width``: (min, max) width.
        circle_density: discs/rings per m².
        checker_density: small checker patches per m².
        glyph_density: letters/digits per m².
        rotated: probability that a rectangle/checker patch is rotated.
    """

    palette: np.ndarray
    noise_cells: tuple[float, ...]
    noise_contrast: float
    rect_density: float
    rect_size: tuple[float, float]
    line_density: float
    line_width: tuple[float, float]
    circle_density: float
    checker_density: float
    glyph_density: float
    rotated: float


STYLES: dict[str, TextureStyle] = {
    # Target domain: warm, saturated, poster-like, many filled rectangles and glyphs.
    "target": TextureStyle(
        palette=np.array(
            [[200, 55, 40], [240, 195, 70], [25, 25, 30], [245, 240, 225], [35, 85, 160],
             [55, 135, 70], [150, 90, 45], [120, 30, 90], [230, 120, 40]], dtype=np.float32),
        noise_cells=(0.6, 0.2, 0.07),
        noise_contrast=1.8,
        rect_density=28.0,
        rect_size=(0.025, 0.35),
        line_density=10.0,
        line_width=(0.004, 0.02),
        circle_density=6.0,
        checker_density=0.8,
        glyph_density=8.0,
        rotated=0.35,
    ),
    # Source domain: cool, pastel, lower-contrast background, stripes and dots dominate.
    "source": TextureStyle(
        palette=np.array(
            [[165, 200, 230], [95, 130, 190], [205, 235, 220], [60, 75, 115], [230, 220, 250],
             [130, 200, 190], [20, 45, 70], [250, 250, 255]], dtype=np.float32),
        noise_cells=(1.0, 0.35, 0.12),
        noise_contrast=1.1,
        rect_density=10.0,
        rect_size=(0.04, 0.5),
        line_density=30.0,
        line_width=(0.006, 0.03),
        circle_density=18.0,
        checker_density=1.5,
        glyph_density=3.0,
        rotated=0.6,
    ),
}

_GLYPHS = "ABCDEFGHKLMNPRSTUVWXYZ0123456789#%&@"
_SHIFT = 4  # fixed-point bits for cv2 drawing (sub-texel positions)
_ONE = 1 << _SHIFT


def _fx(a: np.ndarray) -> np.ndarray:
    """Texel coordinates → cv2 fixed-point int32 coordinates."""
    return np.round(np.asarray(a) * _ONE).astype(np.int32)


def _noise(rng: np.random.Generator, w_m: float, h_m: float, W: int, H: int, cells: tuple[float, ...]) -> np.ndarray:
    """Multi-octave value noise in [0, 1], ``(H, W)`` float32, blob sizes ``cells`` metres."""
    acc = np.zeros((H, W), np.float32)
    total = 0.0
    for k, cell in enumerate(cells):
        gw, gh = int(np.ceil(w_m / cell)) + 2, int(np.ceil(h_m / cell)) + 2
        g = rng.random((gh, gw), dtype=np.float32)
        amp = 0.5**k
        acc += amp * cv2.resize(g, (W, H), interpolation=cv2.INTER_CUBIC)
        total += amp
    return acc / total


def _color(rng: np.random.Generator, style: TextureStyle, n: int) -> np.ndarray:
    """``n`` palette colours with ±20 jitter, ``(n, 3)`` float in 0..255."""
    c = style.palette[rng.integers(0, len(style.palette), n)]
    return np.clip(c + rng.uniform(-20, 20, (n, 3)), 0, 255)


def _rot_rect(cx: float, cy: float, w: float, h: float, ang: float) -> np.ndarray:
    """Corners ``(4, 2)`` of a ``w × h`` rectangle centred at ``(cx, cy)`` rotated by ``ang``."""
    c, s = np.cos(ang), np.sin(ang)
    loc = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) * 0.5
    return loc @ np.array([[c, s], [-s, c]]) + (cx, cy)


def face_texture(rng: np.random.Generator, w_m: float, h_m: float, ppm: float, style: TextureStyle,
                 feature_scale: float = 1.0) -> np.ndarray:
    """Procedural texture of a ``w_m × h_m`` metre face at ``ppm`` texels per metre.

    Random draws depend only on the metric size, so the pattern is the same at any ``ppm``.
    ``feature_scale`` multiplies every feature size (and divides densities by its square):
    faces seen from far away get proportionally bigger features, so the image statistics
    stay similar (and texture synthesis stays cheap for large faces).

    Returns:
        ``(H, W, 3)`` uint8 RGB, ``W = max(2, round(w_m·ppm))``, same for ``H``.
    """
    W, H = max(2, int(round(w_m * ppm))), max(2, int(round(h_m * ppm)))
    s = ppm  # metres → texels
    fs = float(feature_scale)
    n = _noise(rng, w_m, h_m, W, H, tuple(c * fs for c in style.noise_cells))
    n = np.clip((n - 0.5) * style.noise_contrast + 0.5, 0.0, 1.0)[..., None]
    c0, c1 = _color(rng, style, 2)
    img = np.ascontiguousarray((c0 * (1 - n) + c1 * n).astype(np.uint8))

    for draw in (_draw_rects, _draw_checkers, _draw_discs, _draw_lines, _draw_glyphs):  # in this order (rng)
        draw(img, rng, style, w_m, h_m, s, fs)
    return cv2.GaussianBlur(img, (0, 0), 0.6)


def _draw_rects(img: np.ndarray, rng: np.random.Generator, style: TextureStyle, w_m: float, h_m: float, s: float,
                fs: float) -> None:
    """Rectangles (filled or outlined, axis-aligned or rotated), log-uniform sizes.
    Drawn into ``img`` (``s`` texels per metre, feature scale ``fs``)."""
    area = w_m * h_m / (fs * fs)
    nr = int(rng.poisson(style.rect_density * area))
    lo, hi = np.log(style.rect_size[0] * fs), np.log(style.rect_size[1] * fs)
    pos = rng.random((nr, 2)) * (w_m, h_m)
    size = np.exp(rng.uniform(lo, hi, (nr, 2)))
    ang = np.where(rng.random(nr) < style.rotated, rng.uniform(0, np.pi, nr), 0.0)
    filled = rng.random(nr) < 0.75
    thick = rng.uniform(0.005, 0.02, nr) * fs
    cols = _color(rng, style, nr)
    for k in range(nr):
        pts = _fx(_rot_rect(pos[k, 0] * s, pos[k, 1] * s, size[k, 0] * s, size[k, 1] * s, ang[k]))
        col = tuple(float(v) for v in cols[k])
        if filled[k]:
            cv2.fillConvexPoly(img, pts, col, cv2.LINE_AA, _SHIFT)
        else:
            cv2.polylines(img, [pts], True, col, max(1, int(round(thick[k] * s))), cv2.LINE_AA, _SHIFT)


def _draw_checkers(img: np.ndarray, rng: np.random.Generator, style: TextureStyle, w_m: float, h_m: float, s: float,
                   fs: float) -> None:
    """Checker patches: small, irregular count of cells, random rotation (not a global grid).
    Drawn into ``img`` (``s`` texels per metre, feature scale ``fs``)."""
    area = w_m * h_m / (fs * fs)
    nc = int(rng.poisson(style.checker_density * area))
    for _ in range(nc):
        cx, cy = rng.random(2) * (w_m, h_m)
        nx, ny = rng.integers(2, 6, 2)
        cell = rng.uniform(0.02, 0.06) * fs
        a = rng.uniform(0, np.pi) if rng.random() < style.rotated else 0.0
        ca, cb = _color(rng, style, 2)
        u = np.array([np.cos(a), np.sin(a)]) * cell
        v = np.array([-np.sin(a), np.cos(a)]) * cell
        org = np.array([cx, cy]) - 0.5 * (nx * u + ny * v)
        for i in range(nx):
            for j in range(ny):
                p = org + i * u + j * v
                quad = np.array([p, p + u, p + u + v, p + v]) * s
                col = ca if (i + j) % 2 == 0 else cb
                cv2.fillConvexPoly(img, _fx(quad), tuple(float(x) for x in col), cv2.LINE_AA, _SHIFT)


def _draw_discs(img: np.ndarray, rng: np.random.Generator, style: TextureStyle, w_m: float, h_m: float, s: float,
                fs: float) -> None:
    """Discs and rings.
    Drawn into ``img`` (``s`` texels per metre, feature scale ``fs``)."""
    area = w_m * h_m / (fs * fs)
    ncir = int(rng.poisson(style.circle_density * area))
    cpos = rng.random((ncir, 2)) * (w_m, h_m)
    rad = np.exp(rng.uniform(np.log(0.01), np.log(0.12), ncir)) * fs
    ring = rng.random(ncir) < 0.4
    ccols = _color(rng, style, ncir)
    for k in range(ncir):
        th = max(1, int(round(0.2 * rad[k] * s))) if ring[k] else -1
        cv2.circle(img, tuple(_fx(cpos[k] * s)), max(1, int(round(rad[k] * s * _ONE))),
                   tuple(float(x) for x in ccols[k]), th, cv2.LINE_AA, _SHIFT)


def _draw_lines(img: np.ndarray, rng: np.random.Generator, style: TextureStyle, w_m: float, h_m: float, s: float,
                fs: float) -> None:
    """Line segments of several widths and colours.
    Drawn into ``img`` (``s`` texels per metre, feature scale ``fs``)."""
    area = w_m * h_m / (fs * fs)
    nl = int(rng.poisson(style.line_density * area))
    p0 = rng.random((nl, 2)) * (w_m, h_m)
    ln = rng.uniform(0.05, 0.8, nl) * fs
    la = rng.uniform(0, np.pi, nl)
    p1 = p0 + np.stack([np.cos(la), np.sin(la)], 1) * ln[:, None]
    lw = rng.uniform(*style.line_width, nl) * fs
    lcols = _color(rng, style, nl)
    for k in range(nl):
        cv2.line(img, tuple(_fx(p0[k] * s)), tuple(_fx(p1[k] * s)), tuple(float(x) for x in lcols[k]),
                 max(1, int(round(lw[k] * s))), cv2.LINE_AA, _SHIFT)


def _draw_glyphs(img: np.ndarray, rng: np.random.Generator, style: TextureStyle, w_m: float, h_m: float, s: float,
                 fs: float) -> None:
    """Glyphs (letters/digits): many distinct corners at small scale.
    Drawn into ``img`` (``s`` texels per metre, feature scale ``fs``)."""
    area = w_m * h_m / (fs * fs)
    ng = int(rng.poisson(style.glyph_density * area))
    gpos = rng.random((ng, 2)) * (w_m, h_m)
    gh = rng.uniform(0.03, 0.15, ng) * fs
    gch = rng.integers(0, len(_GLYPHS), ng)
    gcols = _color(rng, style, ng)
    for k in range(ng):
        scale = gh[k] * s / 22.0  # Hershey simplex capital height ≈ 22 px at scale 1
        if scale < 0.25:
            continue
        org = (int(round(gpos[k, 0] * s)), int(round(gpos[k, 1] * s)))
        cv2.putText(img, _GLYPHS[gch[k]], org, cv2.FONT_HERSHEY_SIMPLEX, scale,
                    tuple(float(x) for x in gcols[k]), max(1, int(round(scale * 2))), cv2.LINE_AA)


@dataclass
class Atlas:
    """All face textures of a scene packed in one image with its mip pyramid beside level 0.

    Level 0 (``W0 × H0``) sits at the origin; level ``l ≥ 1`` (``W0/2^l × H0/2^l``) at
    ``(W0, H0·(1 − 2^(1−l)))``. A world point on face ``f`` with in-plane coordinates
    ``(a, b)`` metres maps to level-0 texel ``(a·scale[f] + ox[f], b·scale[f] + oy[f])``.

    Attributes:
        image: ``(H0, 1.5·W0, 4)`` uint8 RGBA (alpha unused; 4 channels remap ~3× faster).
        w0, h0: size of level 0.
        scale: ``(F,)`` float32 texels per metre of each face.
        ox, oy: ``(F,)`` float32 level-0 offsets.
        level_x, level_y: ``(N_LEVELS + 1,)`` float32 origin of each level (last entry repeats).
    """

    image: np.ndarray
    w0: int
    h0: int
    scale: np.ndarray
    ox: np.ndarray
    oy: np.ndarray
    level_x: np.ndarray
    level_y: np.ndarray


def build_atlas(textures: list[np.ndarray], a_min: np.ndarray, b_min: np.ndarray, scale: np.ndarray,
                brightness: np.ndarray) -> Atlas:
    """Pack face textures (each shaded by its brightness factor) into an :class:`Atlas`.

    Args:
        textures: per face ``(h_f, w_f, 3)`` uint8, texel (0, 0) centred at ``(a_min, b_min)``
            + half a texel.
        a_min, b_min: ``(F,)`` metric origin of each face's in-plane coordinates.
        scale: ``(F,)`` texels per metre.
        brightness: ``(F,)`` shading factor (Lambertian, fixed light) baked into the texels.
    """
    F = len(textures)
    sizes = []
    for t in textures:
        h, w = t.shape[:2]
        sizes.append((-(-(h + 2 * _PAD) // _ALIGN) * _ALIGN, -(-(w + 2 * _PAD) // _ALIGN) * _ALIGN))
    total = sum(h * w for h, w in sizes)
    W0 = max(max(w for _, w in sizes), int(np.sqrt(total) * 1.15))
    W0 = -(-W0 // _ALIGN) * _ALIGN
    # Shelf packing, tallest first.
    order = sorted(range(F), key=lambda i: -sizes[i][0])
    pos = [(0, 0)] * F
    x = y = shelf = 0
    for i in order:
        h, w = sizes[i]
        if x + w > W0:
            x, y, shelf = 0, y + shelf, 0
        pos[i] = (y, x)
        x += w
        shelf = max(shelf, h)
    H0 = -(-(y + shelf) // _ALIGN) * _ALIGN
    base = np.zeros((H0, W0, 3), np.uint8)
    for i, t in enumerate(textures):
        y0, x0 = pos[i]
        h, w = t.shape[:2]
        shaded = cv2.convertScaleAbs(t, alpha=float(brightness[i]))
        padded = cv2.copyMakeBorder(shaded, _PAD, sizes[i][0] - h - _PAD, _PAD, sizes[i][1] - w - _PAD,
                                    cv2.BORDER_REFLECT_101)
        base[y0:y0 + sizes[i][0], x0:x0 + sizes[i][1]] = padded
    base = cv2.cvtColor(base, cv2.COLOR_RGB2RGBA)
    image = np.zeros((H0, W0 + W0 // 2, 4), np.uint8)
    image[:, :W0] = base
    lx, ly = [0.0], [0.0]
    lvl, yy = base, 0
    for _ in range(1, N_LEVELS):
        lvl = cv2.resize(lvl, (lvl.shape[1] // 2, lvl.shape[0] // 2), interpolation=cv2.INTER_AREA)
        image[yy:yy + lvl.shape[0], W0:W0 + lvl.shape[1]] = lvl
        lx.append(float(W0))
        ly.append(float(yy))
        yy += lvl.shape[0]
    lx.append(lx[-1])
    ly.append(ly[-1])
    sc = np.asarray(scale, np.float64)
    ox = np.array([pos[i][1] + _PAD for i in range(F)]) - np.asarray(a_min) * sc - 0.5
    oy = np.array([pos[i][0] + _PAD for i in range(F)]) - np.asarray(b_min) * sc - 0.5
    return Atlas(image, W0, H0, sc.astype(np.float32), ox.astype(np.float32), oy.astype(np.float32),
                 np.array(lx, np.float32), np.array(ly, np.float32))

"""The sign of fy, decided from the data: GT depth + GT poses must be photometrically consistent.

ICL-NUIM's pose convention leaves the sign of fy open (DESIGN §3); a TUM-layout folder can ask
for the same decision with ``fy_sign: auto``. Both loaders call :func:`apply_fy_sign`.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import cv2
import numpy as np

from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import backproject, project, se3_inv, transform
from mutualslam_cli.pixels import in_image

log = logging.getLogger(__name__)


def warp_error(gray_i: np.ndarray, depth_i: np.ndarray, gray_j: np.ndarray, T_wi: np.ndarray, T_wj: np.ndarray,
               K: np.ndarray, step: int = 4) -> tuple[float, int]:
    """Mean grey L1 error of frame ``j`` warped into frame ``i`` with depth of ``i``.

    Pixel ``p`` of ``i`` with depth ``d`` maps to ``π(K, T_wj⁻¹ T_wi d K⁻¹ p̃)`` in ``j``;
    ``j`` is sampled bilinearly there.

    Args:
        gray_i, gray_j: ``(H, W)`` uint8 grey images.
        depth_i: ``(H, W)`` float32 metres, 0 = invalid.
        T_wi, T_wj: ``(4, 4)`` camera-to-world poses.
        K: ``(3, 3)`` camera matrix (fy may be negative).
        step: pixel subsampling of frame ``i``.

    Returns:
        ``(mean |I_i − I_j(w(p))|` in grey levels (nan if no pixel lands inside), pixel count)``.
    """
    H, W = depth_i.shape
    v, u = np.mgrid[0:H:step, 0:W:step]
    u, v = u.ravel(), v.ravel()
    d = depth_i[v, u].astype(np.float64)
    ok = d > 0
    u, v, d = u[ok], v[ok], d[ok]
    if len(d) == 0:
        return float("nan"), 0
    pts_j = transform(se3_inv(T_wj) @ T_wi, backproject(np.stack([u, v], 1).astype(np.float64), d, K))
    uv, z = project(pts_j, K)
    inside = (z > 1e-6) & in_image(uv, W, H)
    n = int(inside.sum())
    if n == 0:
        return float("nan"), 0
    mx = uv[inside, 0].astype(np.float32).reshape(1, -1)
    my = uv[inside, 1].astype(np.float32).reshape(1, -1)
    warped = cv2.remap(gray_j.astype(np.float32), mx, my, cv2.INTER_LINEAR).ravel()
    ref = gray_i[v[inside], u[inside]].astype(np.float32)
    return float(np.mean(np.abs(ref - warped))), n


def decide_fy_sign(seq: Sequence, n_pairs: int = 3, gap: int = 5, step: int = 4) -> tuple[int, dict[str, float]] | None:
    """Choose the sign of fy that makes GT depth + GT poses photometrically consistent.

    Takes up to ``n_pairs`` frame pairs ``(i, i+gap)`` spread over the sequence (both with
    GT pose, ``i`` with depth), warps ``i+gap`` into ``i`` with ``fy = ±|fy|`` and keeps
    the sign with the lower mean grey L1 error (DESIGN §3).

    Returns:
        ``(sign, {"+": err_plus, "-": err_minus})`` or ``None`` when no usable pair exists.
    """
    cand = [k for k, f in enumerate(seq.frames) if f.pose is not None and f.depth_path is not None]
    if len(cand) < 2:
        return None
    pos = {k: n for n, k in enumerate(cand)}
    gap = max(1, min(gap, len(cand) - 1))
    starts = np.unique(np.linspace(0, len(cand) - 1 - gap, n_pairs).round().astype(int))
    K0 = seq.intrinsics.K()
    errs: dict[str, list[float]] = {"+": [], "-": []}
    for s in starts:
        i, j = cand[s], cand[s + gap]
        if pos[i] + gap != pos[j]:
            continue
        gi, gj, di = seq.load_gray(i), seq.load_gray(j), seq.load_depth(i)
        assert di is not None  # cand: frames with a depth file
        for key, sgn in (("+", 1.0), ("-", -1.0)):
            K = K0.copy()
            K[1, 1] = sgn * abs(K0[1, 1])
            e, _ = warp_error(gi, di, gj, seq.frames[i].pose, seq.frames[j].pose, K, step)
            errs[key].append(e)
    means = {k: float(np.nanmean(v)) if np.any(np.isfinite(v)) else float("nan") for k, v in errs.items()}
    if not all(np.isfinite(list(means.values()))):
        return None
    return (1 if means["+"] < means["-"] else -1), means


def apply_fy_sign(seq: Sequence, mode: str | float = "auto", fallback: int = -1) -> Sequence:
    """Set ``seq.intrinsics.fy`` sign in place: ``auto`` decides from the data, else ±1.

    Records ``fy_sign``, ``fy_sign_errors`` and ``fy_sign_source`` in ``seq.meta``.
    """
    fy_abs = abs(seq.intrinsics.fy)
    if str(mode).lower() == "auto":
        res = decide_fy_sign(seq)
        if res is None:
            sign, errors = fallback, None
            source = "fallback: spec sign or -1 (no frame pair with GT poses and depth)"
            log.warning("%s: cannot decide the fy sign from the data; using fy = %+g", seq.name, sign * fy_abs)
        else:
            sign, errors = res
            source = "data"
            log.info("%s: fy sign from data: fy = %+g (grey L1 error +: %.2f, -: %.2f)",
                     seq.name, sign * fy_abs, errors["+"], errors["-"])
    else:
        try:
            sign = 1 if float(mode) > 0 else -1
        except ValueError:
            raise DatasetError(f"{seq.root}: fy_sign must be 'auto', 1 or -1, got {mode!r}") from None
        errors, source = None, "spec"
    seq.intrinsics = replace(seq.intrinsics, fy=sign * fy_abs)
    seq.meta.update({"fy_sign": sign, "fy_sign_errors": errors, "fy_sign_source": source})
    return seq

"""ICL-NUIM (Handa et al., ICRA 2014) → :class:`Sequence`, and the data-driven fy sign.

Two variants:

- ``icl`` (``*_frei_png``): ``associations.txt`` lines ``idx depth/idx.png idx rgb/idx.png``,
  integer frame numbers as timestamps, GT in ``*.gt.freiburg`` (timestamp = frame number,
  matched exactly; the first frame(s) have no GT → pose ``None``), depth PNG /5000.
- ``icl_loop`` (native POV-Ray output): ``scene_00_NNNN.png`` colour, ``scene_00_NNNN.depth``
  text with 640×480 numbers = Euclidean distance from the camera centre along each pixel
  ray (not z), and ``scene_00_NNNN.txt`` POV-Ray camera (``cam_pos``, ``cam_dir``,
  ``cam_up``, ``cam_right`` …). Depth is converted to z-depth by
  ``z = r / sqrt(((u−cx)/fx)² + ((v−cy)/fy)² + 1)`` (ICL-NUIM's own parsing code,
  ``compute3Dpositions.m``). The unit of the native files is taken as metres (as the
  supereight ICL-NUIM reader does); ``extra.depth_unit_m`` overrides it.

Intrinsics fx 481.20, |fy| 480.0, cx 319.5, cy 239.5. The sign of fy depends on the pose
convention of the GT, so it is decided from the data (:func:`decide_fy_sign`).
"""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.datasets.tum import attach_gt, frames_from_associations, image_size, load_gt, make_frames
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import backproject, project, se3_inv, transform
from mutualslam_cli.types import Intrinsics, SequenceSpec, Trajectory

log = logging.getLogger(__name__)

ICL_FX, ICL_FY_ABS, ICL_CX, ICL_CY = 481.20, 480.0, 319.5, 239.5
NATIVE_RE = re.compile(r"^scene_(\d+)_(\d+)\.png$")


# ----------------------------------------------------------------------------- fy sign
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
    inside = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
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
    errs = {"+": [], "-": []}
    for s in starts:
        i, j = cand[s], cand[s + gap]
        if pos[i] + gap != pos[j]:
            continue
        gi, gj, di = seq.load_gray(i), seq.load_gray(j), seq.load_depth(i)
        for key, sgn in (("+", 1.0), ("-", -1.0)):
            K = K0.copy()
            K[1, 1] = sgn * abs(K0[1, 1])
            e, _ = warp_error(gi, di, gj, seq.frames[i].pose, seq.frames[j].pose, K, step)
            errs[key].append(e)
    means = {k: float(np.nanmean(v)) if np.any(np.isfinite(v)) else float("nan") for k, v in errs.items()}
    if not all(np.isfinite(list(means.values()))):
        return None
    return (1 if means["+"] < means["-"] else -1), means


def apply_fy_sign(seq: Sequence, mode: Any = "auto", fallback: int = -1) -> Sequence:
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
    seq.meta.update(fy_sign=sign, fy_sign_errors=errors, fy_sign_source=source)
    return seq


def _spec_sign(spec: SequenceSpec) -> int:
    """Sign of fy given in the spec (fallback when the data cannot decide), else −1."""
    return 1 if spec.intrinsics is not None and spec.intrinsics.fy > 0 else -1


def _icl_intrinsics(spec: SequenceSpec, size: tuple[int, int]) -> Intrinsics:
    if spec.intrinsics is not None:
        return replace(spec.intrinsics, width=size[0], height=size[1])
    return Intrinsics(ICL_FX, -ICL_FY_ABS, ICL_CX, ICL_CY, size[0], size[1])


def _gt_file_icl(spec: SequenceSpec) -> SequenceSpec:
    """Fill ``gt_file`` with the folder's single ``*.gt.freiburg`` when the spec names none."""
    if spec.gt_file:
        return spec
    found = sorted(Path(spec.root).glob("*.gt.freiburg"))
    if len(found) > 1:
        raise DatasetError(f"{spec.root}: several *.gt.freiburg files ({', '.join(p.name for p in found)}); "
                           "name one as 'gt' in datasets.yaml")
    return replace(spec, gt_file=found[0].name) if found else spec


# ----------------------------------------------------------------------------- *_frei_png
def load_icl(spec: SequenceSpec) -> Sequence:
    """Load an ICL-NUIM ``*_frei_png`` folder (see module docstring).

    ``extra.fy_sign``: ``auto`` (default), ``1`` or ``-1``.
    """
    root = Path(spec.root)
    if not root.is_dir():
        raise DatasetError(f"{root}: sequence folder not found (registry entry '{spec.name}')")
    if not (root / "associations.txt").is_file():
        raise DatasetError(f"{root / 'associations.txt'}: not found (expected lines 'idx depth/idx.png idx rgb/idx.png')")
    times, rgb, depth, assoc = frames_from_associations(root, depth_first=True)
    if len(rgb) == 0:
        raise DatasetError(f"{root / 'associations.txt'}: empty sequence: no frames listed")
    spec = _gt_file_icl(spec)
    gt, gt_name = load_gt(spec, default=None)
    poses = attach_gt(times, gt, gt_name, root, max_gap=0.0)  # frame numbers: exact match only
    intr = _icl_intrinsics(spec, image_size(rgb[0]))
    meta: dict[str, Any] = {"format": "icl", "association": assoc, "gt_file": gt_name, "intrinsics_source":
                            "spec" if spec.intrinsics is not None else "ICL-NUIM default"}
    seq = Sequence(spec.name, root, intr, float(spec.depth_scale), make_frames(times, rgb, list(depth), poses), gt, meta)
    return apply_fy_sign(seq, spec.extra.get("fy_sign", "auto"), fallback=_spec_sign(spec))


# ----------------------------------------------------------------------------- native *_loop
class IclLoopSequence(Sequence):
    """A native ICL-NUIM sequence: ``load_depth`` parses ``.depth`` text and returns z-depth."""

    def load_depth(self, i: int) -> np.ndarray | None:
        """Frame ``i`` as ``(H, W)`` float32 z-depth in metres (0 = invalid), or ``None``."""
        path = self.frames[i].depth_path
        if path is None:
            return None
        W, H = self.intrinsics.width, self.intrinsics.height
        try:
            r = np.array(path.read_text().split(), dtype=np.float64)
        except ValueError:
            raise DatasetError(f"{path}: expected {W * H} whitespace-separated numbers (ray lengths)") from None
        if r.size != W * H:
            raise DatasetError(f"{path}: expected {W}×{H} = {W * H} numbers (ray lengths), got {r.size}")
        r = r.reshape(H, W) * float(self.meta.get("depth_unit_m", 1.0))
        return ray_to_z(r, self.intrinsics).astype(np.float32)


def ray_to_z(ray: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Euclidean ray length ``(H, W)`` → z-depth ``(H, W)`` (compute3Dpositions.m, ICL-NUIM)."""
    H, W = ray.shape
    v, u = np.mgrid[0:H, 0:W]
    x = (u - intr.cx) / intr.fx
    y = (v - intr.cy) / intr.fy
    z = ray / np.sqrt(x * x + y * y + 1.0)
    return np.where(np.isfinite(z) & (z > 0), z, 0.0)


def read_povray_camera(path: Path) -> np.ndarray:
    """POV-Ray camera file (``cam_pos = [x, y, z]';`` …) → ``(4, 4)`` ``T_wc``.

    Camera axes are ``right``, ``up``, ``dir`` normalised (``right = up × dir``, a proper
    rotation); with image rows growing downwards this pairs with a negative fy. Units are
    the file's (ICL-NUIM living room: metres).
    """
    vals: dict[str, np.ndarray] = {}
    for k, raw in enumerate(path.read_text().splitlines(), start=1):
        if "=" not in raw:
            continue
        key, val = raw.split("=", 1)
        nums = re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", val)
        vals[key.strip()] = np.array([float(x) for x in nums])
    try:
        pos, d, up = vals["cam_pos"], vals["cam_dir"], vals["cam_up"]
        if len(pos) != 3 or len(d) != 3 or len(up) != 3:
            raise KeyError
    except KeyError:
        raise DatasetError(f"{path}: expected POV-Ray camera lines 'cam_pos = [x, y, z]'', 'cam_dir = …', 'cam_up = …'") from None
    z = d / np.linalg.norm(d)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = pos
    return T


def load_icl_loop(spec: SequenceSpec) -> Sequence:
    """Load a native ICL-NUIM folder (``scene_00_NNNN.png`` / ``.depth`` / ``.txt``).

    GT: ``spec.gt_file`` or a single ``*.gt.freiburg`` (timestamps = frame number NNNN,
    matched exactly — which frame number the first freiburg line refers to is not
    documented, so check the ``fy_sign_errors``), else the per-frame POV-Ray camera files.
    """
    root = Path(spec.root)
    if not root.is_dir():
        raise DatasetError(f"{root}: sequence folder not found (registry entry '{spec.name}')")
    items = sorted((int(m.group(2)), p) for p in root.iterdir() if (m := NATIVE_RE.match(p.name)))
    if not items:
        raise DatasetError(f"{root}: empty sequence: no scene_00_NNNN.png files")
    times = np.array([n for n, _ in items], dtype=np.float64)
    rgb = [p for _, p in items]
    depth = []
    for p in rgb:
        dp = p.with_suffix(".depth")
        if not dp.is_file():
            raise DatasetError(f"{dp}: not found (native ICL-NUIM: one .depth text file per scene_00_NNNN.png)")
        depth.append(dp)
    spec = _gt_file_icl(spec)
    gt, gt_name = load_gt(spec, default=None)
    unit = float(spec.extra.get("depth_unit_m", 1.0))
    if gt is not None:
        poses = attach_gt(times, gt, gt_name, root, max_gap=0.0)
    elif all(p.with_suffix(".txt").is_file() for p in rgb):
        poses = [read_povray_camera(p.with_suffix(".txt")) for p in rgb]
        for T in poses:
            T[:3, 3] *= unit
        gt_name = "scene_*.txt (POV-Ray cameras)"
        gt = Trajectory(times, np.stack(poses))
    else:
        poses = [None] * len(rgb)
    intr = _icl_intrinsics(spec, image_size(rgb[0]))
    meta: dict[str, Any] = {"format": "icl_loop", "gt_file": gt_name, "depth_unit_m": unit,
                            "depth": "ray length → z-depth", "association": {"source": "file names", "pairs": len(rgb)}}
    seq = IclLoopSequence(spec.name, root, intr, 1.0, make_frames(times, rgb, depth, poses), gt, meta)
    return apply_fy_sign(seq, spec.extra.get("fy_sign", "auto"), fallback=_spec_sign(spec))

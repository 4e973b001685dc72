"""ICL-NUIM (Handa et al., ICRA 2014) → :class:`Sequence`.

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
convention of the GT, so it is decided from the data
(:func:`~mutualslam_cli.datasets.fy_sign.decide_fy_sign`).
"""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from mutualslam_cli.datasets.fy_sign import apply_fy_sign
from mutualslam_cli.datasets.layout import attach_gt, frames_from_associations, image_size, load_gt, make_frames
from mutualslam_cli.datasets.sequence import Sequence, SequenceMeta
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics, SequenceSpec, Trajectory

log = logging.getLogger(__name__)

ICL_FX, ICL_FY_ABS, ICL_CX, ICL_CY = 481.20, 480.0, 319.5, 239.5
NATIVE_RE = re.compile(r"^scene_(\d+)_(\d+)\.png$")


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
        raise DatasetError(f"{root / 'associations.txt'}: not found "
                           "(expected lines 'idx depth/idx.png idx rgb/idx.png')")
    times, rgb, depth, assoc = frames_from_associations(root, depth_first=True)
    if len(rgb) == 0:
        raise DatasetError(f"{root / 'associations.txt'}: empty sequence: no frames listed")
    spec = _gt_file_icl(spec)
    gt, gt_name = load_gt(spec, default=None)
    poses = attach_gt(times, gt, gt_name, root, max_gap=0.0)  # frame numbers: exact match only
    intr = _icl_intrinsics(spec, image_size(rgb[0]))
    meta: SequenceMeta = {"format": "icl", "association": assoc, "gt_file": gt_name, "intrinsics_source":
                          "spec" if spec.intrinsics is not None else "ICL-NUIM default"}
    frames = make_frames(times, rgb, list(depth), poses)
    seq = Sequence(spec.name, root, intr, float(spec.depth_scale), frames, gt, meta)
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
    for raw in path.read_text().splitlines():
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
        raise DatasetError(f"{path}: expected POV-Ray camera lines "
                           "'cam_pos = [x, y, z]', 'cam_dir = …', 'cam_up = …'") from None
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
    poses: list[np.ndarray | None]
    if gt is not None:
        poses = attach_gt(times, gt, gt_name, root, max_gap=0.0)
    elif all(p.with_suffix(".txt").is_file() for p in rgb):
        cams = [read_povray_camera(p.with_suffix(".txt")) for p in rgb]
        for T in cams:
            T[:3, 3] *= unit
        gt_name = "scene_*.txt (POV-Ray cameras)"
        gt = Trajectory(times, np.stack(cams))
        poses = list(cams)  # the same arrays
    else:
        poses = [None] * len(rgb)
    intr = _icl_intrinsics(spec, image_size(rgb[0]))
    meta: SequenceMeta = {"format": "icl_loop", "gt_file": gt_name, "depth_unit_m": unit,
                          "depth": "ray length → z-depth", "association": {"source": "file names", "pairs": len(rgb)}}
    seq = IclLoopSequence(spec.name, root, intr, 1.0, make_frames(times, rgb, depth, poses), gt, meta)
    return apply_fy_sign(seq, spec.extra.get("fy_sign", "auto"), fallback=_spec_sign(spec))

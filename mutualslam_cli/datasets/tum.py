"""TUM RGB-D layout folders → :class:`Sequence` (formats ``tum``, ``lab``, ``synthetic``).

A folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp path``), an optional trajectory
(``groundtruth.txt``, camera-to-world) and 16-bit depth PNGs (``depth_scale`` units = 1 m).
RGB and depth are associated greedily within 0.02 s (TUM ``associate.py``); GT poses are
interpolated at the RGB times (:func:`poses_at`).

Intrinsics, first match wins: the spec's explicit values; ``intrinsics.txt`` in the folder
(one line ``fx fy cx cy width height``, written by ``mslam synth`` and usable beside lab
data); ``camera-intrinsics.txt`` (a 3×3 K, as 7-Scenes ships); the TUM family named in the
folder or sequence name (``freiburg1``/``fr1`` …, Sturm et al. 2012 calibration page).
"""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT, associate, read_list_file
from mutualslam_cli.datasets.fy_sign import apply_fy_sign
from mutualslam_cli.datasets.layout import (
    attach_gt,
    check_files,
    frames_from_associations,
    image_size,
    load_gt,
    make_frames,
)
from mutualslam_cli.datasets.sequence import Sequence, SequenceMeta
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.types import Intrinsics, SequenceSpec

log = logging.getLogger(__name__)

# TUM RGB-D calibration page: ROS-default-free values per camera family, as the page rounds
# them (cross-checked against the 6-decimal values other TUM loaders carry, e.g. fr2
# 520.908620 521.007327 325.141442 249.701764 / 0.231222 −0.784899 −0.003257 −0.000105
# 0.917205). fr1/fr2 images are not undistorted in the files (OpenCV k1 k2 p1 p2 k3 given);
# fr3 images are.
FAMILY_INTRINSICS: dict[str, tuple[float, float, float, float, tuple[float, ...] | None]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": (535.4, 539.2, 320.1, 247.6, None),
}
_FAMILY_RE = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def tum_family(*names: str) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` from the first name containing ``freiburgN`` or ``frN``."""
    for n in names:
        m = _FAMILY_RE.search(n or "")
        if m:
            return f"fr{m.group(1)}"
    return None


def read_intrinsics_txt(path: Path) -> Intrinsics:
    """Parse ``intrinsics.txt``: one line ``fx fy cx cy width height [k1 k2 p1 p2 [k3]]`` (``#`` comments;
    the OpenCV distortion is optional, as a converted recording writes it)."""
    for k, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        f = s.split()
        try:
            if len(f) not in (6, 10, 11, 14):
                raise ValueError
            fx, fy, cx, cy = (float(x) for x in f[:4])
            w, h = int(f[4]), int(f[5])
            dist = tuple(float(x) for x in f[6:]) or None
        except ValueError:
            raise DatasetError(f"{path}:{k}: expected 'fx fy cx cy width height [k1 k2 p1 p2 [k3]]', "
                               f"got {s!r}") from None
        return Intrinsics(fx, fy, cx, cy, w, h, dist)
    raise DatasetError(f"{path}: empty; expected one line 'fx fy cx cy width height'")


def read_k_matrix_txt(path: Path, width: int, height: int) -> Intrinsics:
    """Parse a 3×3 camera matrix text file (7-Scenes ``camera-intrinsics.txt``)."""
    try:
        K = np.loadtxt(path, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError
    except ValueError:
        raise DatasetError(f"{path}: expected a 3×3 camera matrix (3 lines of 3 numbers)") from None
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)


def resolve_intrinsics(spec: SequenceSpec, size: tuple[int, int]) -> tuple[Intrinsics, str]:
    """Intrinsics at the stored image size and where they came from (see module docstring)."""
    w, h = size
    root = Path(spec.root)
    if spec.intrinsics is not None:
        K = spec.intrinsics
        if K.width and K.height and (K.width, K.height) != (w, h):
            raise DatasetError(
                f"{root}: intrinsics in the registry entry '{spec.name}' are for {K.width}×{K.height} "
                f"but the images are {w}×{h}"
            )
        return replace(K, width=w, height=h), "spec"
    if (root / "intrinsics.txt").is_file():
        K = read_intrinsics_txt(root / "intrinsics.txt")
        if (K.width, K.height) != (w, h):
            raise DatasetError(f"{root / 'intrinsics.txt'}: size {K.width}×{K.height} but images are {w}×{h}")
        return K, "intrinsics.txt"
    if (root / "camera-intrinsics.txt").is_file():
        return read_k_matrix_txt(root / "camera-intrinsics.txt", w, h), "camera-intrinsics.txt"
    fam = tum_family(root.name, spec.name)
    if fam is not None:
        fx, fy, cx, cy, dist = FAMILY_INTRINSICS[fam]
        return Intrinsics(fx, fy, cx, cy, w, h, dist), f"family {fam}"
    raise DatasetError(
        f"{root}: no intrinsics: give 'intrinsics: [fx, fy, cx, cy]' in datasets.yaml, or put "
        "intrinsics.txt ('fx fy cx cy width height') in the folder, or name it after a TUM family (fr1/fr2/fr3)"
    )


def load_tum(spec: SequenceSpec) -> Sequence:
    """Load a TUM-layout folder (``tum``, ``lab``, ``synthetic``, 7-Scenes conversions).

    Args:
        spec: the resolved registry entry or folder spec. ``extra`` keys: ``max_dt`` (s),
            ``max_gt_gap`` (s), ``fy_sign`` (``auto`` runs
            :func:`~mutualslam_cli.datasets.fy_sign.decide_fy_sign`), ``all_frames`` (true: keep the RGB frames
            without a depth partner, depth-less; the depth metrics score the frames that have one).

    Returns:
        The associated :class:`Sequence` (frames carry GT poses at image time or ``None``).

    Raises:
        DatasetError: missing folder / lists / GT file, malformed lines, missing images,
            no GT overlap, no associated frame.
    """
    root = Path(spec.root)
    if not root.is_dir():
        raise DatasetError(f"{root}: sequence folder not found (registry entry '{spec.name}')")
    max_dt = float(spec.extra.get("max_dt", MAX_DT))
    if not isinstance(spec.extra.get("all_frames", False), bool):
        raise DatasetError(f"{spec.name}: all_frames = {spec.extra['all_frames']!r}: expected true or false")
    meta: SequenceMeta = {"format": spec.format}
    rgb_txt, depth_txt = root / "rgb.txt", root / "depth.txt"
    if rgb_txt.is_file() and (depth_txt.is_file() or spec.format in ("lab", "synthetic")):
        rgb_l = read_list_file(rgb_txt)
        if depth_txt.is_file():
            depth_l = read_list_file(depth_txt)
            pairs = associate(rgb_l.timestamps, depth_l.timestamps, max_dt=max_dt)
            ri = [i for i, _ in pairs]
            di = [j for _, j in pairs]
            depth: list[Path | None] = list(check_files(root, depth_l, [depth_l.paths[j] for j in di], di))
            if spec.extra.get("all_frames") is True:  # every RGB frame, depth where it has a partner
                partner = dict(zip(ri, depth))
                ri = list(range(len(rgb_l)))
                depth = [partner.get(i) for i in ri]
            rgb = check_files(root, rgb_l, [rgb_l.paths[i] for i in ri], ri)
            times = rgb_l.timestamps[ri]
            meta["association"] = {"source": "rgb.txt+depth.txt", "rgb": len(rgb_l), "depth": len(depth_l),
                                   "pairs": len(pairs), "max_dt": max_dt}
        else:
            ri = list(range(len(rgb_l)))
            rgb = check_files(root, rgb_l, rgb_l.paths, ri)
            depth = [None] * len(rgb)
            times = rgb_l.timestamps
            meta["association"] = {"source": "rgb.txt", "rgb": len(rgb_l), "depth": 0, "pairs": 0}
            meta.setdefault("warnings", []).append(f"{depth_txt}: not found; frames have no depth")
    elif (root / "associations.txt").is_file():
        times, rgb, depth_p, assoc = frames_from_associations(root, depth_first=False)
        depth = list(depth_p)
        meta["association"] = assoc
    elif not rgb_txt.is_file():
        raise DatasetError(f"{rgb_txt}: not found (expected lines 'timestamp rgb/<file>.png') and no associations.txt")
    else:
        raise DatasetError(f"{depth_txt}: not found (expected lines 'timestamp depth/<file>.png', 16-bit PNG)")
    if len(rgb) == 0:
        raise DatasetError(
            f"{root}: empty sequence: no RGB frame associated with a depth frame within {max_dt} s"
            if meta["association"].get("depth") else f"{root}: empty sequence: no frames listed"
        )
    gt, gt_name = load_gt(spec)
    poses = attach_gt(times, gt, gt_name, root, float(spec.extra.get("max_gt_gap", 0.1)))
    intr, source = resolve_intrinsics(spec, image_size(rgb[0]))
    frames = make_frames(times, rgb, depth, poses)
    meta.update({"intrinsics_source": source, "gt_file": gt_name, "fy_sign": 1 if intr.fy > 0 else -1,
                 "fy_sign_errors": None})
    seq = Sequence(spec.name, root, intr, float(spec.depth_scale), frames, gt, meta)
    if str(spec.extra.get("fy_sign", "")).lower() == "auto":
        apply_fy_sign(seq, "auto", fallback=1 if intr.fy > 0 else -1)
    return seq

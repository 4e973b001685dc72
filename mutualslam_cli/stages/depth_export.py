"""The depth of chosen frames, saved and pictured, GT or not (:func:`run_stage`): what someone running
on their own robot looks at.

``eval.export_frames`` frames, evenly spread over the sequence, are brought to the pinhole camera the
network works in (:class:`~mutualslam_cli.vo.camera.Undistorter`; without lens distortion the frame as
it is), and both models predict their depth. The adapted model's depth, resized to the frame's size so
that it lies pixel on pixel over the (undistorted) frame, is saved as

- ``depth/<frame>.png``: 16-bit, :data:`PNG_SCALE` per unit (TUM RGB-D's convention; 0 = no value, and
  depth beyond 65535 / 5000 units is stored as 0);
- ``depth/<frame>.npy``: ``(H, W)`` float32, the same values unquantised.

The unit is the network's: the adapted model learnt the VO map's scale (monocular: arbitrary, the same
for the whole run), the pre-trained one its training scale. ``depth/index.csv`` lists the frames
(timestamp, RGB file, files, median depth), and ``depth.png`` shows each frame beside both models'
inverse depth in one colour map (GT depth in a fourth column when the frame has it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from mutualslam_cli.atomic import atomic_path, atomic_write_text, atomic_write_with
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.stages.adaptation import Adapted
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.evaluation import predictors_for
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)

#: Raw PNG units per depth unit (TUM RGB-D: 5000 per metre).
PNG_SCALE = 5000.0
#: Percentiles of inverse depth that span the colour map of each panel of ``depth.png``.
COLOUR_RANGE = (5.0, 95.0)


def chosen_frames(n_frames: int, k: int) -> list[int]:
    """``k`` frame indices evenly spread over ``n_frames`` (first and last included), ascending, unique."""
    if k <= 0 or n_frames <= 0:
        return []
    return [int(i) for i in np.unique(np.linspace(0, n_frames - 1, min(k, n_frames)).round().astype(int))]


def to_png_units(depth: np.ndarray) -> np.ndarray:
    """``(H, W)`` float depth → uint16 at :data:`PNG_SCALE` per unit; non-finite, ≤ 0 or too far → 0."""
    raw = np.round(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float64) * PNG_SCALE)
    raw[(raw <= 0) | (raw > np.iinfo(np.uint16).max)] = 0
    return raw.astype(np.uint16)


def _png_writer(raw: np.ndarray) -> Callable[[str], bool]:
    """The writer :func:`~mutualslam_cli.atomic.atomic_write_with` calls with the temporary name: ``raw`` as a PNG."""
    return lambda name: bool(cv2.imwrite(name, raw))


def predict_frames(seq: Sequence, frames: list[int], nets: dict[str, torch.nn.Module], run: RunContext,
                   fast: bool) -> tuple[list[np.ndarray], dict[str, list[np.ndarray]], list[np.ndarray | None]]:
    """The pinhole frames ``(H, W, 3)`` uint8, each model's depth resized to ``(H, W)`` float32 (network
    units), and the GT depth ``(H, W)`` metres (or ``None``) of ``frames``."""
    und = Undistorter(seq.intrinsics)
    rgbs = [und.image(seq.load_rgb(i)) for i in frames]
    gts = [None if seq.frames[i].depth_path is None or (raw := seq.load_depth(i)) is None else und.depth(raw)
           for i in frames]
    out: dict[str, list[np.ndarray]] = {}
    for name, predict in predictors_for(seq, nets, run.cfg, fast, run.predictors).items():
        out[name] = [cv2.resize(np.asarray(d, np.float32), (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_LINEAR)
                     for rgb, d in zip(rgbs, (predict([rgb])[0] for rgb in rgbs))]
    return rgbs, out, gts


def run_stage(run: RunContext, net0: torch.nn.Module, adapted: Adapted, fast: bool) -> None:
    """Save the adapted model's depth of ``eval.export_frames`` frames and draw ``depth.png`` (module docstring)."""
    seq, cfg = run.seq, run.cfg
    frames = chosen_frames(len(seq), cfg.eval.export_frames)
    if not frames:
        run.summary.absent("depth.exported_frames", "eval.export_frames = 0")
        return
    nets = {"pretrained": net0}
    if cfg.adapt.scheme != "none":
        nets["adapted"] = adapted.net
    with run.timed("evaluation"):
        rgbs, depth, gts = predict_frames(seq, frames, nets, run, fast)
        saved = depth.get("adapted", depth["pretrained"])
        rows = []
        folder = run.folder / "depth"
        folder.mkdir(parents=True, exist_ok=True)
        for j, i in enumerate(frames):
            stem = f"{i:06d}"
            raw = to_png_units(saved[j])
            atomic_write_with(folder / f"{stem}.png", _png_writer(raw), "a 16-bit depth PNG")
            with atomic_path(folder / f"{stem}.npy") as tmp, open(tmp, "wb") as f:
                np.save(f, saved[j].astype(np.float32))
            valid = saved[j][np.isfinite(saved[j]) & (saved[j] > 0)]
            rows.append({"frame": i, "timestamp": seq.frames[i].timestamp, "rgb": str(seq.frames[i].rgb_path),
                         "png": f"{stem}.png", "npy": f"{stem}.npy",
                         "model": "adapted" if "adapted" in depth else "pretrained",
                         "median_depth": float(np.median(valid)) if valid.size else float("nan"),
                         "has_gt_depth": gts[j] is not None})
        atomic_write_text(folder / "index.csv", pd.DataFrame(rows).to_csv(index=False))
        heading = f"{seq.name} · {cfg.adapt.scheme} · seed {cfg.seed}"
        depth_picture(run.folder / "depth.png", rgbs, depth, gts, [seq.frames[i].timestamp for i in frames],
                      frames, heading)
    run.summary.set("depth.exported_frames", len(frames))


def inverse_depth_colours(depth: np.ndarray, cmap: str = "magma") -> np.ndarray:
    """``(H, W)`` depth → ``(H, W, 3)`` float RGB in [0, 1]: inverse depth between its
    :data:`COLOUR_RANGE` percentiles (each panel its own range: monocular scales differ); no value → black."""
    import matplotlib

    valid = np.isfinite(depth) & (depth > 0)
    inv = np.zeros_like(depth, dtype=np.float64)
    inv[valid] = 1.0 / depth[valid]
    if not valid.any():
        return np.zeros((*depth.shape, 3))
    lo, hi = np.percentile(inv[valid], COLOUR_RANGE)
    x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgb = matplotlib.colormaps[cmap](x)[..., :3]
    rgb[~valid] = 0.0
    return rgb


def depth_picture(path: Path, rgbs: list[np.ndarray], depth: dict[str, list[np.ndarray]],
                  gts: list[np.ndarray | None], times: list[float], frames: list[int], heading: str) -> None:
    """One row per frame: the (pinhole) frame, each model's inverse depth, and GT depth when any frame has it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {"pretrained": "pre-trained", "adapted": "adapted"}
    cols = ["frame"] + [m for m in labels if m in depth] + (["gt"] if any(g is not None for g in gts) else [])
    h, w = rgbs[0].shape[:2]
    fig, axes = plt.subplots(len(frames), len(cols), squeeze=False,
                             figsize=(2.6 * len(cols), 2.6 * len(frames) * h / w + 0.6))
    for r, i in enumerate(frames):
        for c, col in enumerate(cols):
            ax = axes[r][c]
            if col == "frame":
                ax.imshow(rgbs[r])
                ax.set_title(f"frame {i} · {times[r]:.3f} s", fontsize=8)
            elif col == "gt":
                g = gts[r]
                ax.imshow(inverse_depth_colours(g) if g is not None else np.zeros((h, w, 3)))
                ax.set_title("GT depth" if g is not None else "no GT depth", fontsize=8)
            else:
                d = depth[col][r]
                ax.imshow(inverse_depth_colours(d))
                ax.set_title(f"{labels[col]} · median {np.nanmedian(d):.2f}", fontsize=8)
            ax.set_axis_off()
    fig.suptitle(f"{heading}: inverse depth, each panel scaled to its own 5–95 %", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)

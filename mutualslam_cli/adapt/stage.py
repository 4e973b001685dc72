"""The adaptation stage of a run: the front end's keyframes through Algorithm 1 (DESIGN §1, §5)."""

from __future__ import annotations

import time
from typing import Any, Callable

import torch

from mutualslam_cli.adapt.buffer import KeyframeSample
from mutualslam_cli.adapt.depthnet import prepare
from mutualslam_cli.adapt.inputs import keyframe_images, scale_pixels
from mutualslam_cli.adapt.online import OnlineAdapter, StepInfo
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.vo.output import VOResult

Progress = Callable[[str, dict[str, Any]], None]
"""``progress(stage, info)``: stage name and a dict of figures (``done``, ``total``, …)."""


def run_adaptation(seq: Sequence, vo: VOResult, net: torch.nn.Module, cfg: RunConfig, fast: bool,
                   progress: Progress | None = None,
                   on_global_ba: Callable[[StepInfo], None] | None = None,
                   ) -> tuple[torch.nn.Module, list[dict[str, Any]], OnlineAdapter | None]:
    """Feed the keyframes, in order, through Algorithm 1 with the configured scheme.

    Each keyframe is given at network resolution (``cfg.net.width × height``, undistorted) with
    the map points it observes as sparse depth (map units).

    Args:
        on_global_ba: called when Algorithm 1 requests global BA (see :class:`OnlineAdapter`).

    Returns:
        ``(adapted_net, per_keyframe_rows, adapter)``; for scheme ``none`` the network is returned
        unchanged with no rows and ``adapter`` is ``None``.
    """
    if cfg.adapt.scheme == "none":
        return net, [], None
    w, h = cfg.net.width, cfg.net.height
    K_net = torch.from_numpy(vo.intrinsics.scaled(w, h).K()).float()
    net = prepare(net, fast)
    adapter = OnlineAdapter(net, cfg.adapt, K_net, seed=cfg.seed, fast=fast, on_global_ba=on_global_ba,
                            val_scope=cfg.adapt.val_scope, reg_mode=cfg.adapt.reg_mode)
    load = keyframe_images(seq, vo, w, h)
    pw = vo.points_world()
    rows = []
    t0 = time.perf_counter()
    for kf in vo.keyframes:
        uv, d = vo.sparse_depth(kf.id, pw)
        sample = KeyframeSample(
            kf_id=kf.id, image=load(kf.id), K=K_net, pose=kf.pose,
            uv=torch.from_numpy(scale_pixels(uv, vo.intrinsics, w, h)).float(),
            depth=torch.from_numpy(d).float(),
        )
        row = step_row(adapter.add_keyframe(sample))
        row["n_sparse"] = len(d)
        rows.append(row)
        if progress:
            progress("adapt", {"done": kf.id + 1, "total": len(vo.keyframes), **row,
                               "elapsed_s": time.perf_counter() - t0})
    return adapter.net, rows, adapter


def step_row(info: StepInfo) -> dict[str, Any]:
    """A flat CSV row from the adapter's step info (loss parts as ``loss_<part>`` columns)."""
    row: dict[str, Any] = {}
    for k, v in dict(vars(info)).items():
        if isinstance(v, dict):
            row.update({f"{k}_{p}": x for p, x in v.items()})
        elif isinstance(v, (list, tuple)):
            row[k] = " ".join(map(str, v))
        else:
            row[k] = v.value if hasattr(v, "value") else v
    return row

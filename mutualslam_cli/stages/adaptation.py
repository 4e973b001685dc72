"""The adaptation stage of a run: the front end's keyframes through Algorithm 1 (DESIGN §1, §5).

With a ``global_ba`` step this is the *mutual* loop (paper §III-A, §III-C): when Algorithm 1
requests global BA after keyframe t, the step culls and refines the map of keyframes ≤ t with the
current network, and the refined keyframe poses and sparse depths replace those of every stored
keyframe (:meth:`~mutualslam_cli.adapt.online.OnlineAdapter.update_poses`,
:meth:`~mutualslam_cli.adapt.online.OnlineAdapter.update_sparse`), so later batches' sparse loss
and photometric warps use them. Keyframes arriving later are read from the refined map, whose
later poses followed the correction (:func:`mutualslam_cli.ba.global_ba.run_global_ba`).
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping

import numpy as np
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample
from mutualslam_cli.adapt.depthnet import predict_depth, prepare
from mutualslam_cli.adapt.inputs import keyframe_images, scale_pixels
from mutualslam_cli.adapt.online import OnlineAdapter, StepInfo
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.vo.result import VOResult

Progress = Callable[[str, dict[str, Any]], None]
"""``progress(stage, info)``: stage name and a dict of figures (``done``, ``total``, …)."""

DepthOf = Callable[[int], np.ndarray]
"""``depth_of(kf_id)``: ``(h, w)`` depth of the current network at network resolution, map units."""

GlobalBA = Callable[[VOResult, int, DepthOf, Mapping[int, float]], VOResult]
"""``global_ba(vo, kf_id, depth_of, val_loss) -> vo'``: culling + global BA of keyframes ≤ ``kf_id``
of the loop's map ``vo`` with the current network (``val_loss``: L_val per stored keyframe);
returns the loop's new map (culled points dropped, later keyframes following the correction)."""


def depth_predictor(net: torch.nn.Module, load: Callable[[int], torch.Tensor], fast: bool,
                    buffer: KeyframeBuffer | None = None) -> DepthOf:
    """:data:`DepthOf` of ``net`` for keyframe images from ``buffer`` when stored, else ``load(kf_id)``."""

    def depth_of(kf_id: int) -> np.ndarray:
        img = buffer.get(kf_id).image if buffer is not None and kf_id in buffer else load(kf_id)
        return predict_depth(net, img[None], fast)[0]

    return depth_of


def run_adaptation(seq: Sequence, vo: VOResult, net: torch.nn.Module, cfg: RunConfig, fast: bool,
                   progress: Progress | None = None, global_ba: GlobalBA | None = None,
                   ) -> tuple[torch.nn.Module, list[dict[str, Any]], OnlineAdapter | None, VOResult]:
    """Feed the keyframes, in order, through Algorithm 1 with the configured scheme.

    Each keyframe is given at network resolution (``cfg.net.width × height``, undistorted) with
    the map points it observes as sparse depth (map units), from the loop's current map.

    Args:
        global_ba: run when Algorithm 1 requests global BA (module docstring); ``None``: the
            request is only recorded (``run_global_ba`` column).

    Returns:
        ``(adapted_net, per_keyframe_rows, adapter, map)``: ``map`` is the loop's map at the end
        (``vo`` itself unless a BA ran); rows of BA keyframes have ``ba_s`` (seconds of the
        trigger: L_val, culling, BA, feedback). For scheme ``none`` the network is returned
        unchanged with no rows, ``adapter`` is ``None`` and the map is ``vo``.
    """
    if cfg.adapt.scheme == "none":
        return net, [], None, vo
    w, h = cfg.net.width, cfg.net.height
    K_net = torch.from_numpy(vo.intrinsics.scaled(w, h).K()).float()
    net = prepare(net, fast)
    load = keyframe_images(seq, vo, w, h)
    held = [vo, vo.points_world()]  # the loop's map and its world points; a BA replaces both
    ba_s: dict[int, float] = {}

    def sparse(kf_id: int) -> tuple[torch.Tensor, torch.Tensor]:
        uv, d = held[0].sparse_depth(kf_id, held[1])
        return torch.from_numpy(scale_pixels(uv, vo.intrinsics, w, h)).float(), torch.from_numpy(d).float()

    def on_global_ba(info: StepInfo) -> None:
        assert global_ba is not None
        t = time.perf_counter()
        new = global_ba(held[0], info.kf_id, depth_predictor(adapter.net, load, fast, adapter.buffer),
                        adapter.per_keyframe_val_loss())
        held[:] = [new, new.points_world()]
        ids = [k.id for k in new.keyframes[:info.kf_id + 1]]
        adapter.update_poses({k: new.keyframes[k].pose for k in ids})
        adapter.update_sparse({k: sparse(k) for k in ids})
        ba_s[info.kf_id] = time.perf_counter() - t

    adapter = OnlineAdapter(net, cfg.adapt, K_net, seed=cfg.seed, fast=fast,
                            on_global_ba=on_global_ba if global_ba is not None else None,
                            val_scope=cfg.adapt.val_scope, reg_mode=cfg.adapt.reg_mode)
    rows = []
    t0 = time.perf_counter()
    for kf in vo.keyframes:
        uv, d = sparse(kf.id)
        sample = KeyframeSample(kf_id=kf.id, image=load(kf.id), K=K_net, pose=held[0].keyframes[kf.id].pose,
                                uv=uv, depth=d)
        row = step_row(adapter.add_keyframe(sample))
        row["n_sparse"] = len(d)
        if kf.id in ba_s:
            row["ba_s"] = ba_s[kf.id]
        rows.append(row)
        if progress:
            progress("adapt", {"done": kf.id + 1, "total": len(vo.keyframes), **row,
                               "elapsed_s": time.perf_counter() - t0})
    return adapter.net, rows, adapter, held[0]


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


# ----------------------------------------------------------------------------- summary keys


def summarise_adaptation(summary: Summary, scheme: str, step_ms: list[float], keyframe_ms: list[float],
                         kf_rows: list[dict[str, Any]] | None = None) -> None:
    """``timing.finetune_ms`` (median per optimiser step) and ``timing.finetune_kf_ms`` (per keyframe);
    with the keyframe rows, ``adaptation.keyframes_trained`` and, for scheme ``luo``,
    ``adaptation.luo_keyframes_with_partner`` (training keyframes that found a simulated stereo partner)."""
    why = "scheme 'none': no fine-tuning" if scheme == "none" else "no keyframe was trained on"
    summary.set("timing.finetune_ms", float(np.median(step_ms)) if step_ms else None, why)
    summary.set("timing.finetune_kf_ms", float(np.median(keyframe_ms)) if keyframe_ms else None, why)
    if kf_rows is None:
        return
    summary.set("adaptation.keyframes_trained", sum(bool(r.get("trained")) for r in kf_rows))
    if scheme == "luo":
        training = [r for r in kf_rows if not r.get("is_validation")]
        summary.set("adaptation.luo_keyframes_with_partner", sum(bool(str(r.get("sources") or "").strip())
                                                                 for r in training))
        summary.set("adaptation.training_keyframes", len(training))

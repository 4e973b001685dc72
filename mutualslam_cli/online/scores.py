"""Online depth evaluation: every evaluated frame scored with the model *of its time*.

The evaluation stage (:mod:`~mutualslam_cli.stages.evaluation`) scores the final model on every
frame, so a frame seen early is scored with a network that trained on keyframes long after it.
Luo et al. score each keyframe with the model of its time (the paper notes this under Table 1),
and it is what a SLAM system consuming the depth sees live. Here frame ``f`` is scored with the
network as it was *before it learned from* ``f``: after the adaptation loop trained on the last keyframe
whose frame index is ``< f`` (its fine-tuning and any global BA it triggered); a keyframe's own frame is
scored before the steps on that keyframe (test-time adaptation's rule: a frame is scored before the model
trains on it, so no score is of a model that saw its frame), and frames up to the first keyframe, its own
included, get the pre-trained network. The realtime schedule applies the same rule on its clock: each frame
by the weights before the step that ends after it (:mod:`~mutualslam_cli.online.realtime`). Frames and GT
are those of the evaluation (every ``eval.stride``-th frame with GT depth, undistorted to the network's
pinhole camera).

**Runtime.** On CPUs of the kinds in :data:`OPENVINO_ONLINE_KINDS`, where ``net.runtime`` resolves to
OpenVINO bf16 (:func:`~mutualslam_cli.adapt.inference.resolve_runtime`), the online scores go through the
evaluation's runtime: the network is converted once, at the first scored frames, and each later model only
swaps the compiled weights (:class:`~mutualslam_cli.adapt.ov_refresh.RefreshablePredictor`; the refreshes'
seconds are ``timing.online_refresh_s``), and the evaluation reuses that predictor for the final model instead
of converting it again. The refresh (fold + compile, ~0.2 s on one idle core, 0.35–0.4 s loaded) pays only
where OpenVINO predicts much faster than PyTorch: on AMX (OpenVINO ~11–14 ms a frame against ~127 ms
through PyTorch, issue 51) it pays on the first frame of a model. On AMD EPYC with AVX512-BF16 (no AMX) it
does not: alternated runs of tum_fr1_xyz (replay+ewc, 1 thread, loaded host; 16 models, ~6 frames each)
took 22.6 s of online scoring through OpenVINO (6.1 s of it refreshes, ~5 s the first conversion) against
15.3 s through PyTorch bf16 autocast, the evaluation's saved conversion (2 s) included — so there, and on
GPUs, CPUs without bf16 (OpenVINO fp32 there: 100 ms a frame against 130 through PyTorch, a refresh 120–130 ms,
so at ~6 frames a model it saves nothing; an int8 runtime would need a new calibration per model) or with
``net.runtime=torch``, prediction is the torch path of the training loop (mixed precision with ``fast``) on
the network's device. Either path's depth is within
:data:`~mutualslam_cli.adapt.ov_refresh.BF16_REL_TOL` of fp32 with the same weights
(``tests/online/test_scores.py``).

Frames between two keyframes share one model, so they are predicted together when the model is about
to change (:meth:`OnlineScorer.score_until`, called at the next keyframe's arrival), in forward passes of
:func:`batch_size` frames. On the CPU an fp32 (NCHW) network predicts through a channels-last twin that
takes its weights at each call (the layout oneDNN prefers). Both change the depth only at float rounding
(the kernels sum in another order: 3e-7 relative here; ``tests/online/test_scores.py`` bounds it).
Measured on a loaded 2-core AVX2 CPU, fp32 640×192, ms per frame (one pass per frame, NCHW = before):

=========  =====  =====  =====  ===============  ===============
threads    b = 1  b = 2  b = 4  channels-last 2  channels-last 4
=========  =====  =====  =====  ===============  ===============
1            331    321    361              279              318
2           1858   1099    726              802              549
=========  =====  =====  =====  ===============  ===============

(two threads among other busy processes stall at every operation's barrier: larger passes amortise it).

Outputs: ``online_*`` columns of ``per_frame.csv`` (``online_pcd_{lsq,median,seq_lsq}``,
``online_esi``, ``online_kf``: the keyframe id whose model scored the frame, -1 = pre-trained) and the
summary keys ``depth.pcd_online[_nonkf].{lsq,median,seq_lsq}`` and ``depth.esi_online``.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Literal

import numpy as np
import pandas as pd
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, predict_depth, prepare
from mutualslam_cli.adapt.inference import resolve_runtime
from mutualslam_cli.adapt.inputs import resample, to_net_image
from mutualslam_cli.adapt.ov_refresh import NotRefreshable, RefreshablePredictor
from mutualslam_cli.adapt.step_info import StepLog
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.device import module_device
from mutualslam_cli.machine import cpu_info
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.metrics.ratios import pcd_from_sketch
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)

#: CPU kinds (:func:`~mutualslam_cli.machine.cpu_kind`) whose online scores go through OpenVINO (module
#: docstring, "Runtime": where a weight refresh costs less than the predictions it speeds up).
OPENVINO_ONLINE_KINDS = ("AMX",)


def online_runtime(cfg: RunConfig, device: torch.device, kind: str | None = None) -> str:
    """``"openvino"`` where the online scores go through the evaluation's OpenVINO bf16 runtime, else ``"torch"``
    (module docstring, "Runtime"); ``kind``: the CPU kind (default: this machine's)."""
    if device.type != "cpu" or resolve_runtime(cfg.net.runtime, cfg.net.fast, device) != "openvino":
        return "torch"
    kind = cpu_info()["cpu_kind"] if kind is None else kind
    return "openvino" if kind in OPENVINO_ONLINE_KINDS else "torch"


#: Frames per forward pass of the online scores on a GPU (at most; the frames one model scores).
BATCH = 8


def batch_size(device: torch.device, threads: int) -> int:
    """Frames per forward pass: :data:`BATCH` on a GPU; on the CPU 2 with one thread, 4 with more (module
    docstring's table: larger passes cost cache misses on one thread and save barrier stalls on several)."""
    if device.type != "cpu":
        return BATCH
    return min(BATCH, 2 if threads <= 1 else 4)


def eval_frames(seq: Sequence, stride: int) -> list[int]:
    """Indices of the frames the depth evaluation scores: every ``stride``-th frame with GT depth."""
    return [i for i, f in enumerate(seq.frames) if f.depth_path is not None][:: max(1, stride)]


#: Columns of :meth:`OnlineScorer.table` besides ``frame`` (per-frame metrics of the model of its time).
COLUMNS = ("pcd_lsq", "pcd_median", "esi", "sum_pg", "sum_pp")


class OnlineScorer:
    """Scores the evaluation's frames as the adaptation loop goes (module docstring).

    Args:
        seq: the sequence.
        frames: frame indices to score, ascending (:func:`eval_frames`).
        cfg: run config (``net.width/height``, ``eval.max_depth``, ``eval.pcd_threshold``).
        fast: bf16 autocast for the predictions.
    """

    def __init__(self, seq: Sequence, frames: list[int], cfg: RunConfig, fast: bool) -> None:
        self.seq, self.cfg, self.fast = seq, cfg, fast
        self._todo = sorted(frames)
        self._next = 0
        self._und = Undistorter(seq.intrinsics)
        self._rows: list[dict[str, float | int]] = []
        self._sketches: list[np.ndarray | None] = []
        self._twin: torch.nn.Module | None = None  # channels-last copy of an NCHW network on the CPU
        self._ov: RefreshablePredictor | Literal[False] | None = None  # None: not decided yet; False: the torch path
        self.seconds = 0.0
        self.log: StepLog | None = None  # the adaptation's step log: scoring and refreshes marked between steps

    def score_until(self, net: torch.nn.Module, frame_index: int, kf_id: int) -> None:
        """Score, with ``net`` (the model after keyframe ``kf_id``; -1 = pre-trained), every pending
        frame whose index is ``< frame_index``, :data:`BATCH` frames per forward pass."""
        t = time.perf_counter()
        cfg = self.cfg
        todo = []
        while self._next < len(self._todo) and self._todo[self._next] < frame_index:
            todo.append(self._todo[self._next])
            self._next += 1
        if not todo:
            return
        predict, device = self._predictor(net)
        bs = batch_size(device, cfg.threads)  # the run's resolved count (stages/context.py: use_threads)
        for c in range(0, len(todo), bs):
            chunk = todo[c:c + bs]
            small = np.stack([resample(self._und.image(self.seq.load_rgb(i)), cfg.net.width, cfg.net.height)
                              for i in chunk])  # (B, h, w, 3) uint8: what goes to the network's device
            for i, depth in zip(chunk, predict(small)):
                gt = self.seq.load_depth(i)
                assert gt is not None  # eval_frames: frames with a depth image only
                stats = asdict(dm.depth_stats(depth, self._und.depth(gt), cfg.eval.max_depth,
                                           cfg.eval.pcd_threshold, sketch=True))
                self._sketches.append(stats.pop("sketch"))
                self._rows.append({"frame": i, "online_kf": kf_id, **{f"online_{k}": stats[k] for k in COLUMNS}})
        self.seconds += time.perf_counter() - t

    @property
    def refresh_seconds(self) -> float:
        """Seconds spent giving the OpenVINO predictor each new model's weights (0 on the torch path)."""
        return float(sum(self._ov.refresh_s)) if self._ov else 0.0

    def _predictor(self, net: torch.nn.Module) -> tuple[Callable[[np.ndarray], np.ndarray], torch.device]:
        """``f(small)``: ``(B, h, w, 3)`` uint8 → ``(B, h, w)`` float32 depth with ``net``'s weights now, and the
        device it runs on (module docstring, "Runtime")."""
        device = module_device(net)
        fresh = self._ov is None
        if fresh:
            self._ov = False
            if isinstance(net, DepthNet) and online_runtime(self.cfg, device) == "openvino":
                try:
                    self._ov = RefreshablePredictor(net, self.cfg.net.width, self.cfg.net.height)
                except NotRefreshable as exc:
                    log.warning("online scores through PyTorch: %s", exc)
        if self._ov:
            if not fresh:
                self._ov.refresh(net)
                if self.log is not None:
                    self.log.mark("refresh")
            ov = self._ov
            return (lambda small: ov(torch.from_numpy(small).permute(0, 3, 1, 2).float() / 255.0)), device
        twin = self._scoring_net(net)
        return (lambda small: predict_depth(twin, small, self.fast)), device

    def eval_predictor(self, net: torch.nn.Module) -> Callable[[list[np.ndarray]], np.ndarray] | None:
        """The evaluation's predictor of ``net`` made of this scorer's OpenVINO conversion (``None`` on the torch
        path): ``B`` frames ``(H, W, 3)`` uint8 (pinhole) → ``(B, h, w)`` depth, as
        :func:`~mutualslam_cli.adapt.inputs.make_predictor` would build by converting ``net`` again (~2 s); at its
        first call it takes ``net``'s weights of then (one refresh, ~0.2 s). Call it after :meth:`finish`: the
        scorer's predictor is the evaluation's from then on."""
        ov = self._ov
        if not ov:
            return None
        width, height, pending = self.cfg.net.width, self.cfg.net.height, [True]

        def predict(frames: list[np.ndarray]) -> np.ndarray:
            if pending:
                ov.refresh(net)
                pending.clear()
            return ov(torch.stack([to_net_image(rgb, width, height) for rgb in frames]))

        return predict

    def _scoring_net(self, net: torch.nn.Module) -> torch.nn.Module:
        """``net``, or on the CPU for an NCHW :class:`DepthNet` its channels-last twin holding its weights now."""
        if not isinstance(net, DepthNet) or net.channels_last or module_device(net).type != "cpu":
            return net
        if self._twin is None:
            self._twin = prepare(copy.deepcopy(net), False, channels_last=True).eval()
        else:
            self._twin.load_state_dict(net.state_dict())  # the weights of now, in the twin's layout
        return self._twin

    def finish(self, net: torch.nn.Module, kf_id: int) -> pd.DataFrame:
        """Score the frames left with the final ``net``; the ``online_*`` table, one row per frame."""
        self.score_until(net, np.iinfo(np.int64).max, kf_id)
        table = pd.DataFrame(self._rows, columns=["frame", "online_kf", *(f"online_{k}" for k in COLUMNS)])
        s = dm.sequence_lsq_scale(table["online_sum_pg"], table["online_sum_pp"])
        table["online_pcd_seq_lsq"] = [pcd_from_sketch(k, s, self.cfg.eval.pcd_threshold) for k in self._sketches]
        return table.drop(columns=["online_sum_pg", "online_sum_pp"])

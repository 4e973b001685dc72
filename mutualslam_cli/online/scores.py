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
pinhole camera); prediction is the torch path of the training loop (mixed precision with ``fast``) on the
network's device, so the last frames — scored online by the final network — also show how far this path is
from the evaluation's runtime.

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
import time
from dataclasses import asdict

import numpy as np
import pandas as pd
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, predict_depth, prepare
from mutualslam_cli.adapt.inputs import resample
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.device import module_device
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.metrics.ratios import pcd_from_sketch
from mutualslam_cli.vo.camera import Undistorter

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
        self.seconds = 0.0

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
        net = self._scoring_net(net)
        bs = batch_size(module_device(net), torch.get_num_threads())
        for c in range(0, len(todo), bs):
            chunk = todo[c:c + bs]
            small = np.stack([resample(self._und.image(self.seq.load_rgb(i)), cfg.net.width, cfg.net.height)
                              for i in chunk])  # (B, h, w, 3) uint8: what goes to the network's device
            for i, depth in zip(chunk, predict_depth(net, small, self.fast)):
                stats = asdict(dm.depth_stats(depth, self._und.depth(self.seq.load_depth(i)), cfg.eval.max_depth,
                                           cfg.eval.pcd_threshold, sketch=True))
                self._sketches.append(stats.pop("sketch"))
                self._rows.append({"frame": i, "online_kf": kf_id, **{f"online_{k}": stats[k] for k in COLUMNS}})
        self.seconds += time.perf_counter() - t

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

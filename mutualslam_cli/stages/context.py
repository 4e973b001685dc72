"""What every stage of a run works in (:class:`RunContext`): the sequence, the config, the run
folder and its summary, the time each stage took and the progress callback; and how a run gets its
sequence (:func:`open_sequence`) and its thread count (:func:`use_threads`)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import torch

from mutualslam_cli.config import RunConfig, with_overrides
from mutualslam_cli.datasets.recordings.recording import RecordingOptions
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.types import Info, Predictor, Progress


@dataclass
class RunContext:
    """One run's shared state; each stage writes its files into ``folder`` and its keys into ``summary``.

    Attributes:
        seq: the sequence.
        cfg: the resolved configuration (threads resolved too).
        folder: the folder the run writes: the staging folder that becomes ``<out>/<sequence>/<scheme>/seed<k>``
            when the run completes (:mod:`~mutualslam_cli.results.staging`).
        out_root: the results root; its ``_cache/`` is shared by the runs of a grid.
        summary: the run's ``summary.json`` under construction.
        progress: ``progress(stage, info)`` or ``None``.
        timings: seconds per stage (``frontend``, ``adaptation``, ``ba``, ``evaluation``, ``dense``).
        device: where the depth network runs (:mod:`~mutualslam_cli.device`), resolved once per run.
        predictors: the evaluation runtimes' predictors built so far, by ``(model name, id(model))``
            (:func:`~mutualslam_cli.stages.evaluation.predictors_for`): built once, reused by later stages.
        device_info: what ``manifest.json`` records of the device (:func:`~mutualslam_cli.device.describe_device`).
    """

    seq: Sequence
    cfg: RunConfig
    folder: Path
    out_root: Path
    summary: Summary = field(default_factory=Summary)
    progress: Progress | None = None
    timings: dict[str, float] = field(default_factory=dict)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    predictors: dict[tuple[str, int], Predictor] = field(default_factory=dict)
    device_info: dict[str, object] = field(default_factory=dict)

    @property
    def cache(self) -> Path:
        """``<out_root>/_cache``: what the runs of a grid share (front ends, pre-trained evaluations)."""
        return self.out_root / "_cache"

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Add the wall time of the ``with`` block to ``timings[stage]`` (seconds)."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.add_time(stage, time.perf_counter() - t)

    def add_time(self, stage: str, seconds: float) -> None:
        """Add ``seconds`` to ``timings[stage]``."""
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds

    def report(self, stage: str, info: Info) -> None:
        """Pass ``info`` to the progress callback, if any."""
        if self.progress is not None:
            self.progress(stage, info)


def resolve_threads(requested: int, workers: int = 1) -> int:
    """The one rule for ``threads: 0``: the threads torch would use in this process (its cores), shared among
    ``workers`` processes on the same machine, at least 1; a positive ``requested`` is kept as it is."""
    return requested if requested > 0 else max(1, torch.get_num_threads() // max(1, workers))


def use_threads(cfg: RunConfig) -> RunConfig:
    """``cfg`` with ``threads`` resolved (:func:`resolve_threads`), set for torch and OpenCV.

    Results follow the thread count (reductions sum in another order), so the count is resolved
    once, used alike by torch, OpenCV and BLAS (:func:`~mutualslam_cli.pipeline.run_sequence`), and
    recorded in ``config.yaml`` like any setting; the stages read ``cfg.threads``, never torch.
    """
    cfg = with_overrides(cfg, threads=resolve_threads(cfg.threads))
    torch.set_num_threads(cfg.threads)
    cv2.setNumThreads(cfg.threads)
    return cfg


def open_sequence(sequence: str | Path | Sequence, cfg: RunConfig, registry: Path | None = None,
                  recording: RecordingOptions | None = None, progress: Progress | None = None) -> Sequence:
    """The sequence a run reads: a loaded one as is, else a ``datasets.yaml`` name, a folder or a recording
    (converted once into ``recording.cache``, reported as ``progress("convert", {"done": frames})``)."""
    if isinstance(sequence, Sequence):
        return sequence
    report = None if progress is None else (lambda n: progress("convert", {"done": n, "total": None}))
    return load_sequence(sequence, data_root=cfg.data.data_root, registry_path=registry,
                         max_frames=cfg.data.max_frames, stride=cfg.data.stride, recording=recording,
                         progress=report)

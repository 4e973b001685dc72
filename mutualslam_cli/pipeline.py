"""One sequence, one scheme (DESIGN §1): Algorithm 1 around a sequence, one call per stage.

:func:`run_sequence` is what ``mslam run`` calls: front end → online adaptation (with culling +
global BA at Algorithm 1's requests: the mutual loop) → final culling + BA → depth evaluation →
(dense reconstruction) → ``summary.json``. Each stage (:mod:`mutualslam_cli.stages`) writes its own
files and summary keys into the run folder. :func:`fuse_run` (``mslam fuse``) runs the dense stage
on a finished run with the same setup. Progress goes to an optional callback
``progress(stage, info)`` and to :mod:`logging`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from threadpoolctl import threadpool_limits

from mutualslam_cli.adapt.inputs import load_network, load_saved_network, use_fast_path
from mutualslam_cli.adapt.weights import ENCODER_FILE, has_depth_files
from mutualslam_cli.allocator import retain_freed_memory
from mutualslam_cli.config import RunConfig, load_config, to_dict
from mutualslam_cli.datasets.recordings.recording import RecordingOptions
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.device import configure, describe_device, resolve_device
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.run_folder import (
    fuse_record,
    is_complete,
    read_manifest,
    run_dir,
    write_json,
    write_yaml,
)
from mutualslam_cli.results.staging import staged
from mutualslam_cli.results.summary import RunSummary, Summary, read_summary
from mutualslam_cli.results.writable import check_output_folder, write_errors
from mutualslam_cli.stages import adaptation, dense, depth_export, evaluation, frontend, scale_drift
from mutualslam_cli.stages.ba import BAStage
from mutualslam_cli.stages.context import RunContext, open_sequence, use_threads
from mutualslam_cli.stages.run_record import write_record
from mutualslam_cli.types import Progress

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """What :func:`run_sequence` returns.

    Attributes:
        folder: the result folder.
        summary: what ``summary.json`` holds.
        skipped: True when the run was already complete and nothing was recomputed.
        timings: seconds per stage (and ``load``, ``total``).
    """

    folder: Path
    summary: RunSummary
    skipped: bool = False
    timings: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- mslam run


def run_sequence(sequence: str | Path | Sequence, cfg: RunConfig, out: str | Path | None = None,
                 command: list[str] | None = None, force: bool = False,
                 progress: Progress | None = None, registry: Path | None = None,
                 recording: RecordingOptions | None = None) -> RunResult:
    """Run one sequence with one scheme and write ``<out>/<seq>/<scheme>/seed<k>/`` (DESIGN §8).

    Args:
        sequence: a ``datasets.yaml`` name, a folder, or a loaded :class:`Sequence`.
        cfg: resolved configuration.
        out: results root (default ``cfg.out``).
        command: the command line, recorded in ``manifest.json``.
        force: recompute even when the run is complete.
        progress: ``progress(stage, info)`` with stages ``convert`` (a recording), ``vo``, ``adapt``, ``eval``,
            ``dense``.
        registry: an alternative ``datasets.yaml``.
        recording: how to read a ROS bag, video or image folder (topics, camera file, GT file); it is
            converted once into ``<out>/_cache/recordings`` unless ``recording.cache`` says otherwise.

    Returns:
        :class:`RunResult`. A complete run (``summary.json`` present) is returned as is unless
        ``force``.

    The run writes a staging folder that replaces the run folder only once ``summary.json`` is in it
    (:mod:`~mutualslam_cli.results.staging`): a run that fails, or is killed, leaves the folder as it was.

    Raises:
        ResultsLocked: another process works in the same run folder (:mod:`~mutualslam_cli.results.lock`).
        ConfigError: ``device`` names a CUDA device this process cannot use.
        OutputError: ``out`` is a file, read-only, or a write failed (the disk full): one line naming the path
            (:mod:`~mutualslam_cli.results.writable`).
    """
    t_start = time.perf_counter()
    device = resolve_device(cfg.device)  # once per run; everything that holds network tensors gets it
    torch.manual_seed(cfg.seed)  # seeds CUDA's generators too
    retain_freed_memory()  # image-sized buffers reuse pages (VO, warps, evaluation)
    cfg = use_threads(cfg)
    out_root = check_output_folder(out if out is not None else cfg.out)  # a file, read-only: before any work
    recording = recording or RecordingOptions()
    if recording.cache is None:
        recording = replace(recording, cache=out_root / "_cache" / "recordings")
    with write_errors(out_root):
        seq = open_sequence(sequence, cfg, registry, recording, progress)
    t_load = time.perf_counter() - t_start
    folder = run_dir(out_root, seq.name, cfg.adapt.scheme, cfg.seed)
    if is_complete(folder) and not force:
        log.info("%s is complete; skipping (use --force to recompute)", folder)
        return RunResult(folder, read_summary(folder), skipped=True)
    kept = "the previous run in it is as it was" if is_complete(folder) else "nothing of this run was kept"
    # a second process on this folder stops at the lock, having touched nothing
    with write_errors(out_root, kept), hold_lock(folder, "mslam run", beside=True), \
            threadpool_limits(limits=cfg.threads, user_api="blas"):
        if is_complete(folder) and not force:  # completed by the previous holder just before we locked
            return RunResult(folder, read_summary(folder), skipped=True)
        # the folder changes only when the run completes (results/staging.py); a write error is named while
        # the staging folder still fills the disk, then the staging folder goes
        with staged(folder) as stage, write_errors(out_root, kept):
            run = RunContext(seq, cfg, stage, out_root, progress=progress, device=device, timings={"load": t_load})
            summary, timings = _run(run, command, t_start)
        return RunResult(folder, summary, timings=timings)


def _run(run: RunContext, command: list[str] | None, t_start: float) -> tuple[RunSummary, dict[str, float]]:
    """Algorithm 1 around a sequence, in its staging folder, under the run folder's lock; returns
    ``(summary, timings)`` (:func:`~mutualslam_cli.stages.run_record.write_record`)."""
    cfg = run.cfg
    write_yaml(run.folder / "config.yaml", to_dict(cfg))
    run.device_info = {**describe_device(run.device), **configure(run.device, cfg.deterministic)}
    log.info("depth network on %s (%s)", run.device, run.device_info["device_name"])
    fast = use_fast_path(cfg.net, run.device)
    net0 = load_network(cfg.net, fast, run.device)  # the pre-trained model
    ba = BAStage(run)  # culling + global BA: at Algorithm 1's requests (the mutual loop) and at the end
    started = frontend.start_stage(run)  # the front end Algorithm 1 follows, and the front end on its own
    if cfg.adapt.scheme == "comoda":  # the baseline: every frame, its own pose network, no keyframes
        adapted = adaptation.run_comoda(run, started, net0, fast)
    else:  # Algorithm 1, with culling + global BA at its requests
        adapted = adaptation.run_algorithm1(run, started, net0, fast, ba.map_ba if cfg.ba.enabled else None)
    adaptation.finish_stage(run, started, adapted)
    fe = frontend.run_stage(run, started)  # the front end's own map: trajectories, map, vo.* keys
    ba.finish(adapted, fe, fast)  # the back end: final culling + global BA
    scale_drift.run_stage(run, {"vo": fe.vo, "ba": ba.final}, {"ba": ba.why_no_final})  # local vs global Sim(3)
    evaluation.run_stage(run, fe, net0, adapted, fast)  # both models' depth on every frame with GT
    depth_export.run_stage(run, net0, adapted, fast)  # chosen frames' depth saved and pictured
    if cfg.dense.enabled:
        dense.run_stage(run, fe, net0, adapted, fast)  # TSDF meshes of both models, scored against GT
    return write_record(run, fe, ba, adapted, command, t_start)  # summary.json last: the run is complete


# ----------------------------------------------------------------------------- mslam fuse


def fuse_run(folder: Path, overrides: list[str] | None = None, registry: Path | None = None,
             progress: Progress | None = None, seq: Sequence | None = None,
             command: list[str] | None = None) -> RunSummary:
    """The dense stage on a finished run folder (``mslam fuse RUN_DIR``), with the run's setup: its
    config, sequence, front end (from the VO cache beside the results, recomputed if absent),
    pre-trained model and ``weights/``; updates ``summary.json`` (the ``dense.*`` keys),
    ``config.yaml``'s ``dense`` section and ``manifest.json`` (a ``fuse`` entry) — in a staging copy of the run
    folder that replaces it when the dense stage is done (a failed fuse leaves the run as it was).

    Args:
        overrides: ``--set``-style ``dense.*`` (or other) settings on top of the run's config.
        seq: use this sequence instead of loading the one the manifest names (tests).

    Returns:
        What the updated ``summary.json`` holds.

    Raises:
        DatasetError: not a complete run folder, or no adapted weights (``--set eval.save_weights=true``).
    """
    folder = Path(folder)
    old = read_summary(folder)
    cfg = load_config(folder / "config.yaml", overrides)
    wdir = folder / "weights"
    adapted = cfg.adapt.scheme != "none"
    if adapted and not has_depth_files(wdir):
        raise DatasetError(f"{folder}: the run kept no adapted weights (no weights/{ENCODER_FILE}); rerun it with "
                           "--set eval.save_weights=true (and --force) to fuse it later")
    record = read_manifest(folder)
    root = (record.get("sequence") or {}).get("root") if isinstance(record.get("sequence"), dict) else None
    if seq is None and not root:
        raise DatasetError(f"{folder}: manifest.json names no sequence root")
    t0 = time.perf_counter()
    with write_errors(folder.parent, "the run is as it was"), hold_lock(folder, "mslam fuse", beside=True), \
            staged(folder, from_current=True) as stage, write_errors(folder.parent, "the run is as it was"):
        cfg = use_threads(cfg)
        device = resolve_device(cfg.device)
        configure(device, cfg.deterministic)
        where = seq if seq is not None else root
        assert where is not None  # neither a sequence nor a root raised DatasetError above
        seq = open_sequence(where, cfg, registry)
        vo, _, _ = frontend.load_frontend(seq, cfg, folder.parents[2] / "_cache" / "vo", progress)
        fast = use_fast_path(cfg.net, device)
        nets = {"pretrained": load_network(cfg.net, fast, device),
                "adapted": load_saved_network(wdir, cfg.net, fast, device) if adapted else None}
        summary = Summary.from_record(old, drop_prefix="dense.")
        dense.run_dense(stage, seq, vo, nets, cfg, fast, summary, progress)
        data = to_dict(cfg)
        data["dense"]["enabled"] = True  # the folder now holds the dense results of these settings
        write_yaml(stage / "config.yaml", data)
        record["fuse"] = fuse_record(command, time.perf_counter() - t0, describe_device(device))
        write_json(stage / "manifest.json", record)
        out = summary.to_dict()
        write_json(stage / "summary.json", out)
    return RunSummary.parse(out, str(folder / "summary.json"))

"""What a run records about itself once its stages are done (:func:`write_record`, the last step of
:func:`~mutualslam_cli.pipeline.run_sequence`), beside the keys each stage writes: which sequence, scheme,
seed and device it was (:func:`record_identity`), where its wall time went (:func:`summarise_times`,
``timing.*``), ``manifest.json`` with what it keeps of the stages' outcomes (:func:`run_facts`: the device,
the sequence, the front end's metadata, BA runs, bridges, loops), and then ``summary.json``."""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import TYPE_CHECKING

from mutualslam_cli.device import device_label
from mutualslam_cli.results.run_folder import manifest, write_json
from mutualslam_cli.results.summary import RunSummary, Summary
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.types import Document

if TYPE_CHECKING:
    from mutualslam_cli.stages.adaptation import Adapted
    from mutualslam_cli.stages.ba import BAStage
    from mutualslam_cli.stages.frontend import FrontEnd

def write_record(run: RunContext, fe: FrontEnd, ba: BAStage, adapted: Adapted, command: list[str] | None,
                 t_start: float) -> tuple[RunSummary, dict[str, float]]:
    """The run's stage times and identity into its summary, ``manifest.json``, then ``summary.json`` (last:
    the run is complete). Returns ``(summary, timings)``: what ``summary.json`` holds, and the seconds per
    stage, ``load`` and ``total`` (``t_start``: :func:`time.perf_counter` when the run began)."""
    total = time.perf_counter() - t_start
    summarise_times(run.summary, run.timings, total, fe.cached)
    record_identity(run)
    timings = {**{f"{k}_s": v for k, v in run.timings.items()}, "total_s": total}
    write_json(run.folder / "manifest.json", manifest(command, run.cfg.seed, timings, run_facts(run, fe, ba, adapted)))
    summary = run.summary.to_dict()
    write_json(run.folder / "summary.json", summary)
    return RunSummary.parse(summary, str(run.folder / "summary.json")), timings


#: The stages whose wall time ``timing.stage_s`` splits a run into (``other``: everything else).
STAGES = ("frontend", "adaptation", "ba", "evaluation", "dense")


def summarise_times(summary: Summary, timings: dict[str, float], total_s: float, vo_cached: bool) -> None:
    """``timing.total_s`` and the run's wall time split by stage, ``timing.stage_s.*`` (seconds).

    ``frontend`` (VO or oracle; a cached front end costs only its loading), ``adaptation`` (online
    fine-tuning without the BA it triggered), ``ba`` (every culling + global BA: Algorithm 1's
    requests and the final one), ``evaluation`` (depth of every frame with GT by both models),
    ``dense`` (when it ran), ``other`` (the rest: loading the sequence and the network, trajectory
    and map metrics, writing files). They add up to ``total_s``. ``timing.beyond_steps``: what the run cost
    beyond its optimiser steps, as a share of them (``total_s / timing.finetune_steps_s − 1``; DESIGN §10: ≤ 0.25).
    """
    parts = {k: timings.get(k, 0.0) for k in STAGES if k != "dense" or "dense" in timings}
    parts["other"] = total_s - sum(parts.values())
    summary.set("timing.total_s", total_s)
    for k, v in parts.items():
        summary.set(f"timing.stage_s.{k}", float(v))
    steps_s = summary.number("timing.finetune_steps_s")
    summary.set("timing.beyond_steps", total_s / steps_s - 1.0 if steps_s else None,
                "no optimiser step")  # DESIGN §10: a run costs its steps + at most 25 % (≤ 0.25)
    if vo_cached:
        summary.notes["timing.stage_s.frontend"] = "front end loaded from the cache"


def record_identity(run: RunContext) -> None:
    """The run's identity in its summary: ``sequence.name``, ``sequence.frames``, ``scheme``, ``seed`` and the
    device it ran on (``run.*``; ``run.device_label`` is what reports group by, never averaging across devices)."""
    seq, cfg, summary = run.seq, run.cfg, run.summary
    summary.set("sequence.name", seq.name)
    summary.set("sequence.frames", len(seq))
    summary.set("scheme", cfg.adapt.scheme)
    summary.set("seed", cfg.seed)
    dev = run.device_info
    for key in ("device", "device_name", "device_memory_gb", "cuda_version", "cudnn_version"):
        summary.set(f"run.{key}", dev.get(key), "not a CUDA device" if key.startswith("cud") else "unknown")
    summary.set("run.device_label", device_label(dev))  # what reports group by: never averaged across devices


def run_facts(run: RunContext, fe: FrontEnd, ba: BAStage, adapted: Adapted) -> Document:
    """What ``manifest.json`` keeps of the run beyond the command, versions and timings
    (:func:`~mutualslam_cli.results.run_folder.manifest`'s ``extra``)."""
    seq = run.seq
    return {
        "device": run.device_info,
        "sequence": {"name": seq.name, "root": str(seq.root), "frames": len(seq), "meta": seq.meta,
                     "intrinsics": seq.intrinsics.as_list()},
        "vo_meta": {k: v for k, v in fe.vo.meta.items() if isinstance(v, (int, float, str, bool, dict, list))},
        "map_points_with_gt": fe.points_with_gt,
        "ba_runs": [r.to_json() for r in ba.record.runs],
        "bridges": [asdict(b) for b in adapted.bridges or []],
        "bridges_credit": [asdict(b) for b in adapted.credit],
        "bridges_refused": [asdict(b) for b in adapted.refused],
        "loops": [lp.to_json() for lp in adapted.loops],
    }

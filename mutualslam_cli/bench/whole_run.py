"""A whole default ``mslam run`` split by stage, per frame (DESIGN §10: a run costs its steps + at most 25 %).

One run of the default configuration (our VO, ``replay+ewc``, online scores) on a real window, in a
subprocess; its ``summary.json`` says where the time went. The stages (seconds, and seconds per frame of
the sequence):

- ``frontend``: the VO front end (``timing.stage_s.frontend``);
- ``steps``: the fine-tuning optimiser steps (``timing.finetune_steps_s``);
- ``consolidation``: the regulariser's end of batch, EWC's per-keyframe Fisher (``timing.finetune_consolidate_s``);
- ``adaptation_other``: the rest of the adaptation stage (Algorithm 1's validations, batch assembly, the loop);
- ``online_scoring``: each frame scored with the model of its time (``timing.online_scoring_s``);
- ``final_eval``: the evaluation stage less the online scores (both models on every frame with GT);
- ``ba``: global BA (``timing.stage_s.ba``); ``other``: loading, reports, the rest.

``total_vs_steps`` is the run's total over ``steps × median step`` (the design's ≤ 1.25).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TypedDict

from mutualslam_cli.bench import figure
from mutualslam_cli.types import JSON, Info, JSONObject

#: The stages of :func:`split_by_stage`, in the order of a run.
STAGES = ("frontend", "steps", "consolidation", "adaptation_other", "online_scoring", "final_eval", "ba", "other")


class WholeRunFigures(TypedDict):
    """:func:`whole_run_figures`'s (seconds, ms, shares; see there)."""

    frames: int
    total_s: float
    stage_s: dict[str, float]
    stage_s_per_frame: dict[str, float]
    steps: int
    median_step_ms: JSON
    total_vs_steps: float | None
    evaluation_share: float | None
    pcd_lsq_adapted: JSON


def _block(d: JSONObject, key: str) -> JSONObject:
    """The sub-mapping ``d[key]`` of a parsed summary (missing or empty: ``{}``)."""
    v = d.get(key) or {}
    if not isinstance(v, dict):
        raise TypeError(f"summary block {key!r} is not a mapping: {v!r}")
    return v


def _number(v: JSON) -> float:
    if isinstance(v, (list, dict)):
        raise TypeError(f"not a number: {v!r}")
    return float(v) if v is not None else 0.0


def split_by_stage(timing: JSONObject) -> dict[str, float]:
    """Seconds of each of :data:`STAGES` from a summary's ``timing`` block (missing parts count 0)."""
    stage = _block(timing, "stage_s")

    def get(d: JSONObject, k: str) -> float:
        return _number(d.get(k))

    steps, cons, online = get(timing, "finetune_steps_s"), get(timing, "finetune_consolidate_s"), \
        get(timing, "online_scoring_s")
    return {"frontend": get(stage, "frontend"), "steps": steps, "consolidation": cons,
            "adaptation_other": max(0.0, get(stage, "adaptation") - steps - cons), "online_scoring": online,
            "final_eval": max(0.0, get(stage, "evaluation") - online), "ba": get(stage, "ba"),
            "other": get(stage, "other")}


def whole_run_figures(summary: JSONObject, frames: int) -> WholeRunFigures:
    """The bench's figures of one run's ``summary.json`` on a sequence of ``frames`` frames.

    Returns:
        ``{"frames", "total_s", "stage_s": {stage: s}, "stage_s_per_frame": {stage: s}, "steps",
        "median_step_ms", "total_vs_steps", "evaluation_share", "pcd_lsq_adapted"}``.
    """
    timing = _block(summary, "timing")
    stages = split_by_stage(timing)
    total = _number(timing.get("total_s")) or sum(stages.values())
    steps = int(_number(_block(summary, "adaptation").get("steps")))
    step_ms = timing.get("finetune_ms")
    cost = steps * _number(step_ms) / 1000.0 if steps and step_ms else None
    pcd = _block(_block(_block(summary, "depth"), "pcd"), "lsq")
    return {"frames": frames, "total_s": total, "stage_s": stages,
            "stage_s_per_frame": {k: v / frames for k, v in stages.items()} if frames else {},
            "steps": steps, "median_step_ms": step_ms, "total_vs_steps": total / cost if cost else None,
            "evaluation_share": (stages["online_scoring"] + stages["final_eval"]) / total if total else None,
            "pcd_lsq_adapted": pcd.get("adapted")}


def bench_whole_run(seq: str = "tum_fr1_xyz", threads: int = 1, sets: list[str] | None = None) -> Info:
    """Time one default ``mslam run`` of ``seq`` (a datasets.yaml name) with ``threads`` torch threads, in a
    temporary results folder (nothing cached from before: the pre-trained evaluation and the front end's
    journal are computed too, as in a first run); :func:`whole_run_figures` of it, prefixed ``whole_run_``."""
    from mutualslam_cli.datasets.registry import load_sequence

    frames = len(load_sequence(seq))
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "mutualslam_cli.cli", "run", seq, "--out", tmp, "--set", f"threads={threads}"]
        for s in sets or []:
            cmd += ["--set", s]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        found = sorted(Path(tmp).rglob("summary.json"))
        if r.returncode != 0 or not found:
            return {"whole_run_note": f"mslam run {seq} failed: {r.stderr[-400:]}"}
        figures = whole_run_figures(json.loads(found[0].read_text()), frames)
    return {"whole_run_seq": seq, "whole_run_threads": threads, "whole_run_wall_s": wall,
            **{f"whole_run_{k}": v for k, v in figures.items()}}


def table_lines(res: Mapping[str, object]) -> list[str]:
    """Markdown lines of the whole-run figures in ``res`` (empty without them)."""
    if "whole_run_stage_s" not in res:
        return [f"\nwhole run: {res['whole_run_note']}"] if "whole_run_note" in res else []
    n, stages, total_s = figure(res, "whole_run_frames"), res["whole_run_stage_s"], figure(res, "whole_run_total_s")
    if n is None or total_s is None or not isinstance(stages, dict):
        raise TypeError("whole-run figures without their frames, total or stages")
    lines = [f"\nwhole `mslam run {res['whole_run_seq']}` (default config, {res['whole_run_threads']} thread(s), "
             f"{n} frames, CPU kind {res.get('cpu_kind', 'unknown')}): total {total_s:.1f} s = "
             f"{total_s / n:.2f} s/frame; total ÷ (steps × median step) = "
             + (f"{res['whole_run_total_vs_steps']:.2f}" if res.get("whole_run_total_vs_steps") else "—")
             + " (target ≤ 1.25)\n", "| stage | s | s/frame | share |", "|---|---|---|---|"]
    total = total_s or 1.0
    for k in STAGES:
        lines.append(f"| {k} | {stages[k]:.1f} | {stages[k] / n:.3f} | {100 * stages[k] / total:.0f} % |")
    return lines

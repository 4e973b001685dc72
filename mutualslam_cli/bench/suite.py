"""``make bench``: the speed figures of DESIGN §10, medians measured in one run.

Usage: ``mslam bench suite [--quick] [--memory] [--whole-run] [--grid | --only-grid] [--threads N]
[--out results/bench.json]`` (:func:`run_suite`; ``make bench`` is ``mslam bench suite --memory --whole-run --grid``).

Sections: synthetic rendering, loader and VO front end, depth network, global photometric BA
(:func:`mutualslam_cli.bench.ba.bench_ba`: time of 10 LM iterations on 100 keyframes × 10 000
points and the accuracy it recovers) and, with ``--memory``, peak memory of ``mslam run`` with
the BA's share of its wall time (``summary.json`` ``timing.ba_s / timing.total_s``) and, with
``--whole-run``, a whole default run on a real window split by stage, per frame, with its total over
steps × median step (:mod:`mutualslam_cli.bench.whole_run`). The CPU model
and SIMD flags the figures were measured on are recorded too.

Every figure is a median over repeats; fp32 and fast-path figures are measured side by side in
the same run so their ratio is meaningful even when the machine's speed drifts. Results go to
stdout (a Markdown table) and to a JSON file.
"""

from __future__ import annotations

import collections
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypedDict

import torch

from mutualslam_cli.adapt.depthnet import fast_path_supported
from mutualslam_cli.adapt.inference import openvino_available
from mutualslam_cli.bench import figure
from mutualslam_cli.bench.ba import BABench, bench_ba, holds_ba, report
from mutualslam_cli.bench.finetune import (
    bench_comoda_step,
    bench_finetune_step,
    bench_inference,
    bench_inference_openvino,
    bf16_depth_difference,
)
from mutualslam_cli.bench.kernels import step_kernels
from mutualslam_cli.bench.vo import bench_vo
from mutualslam_cli.bench.whole_run import bench_whole_run, table_lines
from mutualslam_cli.datasets.check import bench_loader
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.synthetic import bench_render
from mutualslam_cli.errors import MslamError
from mutualslam_cli.machine import cpu_info
from mutualslam_cli.types import Info


def reference_ms(repeats: int = 7) -> float:
    """Median time (ms) of a fixed pure-Python workload: a yardstick of the machine's speed.

    This machine's speed drifts by tens of percent over minutes (shared host); recording the
    yardstick at the start and end of a bench run lets a reader compare runs made at
    different times (a slower yardstick means every figure of that run is pessimistic).
    """
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        acc = 0
        for i in range(1_000_000):
            acc += i & 7
        times.append(1000.0 * (time.perf_counter() - t0))
    return statistics.median(times)


class RunTiming(TypedDict):
    """:func:`_ba_share`'s figures of one ``mslam run`` (seconds; ``None`` where the summary has none)."""

    total_s: float | None
    ba_s: float | None
    ba_share: float | None
    finetune_ms: float | None


def _render(quick: bool) -> Info:
    runs = [bench_render(640, 480, n=10 if quick else 30, scene=s) for s in ("room", "planar", "far")]
    return {"render_fps": statistics.median(r["fps"] for r in runs),
            "render_fps_by_scene": {s: r["fps"] for s, r in zip(("room", "planar", "far"), runs)}}


def _loader_and_vo(quick: bool) -> Info:
    try:
        seq = load_sequence("tum_fr1_xyz")
    except MslamError as e:
        return {"note": f"tum_fr1_xyz not available: {e}"}
    loads = [bench_loader(seq, n=len(seq))["fps"] for _ in range(3)]
    vo = bench_vo(seq, repeats=2 if quick else 5)
    return {"loader_fps": statistics.median(loads), "vo_fps": vo["fps"], "vo_fps_runs": vo["fps_runs"],
            "vo_ms_per_frame": vo["ms_per_frame"], "vo_keyframes": vo["keyframes"]}


def _network(quick: bool, threads: int) -> Info:
    out: Info = {"threads": threads, "bf16_supported": fast_path_supported()}
    predict: dict[str, float] = {}  # ms by path, as in out
    finetune: dict[str, float] = {}
    reps = 3 if quick else 10
    for name, fast, cl in (("fp32", False, False), ("fast", True, True)):
        if fast and not fast_path_supported():
            out["fast_note"] = "bf16 not supported on this CPU"
            continue
        out[f"predict_{name}_ms"] = predict[name] = bench_inference(640, 192, 2 * reps, fast, threads,
                                                                    channels_last=cl)["ms"]
        out[f"finetune_{name}_ms"] = finetune[name] = bench_finetune_step(640, 192, reps, fast, threads,
                                                                          channels_last=cl)["ms"]
    out["comoda_step_ms"] = bench_comoda_step(640, 192, reps, fast_path_supported(), threads)["ms"]
    if openvino_available():  # the evaluation's runtime (net.runtime auto: bf16 where the CPU has it, else fp32), int8
        for name, int8 in (("openvino", False), ("openvino_int8", True)):
            ov = bench_inference_openvino(640, 192, 2 * reps, threads, int8=int8)
            out[f"predict_{name}_ms"], out[f"{name}_convert_s"] = ov["ms"], ov["convert_s"]
            out[f"predict_{name}_speedup"] = predict["fp32"] / ov["ms"]
    if "fast" in predict:
        out["predict_speedup"] = predict["fp32"] / predict["fast"]
        out["finetune_speedup"] = finetune["fp32"] / finetune["fast"]
        out["bf16_rel_depth_diff"] = bf16_depth_difference(640, 192)
        out["step_kernels"] = step_kernels(fast=True)
    return out


def _ba(quick: bool) -> BABench:
    return bench_ba(runs=2 if quick else 5)


def _ba_share(out: Path) -> RunTiming | Info:
    """``timing.total_s``, ``timing.ba_s``, their ratio and ``timing.finetune_ms`` (the median fine-tuning
    step inside the run) from the ``summary.json`` under ``out``."""
    found = sorted(out.rglob("summary.json"))
    if not found:
        return {"note": f"no summary.json under {out}"}
    timing = json.loads(found[0].read_text()).get("timing", {})
    total, ba = timing.get("total_s"), timing.get("ba_s")
    return {"total_s": total, "ba_s": ba, "ba_share": ba / total if ba is not None and total else None,
            "finetune_ms": timing.get("finetune_ms")}


def _memory(frames: int, threads: int) -> Info:
    """Peak RSS of ``mslam run`` (oracle front end, replay+ewc) on a synthetic sequence of N and 2N frames,
    and the global BA's share of each run's wall time. The runs use the bench's ``threads`` (their median
    step is compared with the bench's step, which is only meaningful at one thread count)."""
    out: Info = {}
    peaks: dict[int, float | None] = {}  # GB by frames, as in out
    steps: list[object] = []  # the median step of each run (ms), as in out
    with tempfile.TemporaryDirectory() as tmp:
        for n in (frames, 2 * frames):
            seq = Path(tmp) / f"room{n}"
            subprocess.run([sys.executable, "-m", "mutualslam_cli.cli", "synth", str(seq), "--frames", str(n)],
                           check=True, capture_output=True)
            code = ("import resource, sys; from mutualslam_cli.cli import app\n"
                    "try:\n    app(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
                    "print('PEAK', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-c", code, "run", str(seq), "--vo", "gt-depth", "--out",
                                str(Path(tmp) / f"res{n}"), "--force", "--set", f"threads={threads}"],
                               capture_output=True, text=True)
            peak_kb = int(r.stdout.rsplit("PEAK", 1)[1].split()[0]) if "PEAK" in r.stdout else None
            out[f"peak_rss_gb_{n}_frames"] = peaks[n] = peak_kb / 1024**2 if peak_kb else None
            out[f"run_s_{n}_frames"] = time.perf_counter() - t0
            out[f"run_timing_{n}_frames"] = timing = _ba_share(Path(tmp) / f"res{n}")
            steps.append(timing.get("finetune_ms"))
    a, b = peaks[frames], peaks[2 * frames]
    if a and b:
        out["peak_rss_gb"] = max(a, b)
        out["peak_rss_ratio_2x"] = b / a
    step_ms = [ms for ms in steps if ms and isinstance(ms, (int, float))]
    if len(step_ms) == len(steps):
        out["finetune_run_ms"] = statistics.median(step_ms)
    return out


def step_in_run(res: Mapping[str, object]) -> dict[str, float]:
    """The run's median step over the bench's step of the same path (fast where the CPU has it, as the run)."""
    bench = figure(res, "finetune_fast_ms") or figure(res, "finetune_fp32_ms")
    run = figure(res, "finetune_run_ms")
    return {"finetune_run_vs_bench": run / bench} if bench and run else {}


#: The grid of the scaling benchmark: 4 jobs (schemes) on one synthetic sequence, a smaller network
#: than the paper's so that each job takes ~15 s (96 frames: the fixed costs of a pool — worker start,
#: the front end — are a small part), the depth oracle front end (shared by all jobs).
GRID_SETS = ["vo.mode=gt-depth", "net.width=320", "net.height=96", "adapt.steps_per_keyframe=4", "ba.enabled=false"]
GRID_SCHEMES = "recent,replay,replay+ewc,replay+mas"


def _grid(frames: int = 96) -> Info:
    """Wall time of ``mslam ablate`` on a 4-job grid with 1 worker (all cores), 1 worker with one
    thread, and 2 workers (one thread each); speed-ups of 2 workers over each."""
    out: Info = {}
    wall: dict[str, float] = {}  # s by grid, as in out
    with tempfile.TemporaryDirectory() as tmp:
        seq = Path(tmp) / "room"
        subprocess.run([sys.executable, "-m", "mutualslam_cli.cli", "synth", str(seq), "--frames", str(frames),
                        "--size", "320x240"], check=True, capture_output=True)
        for name, workers, extra in (("1w", 1, []), ("1w1t", 1, ["--set", "threads=1"]), ("2w", 2, [])):
            cmd = [sys.executable, "-m", "mutualslam_cli.cli", "ablate", str(seq), "--schemes", GRID_SCHEMES,
                   "-j", str(workers), "--out", str(Path(tmp) / name), *extra]
            for s in GRID_SETS:
                cmd += ["--set", s]
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True)
            out[f"grid_{name}_s"] = wall[name] = time.perf_counter() - t0
            if r.returncode != 0:
                out[f"grid_{name}_error"] = r.stderr[-500:]
    if "2w" in wall:
        out["grid_speedup_2w_vs_1w"] = wall["1w"] / wall["2w"]
        out["grid_speedup_2w_vs_1w1t"] = wall["1w1t"] / wall["2w"]
    return out


#: DESIGN §10's targets that hold on every CPU kind: result key → (comparison, value).
TARGETS: dict[str, tuple[str, float]] = {
    "render_fps": (">=", 30.0), "vo_fps": (">=", 60.0), "peak_rss_gb": ("<=", 3.0), "ba_s": ("<=", 5.0),
    "predict_openvino_speedup": (">=", 2.5), "predict_openvino_int8_speedup": (">=", 2.5),
    "grid_speedup_2w_vs_1w": (">=", 1.8), "finetune_run_vs_bench": ("<=", 1.1),
}
#: The targets that depend on the CPU kind (:func:`mutualslam_cli.machine.cpu_kind`): prediction ms as
#: ``mslam run`` does it, one fine-tuning step ms and its speed-up over fp32 (AVX2: measured, no target).
KIND_TARGETS: dict[str, dict[str, tuple[str, float]]] = {
    "AMX": {"predict_ms": ("<=", 15.0), "finetune_ms": ("<=", 250.0), "finetune_speedup": (">=", 2.0),
            "finetune_run_ms": ("<=", 250.0)},
    "AVX512-BF16": {"predict_ms": ("<=", 40.0), "finetune_ms": ("<=", 300.0), "finetune_speedup": (">=", 2.0),
                    "finetune_run_ms": ("<=", 300.0)},
    "AVX2": {"predict_ms": ("<=", 60.0)},
}
#: Rows of the table: (label, result key, target key).
ROWS = (
    ("synthetic rendering 640×480 (frames/s)", "render_fps", "render_fps"),
    ("loader read+decode tum_fr1_xyz (frames/s)", "loader_fps", None),
    ("VO front end tum_fr1_xyz, decode included (frames/s)", "vo_fps", "vo_fps"),
    ("depth prediction 640×192 fp32 (ms)", "predict_fp32_ms", None),
    ("depth prediction 640×192 fast path (ms)", "predict_fast_ms", None),
    ("fine-tuning step fp32 (ms)", "finetune_fp32_ms", None),
    ("fine-tuning step fast path (ms)", "finetune_fast_ms", "finetune_ms"),
    ("prediction speed-up fast/fp32 (×)", "predict_speedup", None),
    ("depth prediction, evaluation runtime OpenVINO, bf16 or fp32 (ms)", "predict_openvino_ms", "predict_ms"),
    ("prediction speed-up OpenVINO/fp32 (×)", "predict_openvino_speedup", "predict_openvino_speedup"),
    ("depth prediction, OpenVINO int8, only when asked (ms)", "predict_openvino_int8_ms", None),
    ("prediction speed-up OpenVINO int8/fp32 (×)", "predict_openvino_int8_speedup", "predict_openvino_int8_speedup"),
    ("fine-tuning speed-up fast/fp32 (×)", "finetune_speedup", "finetune_speedup"),
    ("fine-tuning step inside mslam run, replay+ewc, median (ms)", "finetune_run_ms", "finetune_run_ms"),
    ("step inside the run / step on the bench (×)", "finetune_run_vs_bench", "finetune_run_vs_bench"),
    ("CoMoDa-style update step, current + 3 replayed triplets (ms)", "comoda_step_ms", None),
    ("peak memory of mslam run (GB)", "peak_rss_gb", "peak_rss_gb"),
    ("peak memory, 2× frames / 1× frames", "peak_rss_ratio_2x", None),
    ("global BA, 100 keyframes × 10k points, 10 iterations (s)", "ba_s", "ba_s"),
    ("grid of 4 jobs, 1 worker with all cores (s)", "grid_1w_s", None),
    ("grid of 4 jobs, 1 worker with 1 thread (s)", "grid_1w1t_s", None),
    ("grid of 4 jobs, 2 workers with 1 thread each (s)", "grid_2w_s", None),
    ("grid speed-up, 2 workers / 1 worker with all cores (×)", "grid_speedup_2w_vs_1w", "grid_speedup_2w_vs_1w"),
    ("grid speed-up, 2 workers / 1 worker with 1 thread (×)", "grid_speedup_2w_vs_1w1t", None),
)


def targets(kind: str) -> dict[str, tuple[str, float]]:
    """The targets of a CPU kind: :data:`TARGETS` and that kind's :data:`KIND_TARGETS`."""
    return {**TARGETS, **KIND_TARGETS.get(kind, {})}


def _target_text(target: tuple[str, float] | None, value: float) -> tuple[str, str]:
    if target is None:
        return "—", ""
    op, bound = target
    met = value >= bound if op == ">=" else value <= bound
    return f"{'≥' if op == '>=' else '≤'} {bound:g}", "yes" if met else "**no**"


def _table(res: Info) -> str:
    kind = str(res.get("cpu_kind", "unknown"))
    goal = targets(kind)
    lines = [f"targets for CPU kind {kind} (DESIGN §10)\n", "| what | median | target | met |", "|---|---|---|---|"]
    for what, key, target_key in ROWS:
        v = figure(res, key)
        if v is not None:
            text, met = _target_text(goal.get(target_key) if target_key else None, v)
            lines.append(f"| {what} | {v:.3g} | {text} | {met} |")
    if "reference_ms_start" in res:
        lines.append("\nmachine yardstick (fixed Python loop, ms; lower = faster): "
                     f"{res['reference_ms_start']:.0f} at the "
                     f"start, {res.get('reference_ms_end', float('nan')):.0f} at the end")
    if holds_ba(res):
        p = res["ba_problem"]
        runs = ", ".join(f"{t:.2f}" for t in res["ba_s_runs"])
        lines.append(f"\nglobal BA problem: {p['keyframes']} keyframes {p['image']}, {p['points']} points, "
                     f"{p['observations']} observations; keyframes {p['spacing_cm_median']:.1f} cm apart, "
                     f"baseline median {p['baseline_cm_median']:.1f} cm, parallax median "
                     f"{p['parallax_px_median']:.0f} px; start {p['perturbation']}; runs (s): {runs}\n")
        lines.append(report(res))
    timings = {int(k.split("_")[2]): v for k, v in res.items() if k.startswith("run_timing_") and isinstance(v, dict)}
    for n, t in sorted(timings.items()):
        if t.get("ba_share") is not None:
            lines.append(f"\nmslam run ({n} frames, --vo gt-depth): total {t['total_s']:.1f} s, "
                         f"global BA {t['ba_s']:.1f} s ({100 * t['ba_share']:.0f} %)")
    flags = res.get("cpu_flags")
    if isinstance(flags, list):
        lines.append(f"\nCPU: {res['cpu_model']} ({kind}), {res['cpu_count']} cores; SIMD flags: "
                     f"{' '.join(flags)}")
    k = res.get("step_kernels")
    if isinstance(k, dict) and k.get("convolutions"):
        isa: collections.Counter[str] = collections.Counter()
        for name, n in k["convolutions"].items():
            isa[name.split(":")[-1]] += n
        lines.append("\noneDNN kernels of one fast-path step: convolutions by ISA "
                     f"{', '.join(f'{i} ×{n}' for i, n in isa.most_common())}; by data type "
                     f"{', '.join(f'{d} ×{n}' for d, n in k['convolution_dtypes'].items())} (f32: the loss's box "
                     f"filter); reorders {k['reorder_ms']:.0f} ms beside {k['convolution_ms']:.0f} ms of convolutions")
    lines += table_lines(res)
    vo_ms = res.get("vo_ms_per_frame")
    if isinstance(vo_ms, dict):
        stages = ", ".join(f"{k} {v:.2f}" for k, v in vo_ms.items())
        lines.append(f"\nVO per-stage ms/frame: {stages}")
    return "\n".join(lines)


def run_suite(quick: bool = False, memory: bool = False, grid: bool = False, only_grid: bool = False,
              whole_run: bool = False, threads: int | None = None,
              out: Path | str = Path("results/bench.json")) -> Info:
    """The whole suite: each section's figures, its table's last line to stderr as it completes, then the
    Markdown table to stdout and every figure to ``out`` (JSON).

    Args:
        quick: fewer repeats.
        memory: also the peak memory (GB) of ``mslam run`` on 60 and 120 synthetic frames and the BA's share
            of its wall time (minutes).
        grid: also the wall time (s) of a 4-job grid with 1 and 2 workers (minutes).
        only_grid: only the grid timing (no other section).
        whole_run: also a whole default ``mslam run tum_fr1_xyz``, split by stage per frame (minutes).
        threads: torch threads for the network (``None``: ``os.cpu_count()``).
        out: the JSON file written (its folder is made).

    Returns:
        Every figure: result key → value (ms, s, frames/s, GB or ×, as the key says), the machine's
        :func:`~mutualslam_cli.machine.cpu_info` and the yardstick (:func:`reference_ms`) at start and end.
    """
    threads = threads if threads is not None else os.cpu_count() or 1
    torch.set_num_threads(threads)
    res: Info = {**cpu_info(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                           "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "reference_ms_start": reference_ms()}
    parts: list[Callable[[], Mapping[str, object]]] = [] if only_grid else [
        lambda: _render(quick), lambda: _loader_and_vo(quick), lambda: _network(quick, threads), lambda: _ba(quick)]
    for part in parts + ([_grid] if grid or only_grid else []):
        res.update(part())
        print(_table(res).splitlines()[-1], file=sys.stderr, flush=True)
    if whole_run:
        res.update(bench_whole_run("tum_fr1_xyz", threads))
    if memory:
        res.update(_memory(60, threads))
        res.update(step_in_run(res))
    res["self_peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    res["reference_ms_end"] = reference_ms()
    print(_table(res))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(res, indent=2, default=str) + "\n")
    print(f"\nwritten to {out}")
    return res

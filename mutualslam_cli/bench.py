"""``make bench``: the speed figures of DESIGN §10, medians measured in one run.

Usage: ``python -m mutualslam_cli.bench [--quick] [--memory] [--out results/bench.json]``.

Every figure is a median over repeats; fp32 and fast-path figures are measured side by side in
the same run so their ratio is meaningful even when the machine's speed drifts. Results go to
stdout (a Markdown table) and to a JSON file.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TARGETS = {
    "render_fps": 30.0, "vo_fps": 60.0, "predict_ms": 40.0, "finetune_ms": 400.0, "peak_rss_gb": 3.0,
}


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


def _render(quick: bool) -> dict[str, Any]:
    from mutualslam_cli.datasets.synthetic import bench_render

    runs = [bench_render(640, 480, n=10 if quick else 30, scene=s) for s in ("room", "planar", "far")]
    return {"render_fps": statistics.median(r["fps"] for r in runs),
            "render_fps_by_scene": {s: r["fps"] for s, r in zip(("room", "planar", "far"), runs)}}


def _loader_and_vo(quick: bool) -> dict[str, Any]:
    from mutualslam_cli.datasets.check import bench_loader
    from mutualslam_cli.datasets.registry import load_sequence
    from mutualslam_cli.errors import MslamError
    from mutualslam_cli.vo_bench import bench_vo

    try:
        seq = load_sequence("tum_fr1_xyz")
    except MslamError as e:
        return {"note": f"tum_fr1_xyz not available: {e}"}
    loads = [bench_loader(seq, n=len(seq))["fps"] for _ in range(3)]
    vo = bench_vo(seq, repeats=2 if quick else 5)
    return {"loader_fps": statistics.median(loads), "vo_fps": vo["fps"], "vo_fps_runs": vo["fps_runs"],
            "vo_ms_per_frame": vo["ms_per_frame"], "vo_keyframes": vo["keyframes"]}


def _network(quick: bool, threads: int) -> dict[str, Any]:
    from mutualslam_cli.adapt.bench import bench_finetune_step, bench_inference, bf16_depth_difference
    from mutualslam_cli.adapt.depthnet import fast_path_supported

    out: dict[str, Any] = {"threads": threads, "bf16_supported": fast_path_supported()}
    reps = 3 if quick else 10
    for name, fast, cl in (("fp32", False, False), ("fast", True, True)):
        if fast and not fast_path_supported():
            out["fast_note"] = "bf16 not supported on this CPU"
            continue
        out[f"predict_{name}_ms"] = bench_inference(640, 192, 2 * reps, fast, threads, channels_last=cl)["ms"]
        out[f"finetune_{name}_ms"] = bench_finetune_step(640, 192, reps, fast, threads, channels_last=cl)["ms"]
    if "predict_fast_ms" in out:
        out["predict_speedup"] = out["predict_fp32_ms"] / out["predict_fast_ms"]
        out["finetune_speedup"] = out["finetune_fp32_ms"] / out["finetune_fast_ms"]
        out["bf16_rel_depth_diff"] = bf16_depth_difference(640, 192)
    return out


def _memory(frames: int) -> dict[str, Any]:
    """Peak RSS of ``mslam run`` (oracle front end, replay+ewc) on a synthetic sequence of N and 2N frames."""
    out: dict[str, Any] = {}
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
                                str(Path(tmp) / "res"), "--force"], capture_output=True, text=True)
            peak_kb = int(r.stdout.rsplit("PEAK", 1)[1].split()[0]) if "PEAK" in r.stdout else None
            out[f"peak_rss_gb_{n}_frames"] = peak_kb / 1024**2 if peak_kb else None
            out[f"run_s_{n}_frames"] = time.perf_counter() - t0
    a, b = out.get(f"peak_rss_gb_{frames}_frames"), out.get(f"peak_rss_gb_{2 * frames}_frames")
    if a and b:
        out["peak_rss_gb"] = max(a, b)
        out["peak_rss_ratio_2x"] = b / a
    return out


def _table(res: dict[str, Any]) -> str:
    rows = [
        ("synthetic rendering 640×480 (frames/s)", res.get("render_fps"), "≥ 30"),
        ("loader read+decode tum_fr1_xyz (frames/s)", res.get("loader_fps"), "—"),
        ("VO front end tum_fr1_xyz, decode included (frames/s)", res.get("vo_fps"), "≥ 60"),
        ("depth prediction 640×192 fp32 (ms)", res.get("predict_fp32_ms"), "—"),
        ("depth prediction 640×192 fast path (ms)", res.get("predict_fast_ms"), "≤ 40"),
        ("fine-tuning step fp32 (ms)", res.get("finetune_fp32_ms"), "—"),
        ("fine-tuning step fast path (ms)", res.get("finetune_fast_ms"), "≤ 400"),
        ("prediction speed-up fast/fp32 (×)", res.get("predict_speedup"), "—"),
        ("fine-tuning speed-up fast/fp32 (×)", res.get("finetune_speedup"), "—"),
        ("peak memory of mslam run (GB)", res.get("peak_rss_gb"), "≤ 3"),
        ("peak memory, 2× frames / 1× frames", res.get("peak_rss_ratio_2x"), "≈ 1"),
    ]
    lines = ["| what | median | target |", "|---|---|---|"]
    for what, v, tgt in rows:
        if v is not None:
            lines.append(f"| {what} | {v:.3g} | {tgt} |")
    if "reference_ms_start" in res:
        lines.append("\nmachine yardstick (fixed Python loop, ms; lower = faster): "
                     f"{res['reference_ms_start']:.0f} at the "
                     f"start, {res.get('reference_ms_end', float('nan')):.0f} at the end")
    if "vo_ms_per_frame" in res:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in res["vo_ms_per_frame"].items())
        lines.append(f"\nVO per-stage ms/frame: {stages}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--memory", action="store_true", help="also measure peak memory of `mslam run` (minutes)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads for the network")
    ap.add_argument("--out", default="results/bench.json")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    res: dict[str, Any] = {"cpu_count": os.cpu_count(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                           "reference_ms_start": reference_ms()}
    for part in (lambda: _render(a.quick), lambda: _loader_and_vo(a.quick), lambda: _network(a.quick, a.threads)):
        res.update(part())
        print(_table(res).splitlines()[-1], file=sys.stderr, flush=True)
    if a.memory:
        res.update(_memory(60))
    res["self_peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    res["reference_ms_end"] = reference_ms()
    print(_table(res))
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=2, default=str) + "\n")
    print(f"\nwritten to {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

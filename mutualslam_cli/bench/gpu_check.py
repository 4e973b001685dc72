"""``make gpu-check``: the CUDA path on a machine with an NVIDIA GPU, checked against the CPU (DESIGN §10).

Usage: ``mslam bench gpu-check [--sequence tum_fr1_xyz] [--out DIR] [--skip-cpu]`` (:func:`gpu_check`).

Without CUDA it says why and exits 0 (CI and CPU-only machines). With it, in about five minutes:

1. the fine-tuning step and the depth prediction at 640×192 on the GPU (the bench's, medians), against
   DESIGN §10's targets (step ≤ 25 ms, prediction ≤ 5 ms on one H100-class GPU);
2. one shared 100-frame window end to end (``configs/paper.yaml``, replay+ewc, our VO) with ``device=cuda``
   and with ``device=cpu`` (each its own front end, no shared cache); it checks that the two agree — the
   keyframes (their timestamps) and PCD (lsq, final model) within 1 point — and prints each run's total
   time, in-run step and prediction times. Exit status 1 when a check fails.

A whole 900-frame sequence in ≤ 90 s (the third target) needs a longer sequence than the shared windows:
``mslam run SEQ --device cuda`` on one prints its stage table.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Literal, TypedDict

import torch

from mutualslam_cli.adapt.inputs import use_fast_path
from mutualslam_cli.bench import figure
from mutualslam_cli.bench.finetune import bench_finetune_step, bench_inference
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.device import describe_device, resolve_device
from mutualslam_cli.errors import MslamError
from mutualslam_cli.pipeline import run_sequence

#: DESIGN §10 on one H100-class GPU: bench key → (limit in ms, what).
GPU_TARGETS: dict[Literal["step_ms", "predict_ms"], tuple[float, str]] = {
    "step_ms": (25.0, "fine-tuning step"), "predict_ms": (5.0, "depth prediction")}
#: The CUDA run may differ from the CPU run by this much PCD (points, lsq, final model).
PCD_TOLERANCE = 1.0


def no_cuda_reason() -> str | None:
    """Why this machine cannot run the check (``None``: it can)."""
    if torch.cuda.is_available():
        return None
    if torch.version.cuda is None:
        return (f"torch {torch.__version__} is the CPU build (README: install the CUDA build of the same version "
                "to use a GPU)")
    return f"torch {torch.__version__} (CUDA {torch.version.cuda}) sees no usable GPU or driver"


class GpuBench(TypedDict):
    """:func:`bench_gpu`'s medians (ms) and whether they ran in mixed precision."""

    step_ms: float
    predict_ms: float
    mixed_precision: bool


class Window(TypedDict):
    """:func:`run_window`'s: the run's flat summary (``a.b.c`` → value), its keyframe timestamps and wall time (s)."""

    summary: Mapping[str, object]
    keyframes: list[str]
    wall_s: float


def bench_gpu(device: torch.device, repeats: int = 20) -> GpuBench:
    """Median fine-tuning step and prediction on ``device`` in the precision a run would use there."""
    fast = use_fast_path(load_config().net, device)
    step = bench_finetune_step(640, 192, repeats, fast, warmup=5, device=device)["ms"]
    predict = bench_inference(640, 192, 2 * repeats, fast, warmup=5, device=device)["ms"]
    return {"step_ms": step, "predict_ms": predict, "mixed_precision": fast}


def run_window(sequence: str, spec: str, out: Path, config: Path = CONFIG_DIR / "paper.yaml",
               sets: list[str] | None = None) -> Window:
    """One window end to end on ``spec``; its flat summary, its keyframes (timestamps) and wall time."""
    cfg = load_config(config, [*(sets or []), f"device={spec}"])
    t0 = time.perf_counter()
    r = run_sequence(sequence, cfg, out=out, force=True, command=["gpu-check", spec])
    wall = time.perf_counter() - t0
    lines = (r.folder / "traj_kf.txt").read_text().splitlines()
    kf = [line.split()[0] for line in lines if line.strip() and not line.startswith("#")]  # their timestamps
    return {"summary": r.summary.flat(), "keyframes": kf, "wall_s": wall}


def compare(gpu: Window, cpu: Window) -> list[tuple[str, bool, str]]:
    """The checks of the CUDA run against the CPU run: ``(what, passed, detail)``."""
    pg, pc = figure(gpu["summary"], "depth.pcd.lsq.adapted"), figure(cpu["summary"], "depth.pcd.lsq.adapted")
    same_pcd = pg is not None and pc is not None and abs(pg - pc) <= PCD_TOLERANCE
    return [("same keyframes", gpu["keyframes"] == cpu["keyframes"],
             f"{len(gpu['keyframes'])} on cuda, {len(cpu['keyframes'])} on cpu"),
            (f"PCD lsq within {PCD_TOLERANCE:g} point", same_pcd, f"cuda {pg}, cpu {pc}")]


def _fmt(v: object, nd: int = 1) -> str:
    return "—" if v is None else f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def gpu_check(sequence: str = "tum_fr1_xyz", out: Path | str | None = None, skip_cpu: bool = False,
              device: str = "cuda", config: Path = CONFIG_DIR / "paper.yaml", sets: Iterable[str] = ()) -> int:
    """The check of the module docstring, printed to stdout; the exit status: 0 when every check passes or
    there is no CUDA (it says why), 1 when a check fails or the window cannot run.

    Args:
        sequence: a shared window of 100 frames (datasets.yaml name or sequence folder).
        out: results folder (``None``: a temporary one).
        skip_cpu: only the GPU side (no comparison).
        device: the GPU side's device (tests run it with ``cpu``).
        config: the run config of both windows.
        sets: ``key=value`` overrides of ``config``.
    """
    reason = no_cuda_reason()
    if reason is not None:
        print(f"gpu-check: skipped, no CUDA device: {reason}")
        return 0
    dev = resolve_device(device)
    info = describe_device(dev)
    print(f"gpu-check on {info['device_name']} ({info['device_memory_gb']} GiB, CUDA {info['cuda_version']}, "
          f"cuDNN {info['cudnn_version']}, compute capability {info.get('compute_capability')})")
    bench = bench_gpu(dev)
    ok = True
    for key, (limit, what) in GPU_TARGETS.items():
        passed = bench[key] <= limit
        print(f"  {what}: {bench[key]:.1f} ms (target ≤ {limit:g} ms, mixed precision {bench['mixed_precision']})"
              f" {'ok' if passed else 'ABOVE TARGET'}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(out or tmp)
        try:
            runs = {"cuda": run_window(sequence, device, folder / "cuda", config, list(sets))}
            if not skip_cpu:
                runs["cpu"] = run_window(sequence, "cpu", folder / "cpu", config, list(sets))
        except MslamError as e:
            print(f"gpu-check: the {sequence} window could not run: {e}")
            return 1
    print(f"\n{sequence}, configs/paper.yaml, replay+ewc:")
    print(f"  {'device':<6} {'total s':>8} {'step ms':>8} {'predict ms':>10} {'PCD lsq':>8} {'keyframes':>9}")
    for name, r in runs.items():
        f = r["summary"]
        print(f"  {name:<6} {_fmt(f.get('timing.total_s')):>8} {_fmt(f.get('timing.finetune_ms')):>8} "
              f"{_fmt(f.get('timing.depth_ms')):>10} {_fmt(f.get('depth.pcd.lsq.adapted'), 2):>8} "
              f"{len(r['keyframes']):>9}")
    if "cpu" in runs:
        for what, passed, detail in compare(runs["cuda"], runs["cpu"]):
            ok &= passed
            print(f"  {what}: {'ok' if passed else 'FAILED'} ({detail})")
    print(json.dumps({"bench": bench, **{f"{k}_total_s": r["summary"].get("timing.total_s") for k, r in runs.items()}}))
    return 0 if ok else 1


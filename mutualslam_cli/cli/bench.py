"""``mslam bench``: the benchmarks of :mod:`mutualslam_cli.bench` — the ``make bench`` suite, the global BA, the
CUDA check, the regulariser calibration, the VO table and the fine-tuning micro-benchmark.

Each command is a thin layer over one library function (imported inside the command, so ``mslam --help`` stays
instant); the library prints its own tables and figures to stdout (progress lines of the suite to stderr).
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import SetOpt, app
from mutualslam_cli.config import CONFIG_DIR

bench_app = typer.Typer(cls=common.Commands, no_args_is_help=True,
                        help="Benchmarks: the speed figures (make bench; docs/devices.md), the global BA, the CUDA "
                             "path against the CPU (make gpu-check), the regulariser calibration, the VO table.")
app.add_typer(bench_app, name="bench")


@bench_app.command()
def suite(
    quick: bool = typer.Option(False, "--quick", help="Fewer repeats."),
    memory: bool = typer.Option(False, "--memory", help="Also measure peak memory of `mslam run` (minutes)."),
    grid: bool = typer.Option(False, "--grid", help="Also time a 4-job grid with 1 and 2 workers (minutes)."),
    only_grid: bool = typer.Option(False, "--only-grid", help="Only the grid timing."),
    whole_run: bool = typer.Option(False, "--whole-run", help="Also time a whole default `mslam run tum_fr1_xyz`, "
                                                              "split by stage (minutes)."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="Torch threads for the network "
                                                                       "(default: every core)."),
    out: Path = typer.Option(Path("results/bench.json"), "--out", help="The JSON file of every figure."),
) -> None:
    """The make bench suite: the speed figures (docs/devices.md; medians measured in one run) against their
    targets, as a Markdown table on stdout and every figure in a JSON file.

    Sections: synthetic rendering, loader and VO front end, depth network, global photometric BA; with --memory,
    --whole-run and --grid the minutes-long ones too."""
    from mutualslam_cli.bench.suite import run_suite

    run_suite(quick=quick, memory=memory, grid=grid, only_grid=only_grid, whole_run=whole_run, threads=threads,
              out=out)


@bench_app.command()
def ba(
    iterations: int = typer.Option(10, "--iterations", min=0, help="Full-resolution LM iterations."),
    runs: int = typer.Option(3, "--runs", min=1, help="Timed solves (the median is reported)."),
    levels: int = typer.Option(1, "--levels", min=1, help="Pyramid levels (1: full resolution)."),
    coarse_iterations: int = typer.Option(5, "--coarse-iterations", min=0, help="LM iterations per coarser level."),
) -> None:
    """The global photometric BA on 100 synthetic keyframes × 10 000 points: median time and the accuracy it
    recovers, before and after."""
    from mutualslam_cli.bench.ba import ba_bench

    ba_bench(iterations=iterations, runs=runs, levels=levels, coarse_iterations=coarse_iterations)


@bench_app.command("gpu-check")
def gpu_check(
    sequence: str = typer.Option("tum_fr1_xyz", "--sequence", help="A shared window of 100 frames (datasets.yaml "
                                                                   "name or sequence folder)."),
    out: Path | None = typer.Option(None, "--out", help="Results folder (default: a temporary one)."),
    skip_cpu: bool = typer.Option(False, "--skip-cpu", help="Only the GPU side (no comparison)."),
    device: str = typer.Option("cuda", "--device", help="The GPU side's device (tests run it with cpu)."),
    config: Path = typer.Option(CONFIG_DIR / "paper.yaml", "--config", "-c", show_default="configs/paper.yaml",
                                help="YAML config of both windows."),
    sets: list[str] | None = SetOpt,
) -> None:
    """The CUDA path against the CPU (make gpu-check): step and prediction times on the GPU against their
    targets, then one window on cuda and on cpu with the same keyframes and PCD within 1 point.

    Without CUDA it says why and exits 0; exit status 1 when a check fails or the window cannot run."""
    from mutualslam_cli.bench.gpu_check import gpu_check as check

    raise typer.Exit(check(sequence=sequence, out=out, skip_cpu=skip_cpu, device=device, config=config,
                           sets=sets or ()))


@bench_app.command()
def strength(
    out: Path = typer.Option(Path("results/strength"), "--out", help="Folder of the runs and strength.json."),
    sequence: Path | None = typer.Option(None, "--sequence", help="Sequence folder (default: a rendered "
                                                                  "synthetic room under --out)."),
    frames: int = typer.Option(200, "--frames", min=1, help="Frames of the rendered room."),
    seed: int = typer.Option(3, "--seed", help="Rendering seed of the room."),
) -> None:
    """Calibrate the MAS and SI coefficients to the paper's EWC strength (the same mean shrink), one mslam run
    per step; writes strength.json with the chosen coefficients."""
    from mutualslam_cli.bench.strength import run_strength

    run_strength(out=out, sequence=sequence, frames=frames, seed=seed)


@bench_app.command()
def vo(
    names: list[str] | None = typer.Argument(None, help="datasets.yaml names or sequence folders (default "
                                                        "tum_fr1_xyz icl_lr_kt2 redkitchen_7scenes)."),
) -> None:
    """The VO front end's accuracy and speed table (Markdown): tracked %, keyframes, map points, ATE, the map's
    e_si and frames/s per sequence."""
    from mutualslam_cli.bench.vo import vo_table

    vo_table(names or ())


@bench_app.command()
def contention(
    threads: int = typer.Option(0, "--threads", min=0, help="Torch threads (0: every core)."),
) -> None:
    """The fine-tuning step alone and beside one busy process (ms), as JSON: a ratio far above 'fair' is the
    OpenMP spin stall back (docs/devices.md)."""
    from mutualslam_cli.bench.contention import contention as measure

    print(json.dumps(measure(threads or None), indent=1))


@bench_app.command()
def finetune(
    threads: int = typer.Option(1, "--threads", min=1, help="Torch threads."),
) -> None:
    """The depth network's prediction and fine-tuning step at 640×192: fp32, fp32 channels-last and the fast
    path side by side (ms), and the bf16 depth difference, as JSON."""
    from mutualslam_cli.bench.finetune import compare

    print(json.dumps(compare(threads=threads), indent=1))

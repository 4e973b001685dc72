"""``mslam ablate`` and ``mslam report``: the grid of runs and the paper's tables from it."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape
from rich.table import Table

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import (
    ConfigOpt,
    DataRootOpt,
    DeviceOpt,
    RegistryOpt,
    ResultsOutOpt,
    SetOpt,
    app,
    config_from,
    progress_bar,
)
from mutualslam_cli.results.writable import check_output_folder, write_errors

if TYPE_CHECKING:
    from mutualslam_cli.ablate import JobOutcome

# --------------------------------------------------------------------------- ablate


@app.command()
def ablate(
    seqs: list[str] = typer.Argument(..., help="datasets.yaml names or sequence folders."),
    schemes: str | None = typer.Option(None, "--schemes",
                                          help="Comma-separated scheme names (default: the config's "
                                               "experiment.schemes, else none,recent,replay,replay+ewc,"
                                               "replay+mas,replay+si)."),
    seeds: str | None = typer.Option(None, "--seeds", help="Comma-separated seeds, or a range like 0-2 "
                                                              "(default: the config's experiment.seeds, else 0)."),
    workers: int = typer.Option(1, "--workers", "-j", min=1,
                                help="Worker processes (local pool, or LocalCluster workers with --executor dask)."),
    executor: str = typer.Option("local", "--executor", help="local (process pool) or dask."),
    scheduler: str | None = typer.Option(None, "--scheduler",
                                            help="Dask scheduler address, e.g. tcp://host:8786 "
                                                 "(default: a LocalCluster of --workers processes)."),
    out: Path | None = ResultsOutOpt,
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
    data_root: str | None = DataRootOpt,
    registry: Path | None = RegistryOpt,
    device: str | None = DeviceOpt,
) -> None:
    """The grid sequences × schemes × seeds (× the config's experiment.variants); complete runs are
    skipped, so a killed grid resumes.

    With --executor dask the front ends and jobs run on a Dask cluster; the sequences, the results
    folder (with its _cache/) and the weights must then be on a filesystem every worker sees."""
    from mutualslam_cli.ablate import run_grid
    from mutualslam_cli.grid_plan import plan_grid

    cfg = config_from(config, sets, data_root, device)
    root = Path(out or cfg.out)
    parts = plan_grid(cfg, list(seqs), schemes, seeds, root)
    check_output_folder(root)  # a file, read-only: one line, before the bar
    total = sum(len(p.jobs) for p in parts)
    failed, outcomes = [], []
    with progress_bar() as p:
        task = p.add_task("grid", total=total, info="")

        def done(o: JobOutcome) -> None:
            if o.status == "failed":
                failed.append(o)
            p.update(task, advance=1, info=f"{o.job.sequence} {o.job.scheme} seed{o.job.seed}: {o.status}")

        try:
            for part in parts:
                outcomes += run_grid(part.cfg, part.jobs, part.out, workers=workers, command=sys.argv,
                                     registry=registry, on_done=done, executor=executor, scheduler=scheduler)
        except KeyboardInterrupt:
            p.stop()
            n_done = int(p.tasks[task].completed)
            common.err_console.print(f"[yellow]interrupted[/]: {n_done} of {total} jobs complete, workers stopped; "
                              "run the same command again to resume (complete runs are skipped, "
                              "half-written ones redone).")
            raise typer.Exit(130) from None
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    common.console.print(f"{total} jobs: {counts['done']} done, {counts['skipped']} already complete, "
                  f"{counts['failed']} failed")
    for o in failed:
        common.err_console.print(f"[red]failed[/] {o.job.sequence} {o.job.scheme} seed{o.job.seed}: "
                          f"{(o.error or '').splitlines()[0]}")
    if failed:
        raise typer.Exit(1)


# --------------------------------------------------------------------------- report


@app.command()
def report(
    results: list[Path] = typer.Argument(..., help="Result folders (searched recursively for summary.json)."),
    out: Path | None = typer.Option(None, "--out",
                                       help="Folder for tables and plots (default <config out>/report)."),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
    pair: list[str] | None = typer.Option(None, "--pair",
                                             help="A paired comparison 'A vs B' (repeatable): each side a scheme, "
                                                  "key=value config selectors (comma-separated) and/or @KEY, e.g. "
                                                  "'replay+ewc vs replay', 'ba.final=always vs ba.final=on_request', "
                                                  "'@depth.pcd.lsq.adapted vs @depth.pcd.lsq.pretrained'."),
    metric: str = typer.Option("depth.pcd.lsq.adapted", "--metric",
                               help="Summary key of a --pair side without @KEY."),
    better: str | None = typer.Option(None, "--better", help="higher or lower (default: lower for errors and "
                                                                "times, else higher)."),
    broadcast: bool = typer.Option(False, "--broadcast", help="--pair: an arm with one seed on a sequence stands "
                                                              "for every seed there (schemes without replay)."),
) -> None:
    """The paper's tables and plots from result folders; with --pair, paired differences of two variants run
    on the same sequences and seeds (wins out of N, mean ± std, sign test, bootstrap CI, a verdict).

    A damaged run (a summary.json that is not valid JSON or not an object, an unreadable config.yaml) is
    skipped with a note and the others are reported; the command fails only when no run could be."""
    from mutualslam_cli.report.columns import cell_text
    from mutualslam_cli.report.tables import add_paired, build_tables, collect, write_report

    out = check_output_folder(out or Path(config_from(config, sets).out) / "report", "report")  # before any work
    notes: list[str] = []
    rep = build_tables(collect(list(results), notes), notes)
    if pair:
        add_paired(rep, list(pair), metric, better, broadcast)
    for name, tdf in rep.tables.items():
        # titles and cells are text, not rich markup: a config label "[vo.inject_outliers=0.1]" stays
        t = Table(*(escape(str(c)) for c in tdf.columns), title=escape(rep.titles[name]))
        for row in tdf.itertuples(index=False):
            t.add_row(*(escape(cell_text(v)) for v in row))
        common.console.print(t)
    with write_errors(out, "the tables above were not all written"):
        paths = write_report(rep, out)
    for note in rep.notes:  # paths and values from the result folders: shown, never markup
        common.err_console.print(f"[yellow]note:[/] {common.shown(note)}", highlight=False, soft_wrap=True)
    common.console.print(f"wrote {len(paths)} files to {escape(str(out))}"
                         + (f" ({len(rep.notes)} notes in report.md)" if rep.notes else ""))

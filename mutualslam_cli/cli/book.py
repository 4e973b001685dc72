"""``mslam book``: the results book — every experiment the README reports, from one config, then every table,
figure and verdict with its provenance; ``--render-readme`` rewrites the README's blocks from the committed book."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import DataRootOpt, RegistryOpt, SetOpt, app, progress_bar

if TYPE_CHECKING:  # imported where the command runs (the CLI starts without the book's modules)
    from mutualslam_cli.ablate import JobOutcome
    from mutualslam_cli.book.plan import Plan


@app.command()
def book(
    book_file: Path = typer.Argument(Path("configs/book.yaml"), help="The book file (default configs/book.yaml)."),
    out: Path | None = typer.Option(None, "--out", help="Results folder (default: the book's, results/book)."),
    only: list[str] | None = typer.Option(None, "--only", help="Run and write only this entry (a table, figure, "
                                                                  "finding or grid; repeatable)."),
    workers: int = typer.Option(1, "--workers", "-j", min=1, help="Worker processes (as mslam ablate)."),
    executor: str = typer.Option("local", "--executor", help="local (process pool) or dask."),
    scheduler: str | None = typer.Option(None, "--scheduler", help="Dask scheduler address."),
    sets: list[str] | None = SetOpt,
    data_root: str | None = DataRootOpt,
    registry: Path | None = RegistryOpt,
    dry_run: bool = typer.Option(False, "--dry-run", help="Only say what would run: jobs per grid, how many have a "
                                                          "fresh record, how many a stale one and why."),
    records: Path | None = typer.Option(None, "--records", help="Where each finished job's record is kept (default: "
                                                                "the book's, results/records, committed)."),
    publish: bool = typer.Option(False, "--publish", help="Then copy book.json to results/book.json (the committed "
                                                          "copy) and rewrite the README's blocks from it."),
    render_readme: bool = typer.Option(False, "--render-readme", help="Run nothing: rewrite the README's blocks "
                                                                      "from results/book.json."),
) -> None:
    """Run the results book: its grids through the resumable grid (complete runs skipped: a killed book resumes),
    then results/book/: tables (Markdown, LaTeX, CSV), figures (PNG), the verdicts on the paper's findings,
    each grid's full report, and book.json with every published figure's provenance.

    A preset tuned on a grid's own sequences (its '# tuned-on:' header line) is refused, as is a variant folder
    whose runs were made under another config."""
    from mutualslam_cli.book import readme

    if render_readme:
        stale = readme.render_file()
        common.console.print(f"README: {len(stale)} block(s) rewritten from {escape(str(readme.BOOK_JSON))}"
                             + (f": {', '.join(stale)}" if stale else ""))
        return
    from mutualslam_cli.book.plan import plan_book
    from mutualslam_cli.book.run import job_states, records_root, run_book, total_jobs
    from mutualslam_cli.book.spec import load_book

    spec = load_book(book_file)
    root = Path(out or spec.out)
    reg = str(registry) if registry else None
    if dry_run:
        plan = plan_book(spec, root, spec.grids_for(only), reg, data_root, sets, render=False)
        rroot = records_root(spec, records)
        states = job_states(spec, plan, rroot)
        for p in plan.parts:
            mine = [s for q, _, s in states if q is p]
            count = {k: sum(s.status == k for s in mine) for k in ("fresh", "stale", "missing")}
            kinds = sorted({s.record.cpu_kind for s in mine if s.status == "fresh" and s.record is not None})
            common.console.print(f"{p.grid}/{p.variant}: {len(p.jobs)} jobs, {count['fresh']} complete"
                                 + (f" ({', '.join(kinds)})" if kinds else "") + f", {count['stale']} stale, "
                                 f"{count['missing']} to run (config {p.config_hash})")
            why = next((s.why for s in mine if s.status == "stale"), "")
            if why:
                common.console.print(f"  stale: {escape(why)}", highlight=False)
        for g, names in plan.skipped.items():
            common.console.print(f"{g}: not on this machine, left out: {', '.join(names)}")
        fresh = sum(s.status == "fresh" for _, _, s in states)
        secs = sum(s.record.seconds or 0.0 for _, _, s in states if s.status == "fresh" and s.record is not None)
        common.console.print(f"{total_jobs(plan)} jobs in all: {fresh} complete from the records in "
                             f"{escape(str(rroot))} ({secs / 3600:.1f} h of runs), {total_jobs(plan) - fresh} to run")
        return
    # before the progress bar: a damaged record, a missing sequence, a bad setting is one line and nothing runs
    job_states(spec, plan_book(spec, root, spec.grids_for(only), reg, data_root, sets, render=False),
               records_root(spec, records))
    with progress_bar() as bar:
        task = bar.add_task("book", total=None, info="")

        def planned(plan: Plan) -> None:
            bar.update(task, total=total_jobs(plan))

        def job_done(o: JobOutcome) -> None:
            bar.update(task, advance=1, info=f"{Path(o.job.sequence).name} {o.job.scheme} seed{o.job.seed}: {o.status}")

        try:
            res = run_book(spec, root, list(only or []) or None, workers, executor, scheduler, reg, data_root,
                           list(sets or []), sys.argv, on_plan=planned, on_done=job_done, records=records)
        except KeyboardInterrupt:
            bar.stop()
            common.err_console.print("[yellow]interrupted[/]: complete runs stay; run the same command again to "
                                     "resume (nothing was published).")
            raise typer.Exit(130) from None
    counts = {s: sum(o.status == s for o in res.outcomes) for s in ("done", "skipped", "failed")}
    common.console.print(f"{len(res.outcomes)} jobs: {counts['done']} done, {counts['skipped']} already complete, "
                         f"{counts['failed']} failed")
    for o in res.failed:
        common.err_console.print(f"[red]failed[/] {escape(o.job.sequence)} {o.job.scheme} seed{o.job.seed}: "
                                 f"{common.shown((o.error or '').splitlines()[0] if o.error else '')}")
    for n in res.notes:
        common.err_console.print(f"[yellow]note:[/] {common.shown(n)}", highlight=False, soft_wrap=True)
    if res.failed or res.book_json is None:
        raise typer.Exit(1)
    common.console.print(f"wrote {len(res.written)} files to {escape(str(root))} (book.json: {res.book_json})")
    if publish and res.book_json is not None:
        shutil.copyfile(res.book_json, readme.BOOK_JSON)
        shutil.rmtree(readme.FIGURES, ignore_errors=True)  # the published book's figures, committed beside it
        shutil.copytree(root / "figures", readme.FIGURES)
        stale = readme.render_file()
        common.console.print(f"published {escape(str(readme.BOOK_JSON))}; README: {len(stale)} block(s) rewritten")

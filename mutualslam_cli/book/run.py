"""``mslam book``: every experiment of the book through the resumable grid, then every table, figure and verdict
with its provenance (:func:`run_book`).

The grids run as ``mslam ablate`` runs them (:func:`~mutualslam_cli.ablate.run_grid`: a local process pool or
Dask; complete runs skipped, a killed job's staging folder redone), one (grid, variant) after another into
``<out>/runs/<grid>/<variant>/``, each finished job recorded at once (:mod:`.records`). A book killed at any point
resumes when run again, on any checkout that has the records: what has a fresh record is reused, nothing else was
published (``book.json`` is written last, from the records, and only when every job of the planned grids has a
fresh one — with failures it is not written and the command fails, naming them).

``<out>/`` then holds ``tables/<name>.{md,tex,csv}`` (and ``findings.*``, the verdicts), ``figures/<name>.png``,
``reports/<grid>/`` (``mslam report`` of each grid's runs: every table and figure of the report) and
``book.json``: each published table cell, figure and verdict with where it came from (:mod:`.build`).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import pandas as pd

from mutualslam_cli.ablate import Job, JobOutcome, run_grid
from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.book.build import build_bounds, build_figures, build_tables, collect_book
from mutualslam_cli.book.entries import BookJSON, GridEntry
from mutualslam_cli.book.findings import judge, verdict_rows
from mutualslam_cli.book.plan import Part, Plan, describe, plan_book
from mutualslam_cli.book.records import JobState, job_state, record_from_run, write_record
from mutualslam_cli.book.spec import BookSpec
from mutualslam_cli.config import CONFIG_DIR
from mutualslam_cli.machine import cpu_info
from mutualslam_cli.report.runs import config_labels
from mutualslam_cli.report.tables import build_tables as report_tables
from mutualslam_cli.report.tables import to_latex, to_markdown, write_report
from mutualslam_cli.results.fingerprint import code_fingerprint
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.run_folder import git_revision, is_complete, run_dir
from mutualslam_cli.results.summary import plain
from mutualslam_cli.results.writable import check_output_folder
from mutualslam_cli.types import JSON

#: ``book.json``'s format; a reader refuses another.
FORMAT = 1


@dataclass
class BookResult:
    """What a book run did: every job's outcome, the files written (none when jobs failed) and the notes."""

    outcomes: list[JobOutcome] = field(default_factory=list)
    written: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    book_json: Path | None = None

    @property
    def failed(self) -> list[JobOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]


def total_jobs(plan: Plan) -> int:
    return sum(len(p.jobs) for p in plan.parts)


def records_root(spec: BookSpec, records: str | Path | None = None) -> Path:
    """Where the book's records live: ``records`` when given, else the book's ``records`` (relative to the
    repository)."""
    p = Path(records if records is not None else spec.records)
    return p if p.is_absolute() or records is not None else CONFIG_DIR.parent / p


def _label(job: Job) -> str:
    return Path(job.sequence).name


def job_states(spec: BookSpec, plan: Plan, root: Path) -> list[tuple[Part, Job, JobState]]:
    """Every job of the plan with its standing in the records (:func:`~mutualslam_cli.book.records.job_state`).

    Raises:
        DamagedRecord: a record is damaged or was written by hand (one line naming it).
    """
    return [(p, j, job_state(root, spec.name, p.grid, p.variant, _label(j), j.scheme, j.seed, p.config_hash,
                             plan.data.get(_label(j)))) for p in plan.parts for j in p.jobs]


def _set_aside(folder: Path) -> None:
    """Move a stale run folder out of the grid's way (hidden beside it, replacing an older one set aside)."""
    to = folder.with_name(f".{folder.name}.stale")
    shutil.rmtree(to, ignore_errors=True)
    folder.rename(to)


def run_book(spec: BookSpec, out: Path, only: list[str] | None = None, workers: int = 1, executor: str = "local",
             scheduler: str | None = None, registry: str | None = None, data_root: str | None = None,
             overrides: list[str] | None = None, command: list[str] | None = None,
             on_plan: Callable[[Plan], None] | None = None,
             on_done: Callable[[JobOutcome], None] | None = None, records: str | Path | None = None) -> BookResult:
    """Run the book (module docstring); ``only``: the entries (tables, figures, findings, grids) to run and write;
    ``records``: where the job records are kept (default: the book's, :func:`records_root`).

    A job whose record is fresh is complete (``skipped``); a complete run folder without one is recorded when this
    checkout's code made it, else set aside and run again, as is a job whose record is stale. Each job that
    finishes is recorded at once, so a killed book resumes from its records on any checkout.

    Raises:
        ConfigError, DatasetError: before any work (:func:`~mutualslam_cli.book.plan.plan_book`); DamagedRecord
            for a damaged or hand-written record.
        ResultsLocked: another book (or grid) works in ``out``.
        KeyboardInterrupt: Ctrl-C; finished runs stay complete and recorded, nothing is published.
    """
    out = check_output_folder(out)
    root = records_root(spec, records)
    grids = spec.grids_for(only)
    res = BookResult()
    code = code_fingerprint()  # before the workers fork: they stamp their runs with it
    with hold_lock(out, "mslam book"):
        plan = plan_book(spec, out, grids, registry, data_root, overrides)
        job_states(spec, plan, root)  # a damaged or hand-written record stops the book before any work
        if on_plan is not None:
            on_plan(plan)

        def report(o: JobOutcome) -> None:
            res.outcomes.append(o)
            if on_done is not None:
                on_done(o)

        for part in plan.parts:
            todo = []
            for job in part.jobs:  # read now, not at the start: another machine may have recorded it meanwhile
                state = job_state(root, spec.name, part.grid, part.variant, _label(job), job.scheme, job.seed,
                                  part.config_hash, plan.data.get(_label(job)))
                folder = run_dir(part.out, _label(job), job.scheme, job.seed)
                if state.status == "fresh":
                    report(JobOutcome(job, "skipped", folder if is_complete(folder) else None))
                    continue
                if is_complete(folder):  # finished but not recorded (killed between the two), or stale
                    rec = record_from_run(folder, spec.name, part.grid, part.variant, job.scheme, job.seed,
                                          part.config_hash, plan.data.get(_label(job)))
                    if rec is not None and rec.code == code:
                        write_record(root, rec)
                        report(JobOutcome(job, "skipped", folder))
                        continue
                    _set_aside(folder)
                todo.append(job)

            def recorded(o: JobOutcome, part: Part = part) -> None:
                if o.status == "done" and o.folder is not None:
                    rec = record_from_run(o.folder, spec.name, part.grid, part.variant, o.job.scheme, o.job.seed,
                                          part.config_hash, plan.data.get(_label(o.job)))
                    if rec is not None:
                        write_record(root, rec)
                report(o)

            if todo:
                run_grid(part.cfg, todo, part.out, workers=workers, command=command, registry=registry,
                         on_done=recorded, executor=executor, scheduler=scheduler)
        if res.failed:
            res.notes.append(f"{len(res.failed)} job(s) failed: nothing published; run the book again to retry them")
            return res
        states = job_states(spec, plan, root)
        unfinished = [f"{p.grid}/{p.variant} {_label(j)} {j.scheme} seed{j.seed}: {s.status} {s.why}".rstrip()
                      for p, j, s in states if s.status != "fresh"]
        if unfinished:
            res.notes.append(f"{len(unfinished)} job(s) have no fresh record (nothing published): {unfinished[0]}")
            return res
        write_book(spec, plan, out, set(grids), only, res, states)
    return res


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _relative(path: Path) -> str:
    try:
        return path.resolve().relative_to(CONFIG_DIR.parent).as_posix()
    except ValueError:
        return str(path)


def write_book(spec: BookSpec, plan: Plan, out: Path, grids: set[str], only: list[str] | None,
               res: BookResult, states: list[tuple[Part, Job, JobState]]) -> None:
    """Build and write every output (module docstring) from the jobs' fresh records, ``book.json`` last."""
    notes = res.notes
    runs = collect_book(plan, states)

    def wanted(name: str) -> bool:  # --only: the entries named, and every entry of a grid named
        return not only or name in only or bool(set(only) & grids & set(spec.grids))

    tables = {k: v for k, v in build_tables(spec, runs, plan, grids).items() if wanted(k)}
    tdir, fdir = out / "tables", out / "figures"
    for d in (tdir, fdir):
        d.mkdir(parents=True, exist_ok=True)
    for name, t in tables.items():
        disp = t.display()
        for path, text in ((tdir / f"{name}.md", f"### {t.spec.title}\n\n" + to_markdown(disp)),
                           (tdir / f"{name}.tex", to_latex(disp, t.spec.title, t.bold)),
                           (tdir / f"{name}.csv", t.numeric().to_csv(index=False))):
            atomic_write_text(path, text)
            res.written.append(path)
    findings = {k: v for k, v in judge(spec, runs, grids).items() if wanted(k)}
    if findings:
        v = verdict_rows(findings)
        for path, text in ((tdir / "findings.md", "### The paper's findings on the book's runs\n\n" + to_markdown(v)),
                           (tdir / "findings.csv", v.to_csv(index=False)),
                           (tdir / "findings.tex", to_latex(v, "The paper's findings on the book's runs"))):
            atomic_write_text(path, text)
            res.written.append(path)
    figures = {k: v for k, v in build_figures(spec, runs, plan, fdir, grids, notes).items() if wanted(k)}
    res.written += [fdir / f["file"] for f in figures.values()]
    for grid in sorted(grids):  # the whole report of each grid's runs: every table and figure it can fill
        r = runs[runs["book.grid"] == grid] if not runs.empty else runs
        if not r.empty:  # variants apart: the config label over the grid's runs together
            r = r.drop(columns=[c for c in r if c.startswith("book.")]).copy()
            res.written += write_report(report_tables(r.assign(config=config_labels(r).values), []),
                                        out / "reports" / grid)
    bounds = build_bounds(spec, tables, plan, notes)
    cpu = cpu_info()
    book: BookJSON = {
        "format": FORMAT,
        "book": {"name": spec.name, "file": _relative(spec.path), "file_sha256": _sha256(spec.path),
                 "commit": git_revision(), "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(
                     timespec="seconds"), "cpu_kind": cpu.get("cpu_kind"), "cpu_model": cpu.get("cpu_model"),
                 "only": list(only or []), "runs": len(runs),
                 "commits": sorted({str(c) for c in runs.get("book.commit", []) if c}),
                 "devices": sorted({str(c) for c in runs.get("run.device_label", []) if c == c and c})},
        "grids": _with_cost(describe(plan), runs), "tables": {k: t.as_dict() for k, t in tables.items()},
        "figures": figures, "findings": findings, "bounds": bounds, "notes": notes}
    path = out / "book.json"
    atomic_write_text(path, json.dumps(plain(book), indent=1, ensure_ascii=False, allow_nan=False) + "\n")
    res.written.append(path)
    res.book_json = path


def _with_cost(grids: dict[str, GridEntry], runs: pd.DataFrame) -> dict[str, GridEntry]:
    """``grids`` with each grid's ``seconds`` (the sum of its runs' times, from their records) and ``cpu_kinds``."""
    for g, d in grids.items():
        r = runs[runs["book.grid"] == g] if len(runs) else runs
        secs = [float(x) for x in r.get("book.seconds", []) if x is not None and x == x]
        d["seconds"] = sum(secs) if secs else None
        d["cpu_kinds"] = sorted({str(k) for k in r.get("book.cpu_kind", []) if k})
    return grids


def read_book(path: str | Path) -> BookJSON:
    """A ``book.json`` (:func:`write_book`), its format checked (its entries are taken as :func:`write_book` wrote
    them: the committed book is written only by ``mslam book --publish``).

    Raises:
        ConfigError: not readable, not JSON, or another format.
    """
    from mutualslam_cli.errors import ConfigError

    path = Path(path)
    try:
        book: JSON = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: not a readable book.json ({e})") from None
    if not isinstance(book, dict) or book.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a book.json of format {FORMAT} (written by mslam book)")
    return cast(BookJSON, book)  # a JSON object of the format write_book writes: its shape, unchecked

"""What the book publishes, from its runs: tables whose every cell carries its provenance, figures, and the cells
its bounds rerun (:func:`build_tables`, :func:`build_figures`, :func:`build_bounds`).

The runs are read from the jobs' fresh records (:mod:`~mutualslam_cli.book.records`) into one frame, a row per run
as ``mslam report`` reads a run folder, with ``book.grid`` and ``book.variant`` columns (:func:`collect_book`). A
table's rows are its grid's sequences and an ``Average`` (the mean of the sequence means, over the sequences that
have every column, their count named when that is not all); a cell is the mean ± std over the seeds that have
the value, with, in ``book.json``, every seed's value and run folder, the config hash, the commits and CPU kinds
of those runs, and the schedule — a figure is never published without the runs it came from. A cell whose seeds
ran on more than one CPU kind is marked ``‡`` (:data:`MIXED`) and names the kinds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from mutualslam_cli.ablate import Job
from mutualslam_cli.book.entries import BoundEntry, CellEntry, CellSource, FigureEntry, TableEntry, ValueEntry
from mutualslam_cli.book.plan import Part, Plan, part_of
from mutualslam_cli.book.records import CURVES, JobState
from mutualslam_cli.book.spec import PAPER_TABLES, BookSpec, ColumnSpec, TableSpec
from mutualslam_cli.config import to_dict
from mutualslam_cli.report.columns import numeric
from mutualslam_cli.report.paper import cell
from mutualslam_cli.report.paper_numbers import paper_name
from mutualslam_cli.report.runs import config_labels
from mutualslam_cli.results.run_folder import is_complete, run_dir
from mutualslam_cli.results.summary import flatten
from mutualslam_cli.types import Scalar


def collect_book(plan: Plan, states: list[tuple[Part, Job, JobState]]) -> pd.DataFrame:
    """One row per fresh record of the plan's jobs, as :func:`~mutualslam_cli.report.runs.collect` makes rows of
    run folders: the flattened summary, ``config.<key>`` of the part's config, ``folder`` (the local run folder,
    else the record), ``curve.<model>`` (the running-accuracy curves, for the figures), and ``book.grid``,
    ``book.variant``, ``book.config_hash``, ``book.commit``, ``book.cpu_kind``, ``book.seconds`` and ``book.run``
    (the run's place under the book's ``runs/``)."""
    rows = []
    for part, _job, state in states:
        rec = state.record
        if state.status != "fresh" or rec is None or rec.sequence not in plan.sequences[part.grid]:
            continue
        folder = run_dir(part.out, rec.sequence, rec.scheme, rec.seed)
        row: dict[str, Scalar | pd.Series] = dict(rec.summary)
        row.update({f"config.{k}": v for k, v in flatten(to_dict(part.cfg)).items()})
        row.update({"config.adapt.scheme": rec.scheme, "config.seed": rec.seed, "scheme": rec.scheme,
                    "seed": rec.seed, "sequence.name": rec.sequence,
                    "folder": str(folder if is_complete(folder) else folder.parent),
                    "book.grid": part.grid, "book.variant": part.variant, "book.config_hash": rec.config_hash,
                    "book.commit": rec.commit, "book.code": rec.code, "book.cpu_kind": rec.cpu_kind,
                    "book.seconds": rec.seconds,
                    "book.run": f"{part.grid}/{part.variant}/{rec.sequence}/{rec.scheme}/seed{rec.seed}"})
        frames = rec.curves.get("frame")
        for m in CURVES:
            if frames and m in rec.curves:
                row[f"curve.{m}"] = pd.Series(rec.curves[m], index=frames, dtype=float)
        rows.append(row)
    if not rows:
        return pd.DataFrame(columns=["book.grid", "book.variant", "sequence.name", "scheme", "seed", "folder"])
    runs = pd.DataFrame(rows)
    runs["config.run_device"] = runs.get("run.device_label")
    runs["config"] = config_labels(runs)
    return runs


#: The mark of a cell whose seeds ran on more than one CPU kind.
MIXED = "‡"


def arm_runs(runs: pd.DataFrame, grid: str, variant: str, scheme: str, sequence: str | None = None) -> pd.DataFrame:
    """The runs of one (grid, variant, scheme), of one sequence when given."""
    if runs.empty:
        return runs
    m = (runs["book.grid"] == grid) & (runs["book.variant"] == variant) & (runs["scheme"].astype(str) == scheme)
    if sequence is not None:
        m &= runs["sequence.name"].astype(str) == sequence
    return runs[m]


def _sorted_unique(values: pd.Series) -> list[str]:
    return sorted({str(v) for v in values if v is not None and v == v})


@dataclass
class Cell:
    """One published cell: mean ± std over seeds, the text shown, and where each value came from."""

    mean: float
    std: float
    n: int
    text: str
    source: CellSource = field(default_factory=CellSource)

    def as_dict(self) -> CellEntry:
        def f(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {"mean": f(self.mean), "std": f(self.std), "n": self.n, "text": self.text, **self.source}


def column_cell(runs: pd.DataFrame, col: ColumnSpec, sequence: str, digits: int, config_hash: str,
                schedule: str) -> Cell:
    """The cell of ``col`` on ``sequence`` (module docstring)."""
    r = arm_runs(runs, col.grid, col.variant, col.scheme, sequence)
    v = numeric(r, col.key) * col.scale if len(r) else pd.Series(dtype=float)
    have = r[np.isfinite(v.to_numpy(dtype=float))] if len(r) else r
    vals = v[np.isfinite(v.to_numpy(dtype=float))] if len(r) else v
    n = len(vals)
    mean = float(vals.mean()) if n else float("nan")
    std = float(vals.std(ddof=1)) if n > 1 else float("nan")
    values: list[ValueEntry] = [{"seed": int(s) if s == s else None, "value": float(x), "run": run}
                                for s, x, run in zip(have.get("seed", []), vals, have.get("book.run", []))]
    source: CellSource = {"grid": col.grid, "variant": col.variant, "scheme": col.scheme, "key": col.key,
                          "scale": col.scale, "sequence": sequence, "config_hash": config_hash, "schedule": schedule,
                          "values": values, "commits": _sorted_unique(have["book.commit"]) if n else [],
                          "devices": _sorted_unique(have["run.device_label"]) if n and "run.device_label" in have
                          else [],
                          "cpu_kinds": _sorted_unique(have["book.cpu_kind"]) if n and "book.cpu_kind" in have else [],
                          "codes": _sorted_unique(have["book.code"]) if n and "book.code" in have else []}
    kinds = source["cpu_kinds"]
    text = cell(mean, std, n, digits) + (f" {MIXED}" if isinstance(kinds, list) and len(kinds) > 1 else "")
    return Cell(mean, std, n, text, source)


@dataclass
class BookTable:
    """A built table: ``columns`` (``Sequence`` first), ``rows`` of :class:`Cell` (the first a label), bold cells."""

    spec: TableSpec
    columns: list[str]
    rows: list[tuple[str, list[Cell]]]
    bold: set[tuple[int, str]]

    def display(self) -> pd.DataFrame:
        return pd.DataFrame([[label, *(c.text for c in cells)] for label, cells in self.rows], columns=self.columns)

    def numeric(self) -> pd.DataFrame:
        recs = []
        for label, cells in self.rows:
            d: dict[str, Scalar] = {"sequence": label}
            for c, x in zip(self.columns[1:], cells):
                d.update({f"{c} mean": x.mean, f"{c} std": x.std, f"{c} n": x.n})
            recs.append(d)
        return pd.DataFrame(recs)

    def as_dict(self) -> TableEntry:
        return {"title": self.spec.title, "grid": self.spec.grid, "columns": self.columns,
                "rows": [{"label": label, "cells": [c.as_dict() for c in cells]} for label, cells in self.rows],
                "bold": sorted([i, c] for i, c in self.bold)}


def build_table(spec: TableSpec, runs: pd.DataFrame, plan: Plan) -> BookTable:
    """One table of the book (module docstring)."""
    seqs = list(plan.sequences[spec.grid])
    rows: list[tuple[str, list[Cell]]] = []
    for seq in seqs:
        cells = []
        for col in spec.columns:
            part = part_of(plan, col.grid, col.variant)
            cells.append(column_cell(runs, col, seq, _digits(spec, col), part.config_hash, part.cfg.adapt.schedule))
        rows.append((seq, cells))
    full = [cells for _, cells in rows if all(c.n for c in cells)]
    k = len(full)
    avg = []
    for j, col in enumerate(spec.columns):
        m = float(np.mean([cells[j].mean for cells in full])) if full else float("nan")
        avg.append(Cell(m, float("nan"), k, "—" if not np.isfinite(m) else f"{m:.{_digits(spec, col)}f}",
                        {"average_of": [seqs[i] for i, (_, c) in enumerate(rows) if all(x.n for x in c)]}))
    rows.append(("Average" if k == len(seqs) else f"Average ({k} of {len(seqs)})", avg))
    bold: set[tuple[int, str]] = set()
    if spec.better is not None:
        for i, (_, cells) in enumerate(rows):
            have = [(c.mean, col.label) for c, col in zip(cells, spec.columns) if np.isfinite(c.mean)]
            if len(have) > 1:
                best = (min if spec.better == "lower" else max)(m for m, _ in have)
                bold |= {(i, lab) for m, lab in have if f"{m:.{spec.digits}f}" == f"{best:.{spec.digits}f}"}
    rows += paper_rows(spec, seqs)
    return BookTable(spec, ["Sequence", *(c.label for c in spec.columns)], rows, bold)


def _paper_cell(col: ColumnSpec, digits: int, sequences: list[str]) -> Cell:
    """The paper's number of ``col`` (its ``paper:``), the mean over the paper's ``sequences`` that have it."""
    if col.paper is None:
        return Cell(float("nan"), float("nan"), 0, "—")
    table, _, key = col.paper.partition(".")
    have = [s for s in sequences if key in PAPER_TABLES[table].get(s, {})]
    if not have:
        return Cell(float("nan"), float("nan"), 0, "—")
    v = float(np.mean([PAPER_TABLES[table][s][key] for s in have])) * col.scale
    return Cell(v, float("nan"), 0, f"{v:.{digits}f}", {"paper": col.paper, "paper_sequences": have})


def paper_rows(spec: TableSpec, sequences: list[str]) -> list[tuple[str, list[Cell]]]:
    """The paper's own numbers beside ours: a row per sequence of ours that is one of the paper's (its window, not
    the whole sequence) and a row of the paper's Average over all its sequences; none when no column names one."""
    if not any(c.paper for c in spec.columns):
        return []
    out = []
    for seq in sequences:
        name = paper_name(seq)
        if name is not None:
            out.append((f"paper: {name}", [_paper_cell(c, _digits(spec, c), [name]) for c in spec.columns]))
    every = sorted({s for c in spec.columns if c.paper for s in PAPER_TABLES[c.paper.partition(".")[0]]})
    out.append((f"paper: Average ({len(every)} sequences)",
                [_paper_cell(c, _digits(spec, c), every) for c in spec.columns]))
    return out


def _digits(spec: TableSpec, col: ColumnSpec) -> int:
    return spec.digits if col.digits is None else col.digits


def build_tables(spec: BookSpec, runs: pd.DataFrame, plan: Plan, only_grids: set[str]) -> dict[str, BookTable]:
    """Every table whose grids all ran in this plan."""
    return {name: build_table(t, runs, plan) for name, t in spec.tables.items()
            if {c.grid for c in t.columns} | {t.grid} <= only_grids}


def build_figures(spec: BookSpec, runs: pd.DataFrame, plan: Plan, out: Path, only_grids: set[str],
                  notes: list[str]) -> dict[str, FigureEntry]:
    """Every figure whose grid ran: its PNG under ``out`` and its provenance (the runs, config hash, schemes)."""
    from mutualslam_cli.report.plots import plot_accuracy

    figs: dict[str, FigureEntry] = {}
    for name, f in spec.figures.items():
        if f.grid not in only_grids:
            continue
        r = runs[(runs["book.grid"] == f.grid) & (runs["book.variant"] == f.variant)
                 & runs["scheme"].astype(str).isin(f.schemes)] if not runs.empty else runs
        path = out / f"{name}.png"
        if r.empty or not plot_accuracy(r, path):
            notes.append(f"figure {name}: no run had what it draws")
            continue
        part = part_of(plan, f.grid, f.variant)
        figs[name] = {"title": f.title, "file": path.name, "kind": f.kind, "grid": f.grid, "variant": f.variant,
                      "schemes": list(f.schemes), "config_hash": part.config_hash,
                      "schedule": part.cfg.adapt.schedule, "runs": sorted(r["book.run"]),
                      "commits": _sorted_unique(r["book.commit"]),
                      "devices": _sorted_unique(r["run.device_label"]) if "run.device_label" in r else []}
    return figs


def build_bounds(spec: BookSpec, tables: dict[str, BookTable], plan: Plan, notes: list[str]) -> list[BoundEntry]:
    """The cells the bounds rerun: the seed's value, and everything a test needs to make that one run again."""
    out: list[BoundEntry] = []
    for b in spec.bounds:
        t = tables.get(b.table)
        if t is None:
            continue
        row = next((cells for label, cells in t.rows if label == b.row), None)
        j = t.columns.index(b.column) - 1
        col = t.spec.columns[j]
        hit: ValueEntry | None = None  # the seed's value (the last one, were a seed there twice)
        if row is not None:
            for v in row[j].source.get("values", []):
                if v["seed"] == b.seed:
                    hit = v
        if hit is None:
            notes.append(f"bound {b.table} / {b.row} / {b.column} seed {b.seed}: no such value in the book")
            continue
        value, run = hit["value"], hit["run"]
        part = part_of(plan, col.grid, col.variant)
        out.append({"table": b.table, "row": b.row, "column": b.column, "seed": b.seed, "value": value,
                    "factor": b.factor, "ci": b.ci, "grid": col.grid, "variant": col.variant, "scheme": col.scheme,
                    "key": col.key, "scale": col.scale, "config_hash": part.config_hash, "run": run,
                    "sequence": plan.sequences[col.grid][b.row].as_dict()})
    return out

"""The shapes of every entry of ``book.json`` (:class:`BookJSON`): a table's cells with their provenance, a
figure's, a finding's comparisons, a bound's run, a grid's cost (a grid's sequences: :mod:`.spec`'s
:class:`~.spec.SequenceEntry`).

Types only (no code): :mod:`.build`, :mod:`.findings`, :mod:`.plan` and :mod:`.run` write these shapes,
:mod:`.readme` and :mod:`.bounds` read them. Numbers that could not be computed are ``None`` (``null``), never NaN.
"""

from __future__ import annotations

from typing import TypedDict

from mutualslam_cli.book.spec import SequenceEntry, SynthSpec
from mutualslam_cli.report.paired import PairedDict

__all__ = ["ArmEntry", "BookHead", "BookJSON", "BoundEntry", "CellEntry", "CellSource", "ComparisonEntry",
           "FigureEntry", "FindingEntry", "GridEntry", "RowEntry", "SequenceEntry", "SynthSpec", "TableEntry",
           "ValueEntry", "VariantEntry"]


class VariantEntry(TypedDict):
    """One variant of a grid: its config hash, its ``key=value`` overrides, its job count and schedule."""

    config_hash: str
    sets: list[str]
    jobs: int
    schedule: str


class _GridPlan(TypedDict):
    preset: str
    variants: dict[str, VariantEntry]
    skipped: list[str]
    sequences: list[SequenceEntry]


class GridEntry(_GridPlan, total=False):
    """A grid of the book (:func:`~mutualslam_cli.book.plan.describe`), with its cost once its runs are read:
    ``seconds`` (the sum of its runs' wall times, ``None`` without any) and their ``cpu_kinds``."""

    seconds: float | None
    cpu_kinds: list[str]


class ValueEntry(TypedDict):
    """One seed's value in a cell, and its run (``grid/variant/sequence/scheme/seed<k>`` under ``runs/``)."""

    seed: int | None
    value: float
    run: str


class CellSource(TypedDict, total=False):
    """Where a cell came from: a measured cell has the column's arm, ``sequence``, ``config_hash``, ``schedule``,
    every seed's value and the commits, devices, CPU kinds and code fingerprints of its runs; an Average cell its
    ``average_of`` sequences; a paper cell its ``paper`` number (``table1.Ours``) and ``paper_sequences``."""

    grid: str
    variant: str
    scheme: str
    key: str
    scale: float
    sequence: str
    config_hash: str
    schedule: str
    values: list[ValueEntry]
    commits: list[str]
    devices: list[str]
    cpu_kinds: list[str]
    codes: list[str]
    average_of: list[str]
    paper: str
    paper_sequences: list[str]


class CellEntry(CellSource):
    """A published cell: mean ± std over ``n`` seeds (``None``: not a finite number), the ``text`` shown, and its
    :class:`CellSource`."""

    mean: float | None
    std: float | None
    n: int
    text: str


class RowEntry(TypedDict):
    label: str
    cells: list[CellEntry]


class TableEntry(TypedDict):
    """A built table: ``columns`` (``Sequence`` first), its rows and its bold cells ``[row, column label]``."""

    title: str
    grid: str
    columns: list[str]
    rows: list[RowEntry]
    bold: list[list[int | str]]


class FigureEntry(TypedDict):
    """A drawn figure: its PNG ``file`` (beside ``book.json``'s ``figures/``) and the runs it was drawn from."""

    title: str
    file: str
    kind: str
    grid: str
    variant: str
    schemes: list[str]
    config_hash: str
    schedule: str
    runs: list[str]
    commits: list[str]
    devices: list[str]


class ArmEntry(TypedDict):
    """One arm of a finding's comparison (:class:`~mutualslam_cli.book.spec.ArmSpec`)."""

    grid: str
    variant: str
    scheme: str
    key: str


class ComparisonEntry(PairedDict):
    """A comparison's statistics and verdict, with its two ``arms`` (``a``, ``b``) and the commits and devices of
    their runs."""

    arms: dict[str, ArmEntry]
    commits: list[str]
    devices: list[str]


class FindingEntry(TypedDict):
    """A finding of the paper judged on the book's runs (:func:`~mutualslam_cli.book.findings.judge_one`)."""

    claim: str
    paper: str
    verdict: str
    comparisons: list[ComparisonEntry]
    rule: str


class BoundEntry(TypedDict):
    """A cell a bound reruns: its place in the book, the seed's ``value`` (in the table's unit, after ``scale``),
    the ``factor`` it must hold within, and everything one run needs to be made again."""

    table: str
    row: str
    column: str
    seed: int
    value: float
    factor: float
    ci: bool
    grid: str
    variant: str
    scheme: str
    key: str
    scale: float
    config_hash: str
    run: str
    sequence: SequenceEntry


class BookHead(TypedDict):
    """``book.json``'s ``book``: the book file and its digest, the commit and machine that wrote it, ``--only``,
    and the commits and devices of every run read."""

    name: str
    file: str
    file_sha256: str
    commit: str | None
    created_utc: str
    cpu_kind: str | None
    cpu_model: str | None
    only: list[str]
    runs: int
    commits: list[str]
    devices: list[str]


class BookJSON(TypedDict):
    """A ``book.json`` (:func:`~mutualslam_cli.book.run.write_book`), by name of each table, figure and finding."""

    format: int
    book: BookHead
    grids: dict[str, GridEntry]
    tables: dict[str, TableEntry]
    figures: dict[str, FigureEntry]
    findings: dict[str, FindingEntry]
    bounds: list[BoundEntry]
    notes: list[str]

"""``configs/book.yaml`` → :class:`BookSpec`: what the results book runs and what it publishes.

A book file has five sections (the header of ``configs/book.yaml`` shows each in use):

- ``book:`` its ``name``, the ``preset`` every grid starts from (a config file, relative to the repository),
  ``sets`` (``key=value`` on every grid's config, e.g. ``threads=1``), ``out`` (default ``results/book``) and
  ``records`` (where each finished job's record is kept, relative to the repository: default ``results/records``,
  committed; :mod:`~mutualslam_cli.book.records`);
- ``grids:`` what runs: per grid its ``sequences`` (required: a missing one is an error), ``when_present`` (the
  paper's whole sequences: run where their folder exists, else listed as skipped), ``schemes``, ``seeds``,
  ``one_seed`` (schemes run for the first seed only: those without replay give the same figures for every seed;
  a comparison with them says ``broadcast``), a ``preset`` of its own, ``sets`` (``key=value`` on the preset)
  and ``variants`` (label → overrides: the grid once per variant). A sequence is a ``datasets.yaml`` name, a
  folder, or a rendered room
  ``{synth: room, frames: 40, size: 128x96, seed: 0}`` (rendered once into ``<out>/data/``);
- ``tables:`` what is published: rows = the grid's sequences (+ ``Average``), ``columns`` each a summary ``key``
  of one ``scheme`` (and ``variant``, and ``grid``) as mean ± std over seeds, ``scale`` (100: m → cm), ``digits``
  (the table's, or a column's own), ``paper`` (``table1.Ours``: the paper's own number of that column, shown in
  rows of their own beside ours), ``better`` (the best cell of a row in bold);
- ``figures:`` PNGs drawn from a grid's runs (``kind: accuracy_over_frames``), with their runs as provenance;
- ``findings:`` the paper's claims, each one or more ``comparisons`` ``{a: ARM, b: ARM, better, broadcast}`` (an
  arm: ``grid``, ``variant``, ``scheme``, ``key``) judged by :mod:`mutualslam_cli.report.paired`'s rule;
- ``bounds:`` headline cells a test reruns and bounds (``table``, ``row``, ``column``, ``seed``, ``factor``,
  ``ci``: in CI, else ``slow``).

Everything is read strictly: an unknown key, a wrong type, a reference to a grid, table, scheme or column that
does not exist is one :class:`~mutualslam_cli.errors.ConfigError` line naming the file and the place.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict, TypeGuard, TypeVar

from mutualslam_cli.book.reader import Reader, names, texts
from mutualslam_cli.config.yaml_file import read_yaml_mapping
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.report import paper_numbers
from mutualslam_cli.types import JSON

#: Figure kinds the book draws (:mod:`mutualslam_cli.book.build`).
FIGURE_KINDS = ("accuracy_over_frames",)
#: The label of a grid's one variant when it declares none.
BASE = "base"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class SynthSpec(TypedDict):
    """A rendered room of a grid (``{synth: room, frames: 40, size: 128x96, seed: 0}``; ``size``: ``WxH`` pixels)."""

    scene: str
    frames: int
    size: str
    seed: int


class _Named(TypedDict):
    name: str


class SequenceEntry(_Named, total=False):
    """A grid's sequence as ``book.json`` names it: its ``name``, and ``synth`` for a rendered room."""

    synth: SynthSpec


@dataclass(frozen=True)
class SequenceRef:
    """A sequence of a grid: ``name`` (a ``datasets.yaml`` name or a folder), or a rendered room (``synth``)."""

    name: str
    synth: SynthSpec | None = None

    @property
    def label(self) -> str:
        """The name its runs are filed under (a folder's last part)."""
        return Path(self.name).name if "/" in self.name else self.name

    def as_dict(self) -> SequenceEntry:
        entry: SequenceEntry = {"name": self.name}
        if self.synth:
            entry["synth"] = self.synth.copy()
        return entry


@dataclass(frozen=True)
class GridSpec:
    name: str
    sequences: tuple[SequenceRef, ...]
    when_present: tuple[SequenceRef, ...]
    schemes: tuple[str, ...]
    seeds: tuple[int, ...]
    preset: str
    sets: tuple[str, ...]
    variants: dict[str, tuple[str, ...]]
    one_seed: tuple[str, ...] = ()


@dataclass(frozen=True)
class ColumnSpec:
    label: str
    key: str
    scheme: str
    variant: str
    grid: str
    scale: float = 1.0
    digits: int | None = None
    paper: str | None = None  # "table1.Ours": the paper's own number of that table and column


#: The paper's tables a column may name in ``paper:`` (:mod:`mutualslam_cli.report.paper_numbers`).
PAPER_TABLES = {"table1": paper_numbers.TABLE1, "table2": paper_numbers.TABLE2, "table3": paper_numbers.TABLE3,
                "table4": paper_numbers.TABLE4}


@dataclass(frozen=True)
class TableSpec:
    name: str
    title: str
    grid: str
    columns: tuple[ColumnSpec, ...]
    digits: int = 2
    better: str | None = None


@dataclass(frozen=True)
class FigureSpec:
    name: str
    title: str
    grid: str
    variant: str
    kind: str
    schemes: tuple[str, ...]


@dataclass(frozen=True)
class ArmSpec:
    grid: str
    variant: str
    scheme: str
    key: str

    @property
    def label(self) -> str:
        v = f" [{self.variant}]" if self.variant != BASE else ""
        return f"{self.scheme}{v} @ {self.key}"


@dataclass(frozen=True)
class ComparisonSpec:
    a: ArmSpec
    b: ArmSpec
    better: str
    broadcast: bool = False


@dataclass(frozen=True)
class FindingSpec:
    name: str
    claim: str
    paper: str
    comparisons: tuple[ComparisonSpec, ...]


@dataclass(frozen=True)
class BoundSpec:
    table: str
    row: str
    column: str
    seed: int
    factor: float = 1.5
    ci: bool = False


@dataclass(frozen=True)
class BookSpec:
    """A parsed book file (module docstring)."""

    path: Path
    name: str
    preset: str
    out: str
    grids: dict[str, GridSpec]
    sets: tuple[str, ...] = ()
    tables: dict[str, TableSpec] = field(default_factory=dict)
    figures: dict[str, FigureSpec] = field(default_factory=dict)
    findings: dict[str, FindingSpec] = field(default_factory=dict)
    bounds: tuple[BoundSpec, ...] = ()
    records: str = "results/records"

    def grids_for(self, only: list[str] | None) -> list[str]:
        """The grids the entries ``only`` (tables, figures, findings or grids by name; ``None``: all) read.

        Raises:
            ConfigError: a name that is no entry of the book.
        """
        if not only:
            return list(self.grids)
        need: list[str] = []
        for name in only:
            if name in self.grids:
                need.append(name)
            elif name in self.tables:
                need += [c.grid for c in self.tables[name].columns]
            elif name in self.figures:
                need.append(self.figures[name].grid)
            elif name in self.findings:
                need += [arm.grid for c in self.findings[name].comparisons for arm in (c.a, c.b)]
            else:
                entries = sorted({*self.grids, *self.tables, *self.figures, *self.findings})
                raise ConfigError(f"--only {name}: not an entry of {self.path} (one of {', '.join(entries)})")
        return [g for g in self.grids if g in need]


def _sequence(path: Path, where: str, v: JSON) -> SequenceRef:
    if isinstance(v, str) and v:
        return SequenceRef(v)
    r = Reader(path, where, v)
    scene = r.get("synth", str)
    frames, seed = r.get("frames", int, 40), r.get("seed", int, 0)
    size = r.get("size", str, "128x96")
    if not re.fullmatch(r"\d+x\d+", size):
        raise r.fail(f"'size' = {size!r}: expected WxH, e.g. 128x96")
    name = r.get("name", str, f"synth_{scene}_{frames}f_{size}_s{seed}")
    r.done()
    if not _NAME.match(name):
        raise r.fail(f"'name' = {name!r}: expected a folder name (letters, digits, _ . + -)")
    return SequenceRef(name, {"scene": scene, "frames": frames, "size": size, "seed": seed})


def _seeds(v: list[JSON]) -> TypeGuard[list[int]]:
    return bool(v) and all(isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in v)


def _grid(path: Path, name: str, data: JSON, preset: str) -> GridSpec:
    r = Reader(path, f"grids.{name}", data)
    seqs = tuple(_sequence(path, f"grids.{name}.sequences[{i}]", v)
                 for i, v in enumerate(r.get("sequences", list, [])))
    present = tuple(_sequence(path, f"grids.{name}.when_present[{i}]", v)
                    for i, v in enumerate(r.get("when_present", list, [])))
    schemes = names(r, "schemes")
    seeds = r.get("seeds", list, [0])
    if not _seeds(seeds):
        raise r.fail(f"'seeds' = {seeds!r}: expected a list of seeds ≥ 0")
    variants_raw = r.get("variants", dict, {BASE: []})
    variants: dict[str, tuple[str, ...]] = {}
    for label, sets in variants_raw.items():
        if not isinstance(label, str) or not _NAME.match(label):
            raise r.fail(f"variant {label!r}: expected a folder name")
        if not texts(sets, lambda s: "=" in s):
            raise r.fail(f"variant {label}: expected a list of key=value overrides, got {sets!r}")
        variants[label] = tuple(sets)
    one_seed = names(r, "one_seed", [])
    if set(one_seed) - set(schemes):
        raise r.fail(f"'one_seed': {', '.join(sorted(set(one_seed) - set(schemes)))} not among its schemes")
    g = GridSpec(name, seqs, present, schemes, tuple(seeds), r.get("preset", str, preset), names(r, "sets", []),
                 variants, one_seed)
    r.done()
    labels = [s.label for s in seqs + present]
    if not labels:
        raise r.fail("no sequence: give 'sequences' or 'when_present'")
    unique: tuple[tuple[str, Sequence[object]], ...] = (("sequence", labels), ("scheme", list(schemes)),
                                                         ("seed", list(seeds)))
    for what, items in unique:
        twice = sorted({str(x) for x in items if items.count(x) > 1})
        if twice:
            raise r.fail(f"{what} {twice[0]} given twice (each is one run folder)")
    return g


def _arm(path: Path, where: str, data: JSON, grids: dict[str, GridSpec], grid: str | None = None) -> ArmSpec:
    r = Reader(path, where, data)
    g = r.get("grid", str) if grid is None else r.get("grid", str, grid)
    if g not in grids:
        raise r.fail(f"grid {g!r} is not in grids: ({', '.join(grids)})")
    variants = grids[g].variants
    v = r.get("variant", str, next(iter(variants))) if len(variants) == 1 else r.get("variant", str)
    if v not in variants:
        raise r.fail(f"variant {v!r} is not one of grid {g}'s ({', '.join(variants)})")
    scheme = r.get("scheme", str)
    if scheme not in grids[g].schemes:
        raise r.fail(f"scheme {scheme!r} is not run by grid {g} ({', '.join(grids[g].schemes)})")
    arm = ArmSpec(g, v, scheme, r.get("key", str))
    r.done()
    return arm


_Better = TypeVar("_Better", str, str | None)


def _better(r: Reader, b: _Better) -> _Better:
    """``b`` (``better`` as read) when it is ``higher``, ``lower`` (or ``None``, not given)."""
    if b is not None and b not in ("higher", "lower"):
        raise r.fail(f"'better' = {b!r}: expected higher or lower")
    return b


def load_book(path: str | Path) -> BookSpec:
    """Read and check a book file (module docstring).

    Raises:
        ConfigError: the file cannot be read, or anything in it is malformed or refers to nothing.
    """
    path = Path(path)
    top = Reader(path, "top level", read_yaml_mapping(path, ConfigError, "book file (configs/book.yaml)"))
    head = Reader(path, "book", top.get("book", dict))
    name, preset, out = head.get("name", str), head.get("preset", str, "configs/paper.yaml"), \
        head.get("out", str, "results/book")
    records = head.get("records", str, "results/records")
    sets = names(head, "sets", [])
    if not all("=" in x for x in sets):
        raise head.fail(f"'sets' = {list(sets)!r}: expected key=value overrides")
    head.done()
    grids = {g: _grid(path, g, d, preset) for g, d in top.get("grids", dict).items()}
    if not grids:
        raise top.fail("'grids' is empty: a book runs at least one grid")
    tables = {}
    for t, d in top.get("tables", dict, {}).items():
        r = Reader(path, f"tables.{t}", d)
        grid = r.get("grid", str)
        cols = []
        for i, c in enumerate(r.get("columns", list)):
            cr = Reader(path, f"tables.{t}.columns[{i}]", c)
            label, scale = cr.get("label", str), float(cr.get("scale", (int, float), 1.0))
            digits = cr.get("digits", int, None)
            paper = cr.get("paper", str, None)
            if paper is not None:
                ptable, _, pcol = paper.partition(".")
                if ptable not in PAPER_TABLES or pcol not in next(iter(PAPER_TABLES[ptable].values())):
                    raise cr.fail(f"paper: {paper!r} is none of the paper's numbers (expected TABLE.COLUMN, e.g. "
                                  f"table1.Ours; tables {', '.join(PAPER_TABLES)})")
            arm = _arm(path, f"tables.{t}.columns[{i}]",
                       {k: v for k, v in cr.data.items() if k not in ("label", "scale", "digits", "paper")}, grids,
                       grid)
            cr.used |= {"grid", "variant", "scheme", "key"}
            cr.done()
            cols.append(ColumnSpec(label, arm.key, arm.scheme, arm.variant, arm.grid, scale, digits, paper))
        if len({c.label for c in cols}) != len(cols):
            raise r.fail("two columns share a label")
        tables[t] = TableSpec(t, r.get("title", str), grid, tuple(cols), r.get("digits", int, 2),
                              _better(r, r.get("better", str, None)))
        r.done()
    figures = {}
    for f, d in top.get("figures", dict, {}).items():
        r = Reader(path, f"figures.{f}", d)
        grid = r.get("grid", str)
        if grid not in grids:
            raise r.fail(f"grid {grid!r} is not in grids:")
        kind = r.get("kind", str)
        if kind not in FIGURE_KINDS:
            raise r.fail(f"kind {kind!r}: expected one of {', '.join(FIGURE_KINDS)}")
        variants = grids[grid].variants
        variant = r.get("variant", str, next(iter(variants)))
        if variant not in variants:
            raise r.fail(f"variant {variant!r} is not one of grid {grid}'s")
        schemes = names(r, "schemes", list(grids[grid].schemes))
        figures[f] = FigureSpec(f, r.get("title", str), grid, variant, kind, schemes)
        r.done()
    findings = {}
    for name_, d in top.get("findings", dict, {}).items():
        r = Reader(path, f"findings.{name_}", d)
        comps = []
        for i, c in enumerate(r.get("comparisons", list)):
            cr = Reader(path, f"findings.{name_}.comparisons[{i}]", c)
            a = _arm(path, f"findings.{name_}.comparisons[{i}].a", cr.get("a", dict), grids)
            b = _arm(path, f"findings.{name_}.comparisons[{i}].b", cr.get("b", dict), grids)
            comps.append(ComparisonSpec(a, b, _better(cr, cr.get("better", str)), cr.get("broadcast", bool, False)))
            cr.done()
        findings[name_] = FindingSpec(name_, r.get("claim", str), r.get("paper", str, ""), tuple(comps))
        r.done()
    bounds = []
    for i, d in enumerate(top.get("bounds", list, [])):
        r = Reader(path, f"bounds[{i}]", d)
        bound = BoundSpec(r.get("table", str), r.get("row", str), r.get("column", str), r.get("seed", int, 0),
                          float(r.get("factor", (int, float), 1.5)), r.get("ci", bool, False))
        r.done()
        if bound.table not in tables or bound.column not in {c.label for c in tables[bound.table].columns}:
            raise r.fail(f"no column {bound.column!r} in table {bound.table!r}")
        if bound.factor <= 1:
            raise r.fail(f"factor {bound.factor}: expected > 1")
        bounds.append(bound)
    top.done()
    return BookSpec(path, name, preset, out, grids, sets, tables, figures, findings, tuple(bounds), records)

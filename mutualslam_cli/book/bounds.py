"""A headline figure's bound: the one run behind a cell of the committed book, made again (:func:`rerun_bound`).

``book.json``'s ``bounds`` name, per cell, its grid, variant, scheme, seed, sequence, summary key and the hash of
the config it ran under. The run is made again from the book file's grid (its config must hash the same, else the
committed book is older than its book file and says so), and its value must lie within ``factor``× of the book's
(two-sided: ``value / factor ≤ new ≤ value · factor``) — one run per bound, so a bound costs what one run costs
(``tests/book/test_book_bounds.py`` runs them: those marked ``ci`` in CI, the rest ``slow``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mutualslam_cli.book.entries import BoundEntry
from mutualslam_cli.book.plan import part_of, plan_book, render_synth
from mutualslam_cli.book.spec import BookSpec, SequenceRef
from mutualslam_cli.config import with_overrides
from mutualslam_cli.errors import ConfigError


@dataclass
class BoundCheck:
    """A bound's outcome: the book's value, the new run's, and the interval."""

    book: float
    now: float | None
    lo: float
    hi: float

    @property
    def holds(self) -> bool:
        return self.now is not None and self.lo <= self.now <= self.hi


def interval(value: float, factor: float) -> tuple[float, float]:
    """``[value / factor, value · factor]`` (ordered for a negative value)."""
    a, b = value / factor, value * factor
    return (min(a, b), max(a, b))


def rerun_bound(bound: BoundEntry, spec: BookSpec, out: Path, registry: str | None = None,
                data_root: str | None = None) -> BoundCheck:
    """Make the run of ``bound`` again under ``out`` and compare (module docstring).

    Raises:
        ConfigError: the book file no longer has the bound's grid or variant, or its config hashes otherwise.
    """
    from mutualslam_cli.pipeline import run_sequence

    grid = bound["grid"]
    if grid not in spec.grids:
        raise ConfigError(f"bound {bound['table']}/{bound['row']}: grid {grid!r} is no longer in {spec.path}")
    plan = plan_book(spec, out, [grid], registry, data_root, render=False)
    part = part_of(plan, grid, bound["variant"])
    if part.config_hash != bound["config_hash"]:
        raise ConfigError(f"bound {bound['table']}/{bound['row']}/{bound['column']}: {spec.path} now gives grid "
                          f"{grid}/{bound['variant']} config {part.config_hash}, the committed book ran "
                          f"{bound['config_hash']}: regenerate the book (mslam book --publish)")
    s = bound["sequence"]
    ref = SequenceRef(s["name"], s.get("synth"))
    seq = str(render_synth(ref, out / "data")) if ref.synth is not None else ref.name
    cfg = with_overrides(part.cfg, adapt={"scheme": bound["scheme"]}, seed=int(bound["seed"]))
    r = run_sequence(seq, cfg, out=out / "runs", command=["bound"], registry=Path(registry) if registry else None)
    v = r.summary.number(bound["key"])
    now = None if v is None else float(v) * float(bound.get("scale", 1.0))
    lo, hi = interval(float(bound["value"]), float(bound["factor"]))
    return BoundCheck(float(bound["value"]), now, lo, hi)

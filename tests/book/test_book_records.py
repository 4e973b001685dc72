"""The committed book is its committed records: every record reads (none damaged or written by hand), every
published value is the value of its run's record, and each headline cell of ``results/book.json`` lies within its
bound's factor (1.5×, both ways) of the mean its records give. Fast: reads files only (the reruns are
``test_book_bounds.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.book.bounds import interval
from mutualslam_cli.book.readme import BOOK_JSON, REPO
from mutualslam_cli.book.records import read_record
from mutualslam_cli.book.run import read_book, records_root
from mutualslam_cli.book.spec import load_book

BOOK = read_book(BOOK_JSON)
SPEC = load_book(REPO / BOOK["book"]["file"])
ROOT = records_root(SPEC) / SPEC.name


def _record(run: str):
    return read_record(ROOT / f"{run}.json")


def _cells():
    for name, t in BOOK["tables"].items():
        for row in t["rows"]:
            if row["label"].startswith(("Average", "paper:")):
                continue
            for col, c in zip(t["columns"][1:], row["cells"]):
                yield pytest.param(c, id=f"{name}/{row['label']}/{col}")


def test_every_committed_record_reads():
    paths = sorted(ROOT.rglob("seed*.json"))
    assert paths, f"no records of book {SPEC.name} under {ROOT}"
    for p in paths:
        read_record(p)  # DamagedRecord names the file


@pytest.mark.parametrize("cell", list(_cells()))
def test_each_published_value_is_its_records(cell):
    for v in cell["values"]:
        rec = _record(v["run"])
        assert rec.seed == v["seed"]
        assert rec.config_hash == cell["config_hash"]
        assert float(rec.summary[cell["key"]]) * cell["scale"] == pytest.approx(v["value"], rel=1e-12, abs=1e-12)


def _bounds():
    return [pytest.param(b, id=f"{b['table']}/{b['row']}/{b['column']}") for b in BOOK["bounds"]]


@pytest.mark.parametrize("bound", _bounds())
def test_each_headline_cell_is_within_its_bound_of_its_records(bound):
    t = BOOK["tables"][bound["table"]]
    row = next(r for r in t["rows"] if r["label"] == bound["row"])
    cell = row["cells"][t["columns"].index(bound["column"]) - 1]
    now = [float(_record(v["run"]).summary[cell["key"]]) * cell["scale"] for v in cell["values"]]
    assert now, f"{bound['table']}/{bound['row']}/{bound['column']}: no records"
    lo, hi = interval(float(np.mean(now)), float(bound["factor"]))
    assert lo <= cell["mean"] <= hi
    seed = next(v for v in cell["values"] if v["seed"] == bound["seed"])
    assert bound["value"] == pytest.approx(seed["value"])

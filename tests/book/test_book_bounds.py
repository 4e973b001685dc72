"""Each headline figure of the committed book, bounded: the one run behind it is made again and must land within
its bound's factor of the book's value, both ways (``results/book.json``'s ``bounds``; a bound on a real sequence
is a ``data`` test, one not marked ``ci`` in the book file is ``slow``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mutualslam_cli.book.bounds import interval, rerun_bound
from mutualslam_cli.book.readme import BOOK_JSON, REPO
from mutualslam_cli.book.run import read_book
from mutualslam_cli.book.spec import load_book
from mutualslam_cli.datasets.registry import get_spec


def _bounds() -> list:
    book = read_book(BOOK_JSON)
    out = []
    for b in book["bounds"]:
        marks = ([] if b["sequence"].get("synth") else [pytest.mark.data]) + ([] if b["ci"] else [pytest.mark.slow])
        out.append(pytest.param(book["book"]["file"], b, marks=marks,
                                id=f"{book['book']['name']}:{b['table']}/{b['row']}/{b['column']}/seed{b['seed']}"))
    return out


def test_the_committed_book_has_bounds():
    assert read_book(BOOK_JSON)["bounds"]


@pytest.mark.parametrize(("book_file", "bound"), _bounds())
def test_a_headline_figure_is_reproduced_within_its_bound(book_file, bound, tmp_path, request):
    if "data" in request.node.keywords:
        request.getfixturevalue("shared_data")  # skips where the shared windows are absent
        name = bound["sequence"]["name"]
        if not Path(get_spec(name).root).exists():  # a sequence built from them (make redkitchen-whole)
            pytest.skip(f"{name} is not on this machine")
    check = rerun_bound(bound, load_book(REPO / book_file), tmp_path)
    assert check.holds, (f"{bound['table']}/{bound['row']}/{bound['column']} seed {bound['seed']}: the book has "
                         f"{check.book:.4g}, the run now {check.now}, outside [{check.lo:.4g}, {check.hi:.4g}]")


def test_the_interval_is_two_sided():
    assert interval(2.0, 1.5) == (2.0 / 1.5, 3.0)
    assert interval(-2.0, 1.5) == (-3.0, -2.0 / 1.5)

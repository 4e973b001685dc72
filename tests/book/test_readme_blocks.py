"""The README's results come from the book: its marked blocks are what the renderer makes of the committed
``results/book.json`` — a hand-edited figure there, or a book regenerated without rendering, fails here."""

from __future__ import annotations

import copy

import pytest

from mutualslam_cli.book.readme import BOOK_JSON, README, render, render_block, render_file, stale_blocks
from mutualslam_cli.book.run import read_book
from mutualslam_cli.errors import ConfigError


def test_the_readme_blocks_are_the_committed_book():
    text, book = README.read_text(encoding="utf-8"), read_book(BOOK_JSON)
    assert "<!-- book:" in text  # the mechanism is in use
    stale = stale_blocks(text, book)
    assert not stale, (f"README blocks {stale} differ from {BOOK_JSON}: run `mslam book --render-readme` "
                       "(or `make book`), never edit them by hand")


@pytest.fixture
def book():
    return read_book(BOOK_JSON)


def _one_table(book) -> str:
    return next(iter(book["tables"]))


def test_a_hand_edited_figure_is_found_and_rendering_restores_it(book, tmp_path):
    name = _one_table(book)
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\n<!-- book:{name} -->\nold\n<!-- /book:{name} -->\n\ntext after\n")
    assert render_file(readme, BOOK_JSON, check=True) == [name]
    assert render_file(readme, BOOK_JSON) == [name]
    after = readme.read_text()
    assert render_block(name, book) in after
    assert after.endswith("text after\n")
    assert render_file(readme, BOOK_JSON, check=True) == []
    edited = after.replace(book["tables"][name]["rows"][0]["cells"][0]["text"], "99.9", 1)
    assert edited != after
    assert stale_blocks(edited, book) == [name]


def test_a_block_renders_the_books_cells_and_their_provenance(book):
    name = _one_table(book)
    t = copy.deepcopy(book)
    t["tables"][name]["rows"][0]["cells"][0]["text"] = "12.3 ± 4.5"
    out = render_block(name, t)
    assert "12.3 ± 4.5" in out
    assert t["tables"][name]["title"] in out
    assert f"`{book['book']['name']}`" in out
    assert book["book"]["file"] in out


@pytest.mark.parametrize(("text", "match"), [
    ("<!-- book:nope -->\nx\n<!-- /book:nope -->\n", "no table 'nope'"),
    ("<!-- book:figure:nope -->\nx\n<!-- /book:figure:nope -->\n", "no figure 'nope'"),
    ("<!-- book:table1 -->\nx\n", "has no <!-- /book:table1 -->"),
])
def test_a_block_the_book_cannot_fill_is_one_line(book, text, match):
    with pytest.raises(ConfigError, match=match):
        render(text, book)

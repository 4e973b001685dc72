"""The README's results come from the book: every block between ``<!-- book:NAME -->`` and ``<!-- /book:NAME -->``
(each marker on a line of its own) is rendered from the committed ``results/book.json`` (:func:`render`), so no
hand-typed figure there can go stale — ``tests/book/test_readme_blocks.py`` fails when the README differs from
what this makes of it.

``NAME`` is a table of the book, ``findings`` (the verdicts), ``figure:NAME`` (a figure, from its committed copy
under ``results/figures/``) or ``time`` (the book's cost per grid). Each block ends with a provenance line: the
book's name and file, its commit, the commits and CPU kinds of the runs behind the block, so a reader sees what
made every figure. An entry the book file declares but the committed book does not hold yet (its grids have not
all run) renders as a line saying how to make it; a name the book file does not declare is an error.

    python -m mutualslam_cli.book.readme [--check] [--book results/book.json] [--readme README.md]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from mutualslam_cli.book.entries import BookJSON, CellEntry
from mutualslam_cli.config import CONFIG_DIR
from mutualslam_cli.errors import ConfigError, MslamError

REPO = CONFIG_DIR.parent
#: The committed book the README is rendered from, and the README.
BOOK_JSON = REPO / "results" / "book.json"
#: The committed copies of the published book's figures (``--publish``).
FIGURES = REPO / "results" / "figures"
README = REPO / "README.md"
#: A block: its opening and closing markers each on a line of their own (a marker quoted in prose is not one).
_BLOCK = re.compile(r"^(<!-- book:(?P<name>\S+?) -->\n)(?P<body>.*?)^(<!-- /book:(?P=name) -->)$", re.S | re.M)
_OPEN = re.compile(r"^<!-- book:(\S+?) -->$", re.M)


def _md_table(columns: list[str], rows: list[list[str]], bold: set[tuple[int, str]] | None = None) -> str:
    bold = bold or set()
    head = "| " + " | ".join(columns) + " |\n|" + "|".join("---" for _ in columns) + "|\n"
    body = "".join("| " + " | ".join(f"**{x}**" if (i, c) in bold and x != "—" else x
                                     for x, c in zip(r, columns)) + " |\n" for i, r in enumerate(rows))
    return head + body


def _cells_provenance(cells: list[CellEntry]) -> tuple[set[str], set[str], set[str]]:
    commits, devices, hashes = set(), set(), set()
    for c in cells:
        commits |= set(c.get("commits", []))
        devices |= set(c.get("devices", []))
        if c.get("config_hash"):
            hashes.add(c["config_hash"])
    return commits, devices, hashes


def _short(commits: set[str]) -> str:
    return ", ".join(sorted(c[:7] + ("-dirty" if c.endswith("-dirty") else "") for c in commits)) or "—"


def _caption(book: BookJSON, commits: set[str], devices: set[str], extra: str = "") -> str:
    b = book["book"]
    commit = b.get("commit")
    return (f"<sub>From the results book `{b['name']}` (`{b['file']}`, written {b['created_utc'][:10]} at "
            f"{_short({commit} if commit else set())}){extra}; runs of commit(s) {_short(commits)} on "
            f"{', '.join(sorted(devices)) or '—'}. `mslam book` regenerates it.</sub>\n")


def _not_yet(name: str, book: BookJSON, kind: str) -> str:
    """The text of a block the book file declares but the committed book does not hold yet (its grids have not
    all run); a name the book file does not declare either is an error.

    Raises:
        ConfigError: ``name`` is no entry of the book file.
    """
    from mutualslam_cli.book.spec import load_book

    spec = load_book(REPO / book["book"]["file"])
    entry = name[7:] if name.startswith("figure:") else name
    if entry not in ({"findings", "time"} | set(spec.tables) | set(spec.figures)):
        have = ", ".join(book.get("tables", {})) or "none"
        raise ConfigError(f"README block {name}: the book has no {kind} {entry!r} (tables: {have})")
    only = "" if entry in ("findings", "time") else f" --only {entry}"
    return f"*Not in the committed book yet: `mslam book {book['book']['file']}{only} --publish` makes it.*\n"


def render_block(name: str, book: BookJSON) -> str:
    """The Markdown of block ``name`` (module docstring).

    Raises:
        ConfigError: ``name`` is in no part of the book.
    """
    if name == "time":
        return _time(book)
    if name == "findings" and not book.get("findings"):
        return _not_yet(name, book, "findings")
    if name == "findings":
        rows, commits, devices = [], set(), set()
        for fname, f in book.get("findings", {}).items():
            for i, c in enumerate(f["comparisons"]):
                lo, hi = c["ci95"]
                mean, std = c["mean_diff"], c["std_diff"]
                rows.append([f"**{fname}** {f['claim']}" if i == 0 else "", f.get("paper", "") if i == 0 else "",
                             f"**{f['verdict']}**" if i == 0 else "",
                             f"{c['a']} vs {c['b']}", f"{c['wins']} / {c['n']}",
                             "—" if mean is None else f"{mean:.3g}" + ("" if std is None else f" ± {std:.3g}"),
                             "—" if c["sign_p"] is None else f"{c['sign_p']:.3g}",
                             "—" if lo is None else f"[{lo:.3g}, {hi:.3g}]", c["verdict"]])
            for c in f["comparisons"]:
                commits |= set(c.get("commits", []))
                devices |= set(c.get("devices", []))
        first = next(iter(book.get("findings", {}).values()), None)
        rule = first.get("rule", "") if first is not None else ""
        return (_md_table(["finding", "the paper", "verdict", "comparison (a vs b)", "wins / N", "mean ± std of a − b",
                           "sign p",
                           "95 % CI", "comparison"], rows)
                + f"\n<sub>Rule: {rule}.</sub>\n" + _caption(book, commits, devices))
    if name.startswith("figure:"):
        fig = book.get("figures", {}).get(name[7:])
        if fig is None:
            return _not_yet(name, book, "figure")
        return (f"![{fig['title']}]({FIGURES.relative_to(REPO).as_posix()}/{fig['file']})\n\n*{fig['title']}*, drawn "
                f"from {len(fig['runs'])} runs (grid `{fig['grid']}`, variant `{fig['variant']}`, config "
                f"`{fig['config_hash']}`).\n" + _caption(book, set(fig["commits"]), set(fig["devices"])))
    t = book.get("tables", {}).get(name)
    if t is None:
        return _not_yet(name, book, "table")
    rows = [[r["label"], *(c["text"] for c in r["cells"])] for r in t["rows"]]
    cells = [c for r in t["rows"] for c in r["cells"]]
    commits, devices, hashes = _cells_provenance(cells)
    codes = sorted({x[:8] for c in cells for x in c.get("codes", [])})
    bold = {(int(i), str(c)) for i, c in t.get("bold", [])}
    mixed = sorted({k for c in cells if len(c.get("cpu_kinds", [])) > 1 for k in c["cpu_kinds"]})
    note = f"; ‡ seeds from more than one CPU kind ({', '.join(mixed)})" if mixed else ""
    return (f"{t['title']}\n\n" + _md_table(t["columns"], rows, bold) + "\n"
            + _caption(book, commits, devices, f", config(s) {', '.join(sorted(hashes))}"
                       + (f", code {', '.join(codes)}" if codes else "") + note))


def _time(book: BookJSON) -> str:
    """The book's cost: per grid of the book file, its jobs, the runs' hours (one thread each, from their records)
    and their CPU kinds; a grid the committed book does not hold yet is named with its jobs on the required
    sequences."""
    from mutualslam_cli.book.spec import load_book

    spec = load_book(REPO / book["book"]["file"])
    rows, total, n, missing = [], 0.0, 0, 0
    for g, grid in spec.grids.items():
        d = book.get("grids", {}).get(g)
        if d is None:
            many = len([x for x in grid.schemes if x not in grid.one_seed])
            per = (many * len(grid.seeds) + len(grid.one_seed)) * len(grid.variants)
            jobs = len(grid.sequences) * per
            rows.append([g, f"{jobs}" + (f" + {per} per whole sequence present" if grid.when_present else ""),
                         "not run yet", "—"])
            missing += jobs
            continue
        jobs = sum(v["jobs"] for v in d["variants"].values())
        secs = d.get("seconds")
        rows.append([g, str(jobs), "—" if secs is None else f"{secs / 3600:.2f}",
                     ", ".join(d.get("cpu_kinds", [])) or "—"])
        total += secs or 0.0
        n += jobs
    rows.append(["all", f"{n} run" + (f", {missing} to run" if missing else ""), f"{total / 3600:.2f}", ""])
    return (_md_table(["grid", "jobs", "hours of runs (one thread each)", "CPU kinds"], rows)
            + "\n" + _caption(book, set(book["book"].get("commits", [])), set(book["book"].get("devices", []))))


def render(readme: str, book: BookJSON) -> str:
    """``readme`` with every marked block rendered from ``book``.

    Raises:
        ConfigError: a block names nothing in the book, or an opening marker has no closing one.
    """
    opened = _OPEN.findall(readme)
    closed = {m.group("name") for m in _BLOCK.finditer(readme)}
    unclosed = [n for n in opened if n not in closed]
    if unclosed:
        raise ConfigError(f"README: <!-- book:{unclosed[0]} --> has no <!-- /book:{unclosed[0]} --> after it")
    return _BLOCK.sub(lambda m: m.group(1) + "\n" + render_block(m.group("name"), book) + "\n" + m.group(4), readme)


def stale_blocks(readme: str, book: BookJSON) -> list[str]:
    """The names of the blocks whose text differs from what :func:`render` makes of ``book``."""
    want = {m.group("name"): m.group("body") for m in _BLOCK.finditer(render(readme, book))}
    return [m.group("name") for m in _BLOCK.finditer(readme) if m.group("body") != want[m.group("name")]]


def render_file(readme: Path = README, book_json: Path = BOOK_JSON, check: bool = False) -> list[str]:
    """Rewrite ``readme``'s blocks from ``book_json`` (``check``: only say which differ); the blocks changed."""
    from mutualslam_cli.atomic import atomic_write_text
    from mutualslam_cli.book.run import read_book

    text = readme.read_text(encoding="utf-8")
    book = read_book(book_json)
    stale = stale_blocks(text, book)
    if stale and not check:
        atomic_write_text(readme, render(text, book))
    return stale


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mutualslam_cli.book.readme", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only report the blocks that differ (exit 1 if any)")
    ap.add_argument("--book", type=Path, default=BOOK_JSON)
    ap.add_argument("--readme", type=Path, default=README)
    a = ap.parse_args(argv)
    try:
        stale = render_file(a.readme, a.book, a.check)
    except MslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    verb = "differ from the book" if a.check else "rewritten"
    print(f"{len(stale)} block(s) {verb}" + (f": {', '.join(stale)}" if stale else ""))
    return 1 if a.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())

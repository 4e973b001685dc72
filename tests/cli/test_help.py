"""``--help`` of every command: its docstring's paragraphs wrapped by the terminal, never where the source broke
a line."""

from __future__ import annotations

import inspect
import itertools
import re
from typing import Any

import pytest
import typer
from rich.cells import cell_len
from typer.testing import CliRunner

from mutualslam_cli.cli import app

runner = CliRunner()
WIDTHS = (80, 64)
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _commands() -> list[tuple[str, ...]]:
    """The path of every command and group of ``mslam`` (the root is ``()``)."""
    out: list[tuple[str, ...]] = []

    def walk(cmd: Any, path: tuple[str, ...]) -> None:
        out.append(path)
        if hasattr(cmd, "list_commands"):  # a group (typer's own copy of click's)
            ctx = cmd.context_class(cmd)
            for name in cmd.list_commands(ctx):
                walk(cmd.get_command(ctx, name), path + (name,))

    walk(typer.main.get_command(app), ())
    assert len(out) > 10, out
    return out


def _command(path: tuple[str, ...]) -> Any:
    cmd = typer.main.get_command(app)
    for name in path:
        cmd = cmd.get_command(cmd.context_class(cmd), name)
    return cmd


def _help(path: tuple[str, ...], width: int) -> list[str]:
    r = runner.invoke(app, [*path, "--help"], env={"COLUMNS": str(width), "TERMINAL_WIDTH": str(width)})
    assert r.exit_code == 0, r.output
    return [_ANSI.sub("", line).rstrip() for line in r.output.splitlines()]


def _description(lines: list[str]) -> list[list[str]]:
    """The paragraphs between the usage line and the first panel, each a list of its lines (left-stripped)."""
    start = next(i for i, ln in enumerate(lines) if ln.strip().startswith("Usage:")) + 1
    end = next((i for i, ln in enumerate(lines) if ln.startswith("╭")), len(lines))
    paragraphs: list[list[str]] = [[]]
    for ln in lines[start:end]:
        if ln.strip():
            paragraphs[-1].append(ln.strip())
        elif paragraphs[-1]:
            paragraphs.append([])
    return [p for p in paragraphs if p]


def _early_breaks(paragraph: list[str], avail: int) -> list[str]:
    """Line pairs where the next line's first word would have fit on the line before it: a hard break that the
    terminal did not choose (a greedy wrap at ``avail`` columns never leaves one)."""
    bad = []
    for line, nxt in itertools.pairwise(paragraph):
        word = nxt.split()[0]
        if cell_len(line) + 1 + cell_len(word) <= avail:
            bad.append(f"{line!r} / {nxt!r}")
    return bad


def _command_panel_rows(lines: list[str]) -> list[list[str]]:
    """Each command's help in the ``Commands`` panel as its lines, with the column's width appended last."""
    try:
        top = next(i for i, ln in enumerate(lines) if ln.startswith("╭─ Commands"))
    except StopIteration:
        return []
    body = []
    for ln in lines[top + 1:]:
        if ln.startswith("╰"):
            break
        body.append(ln)
    first = body[0][1:].lstrip()  # "│ name   help …   │"
    start = len(body[0]) - len(first) + len(first.split()[0])
    start += len(body[0][start:]) - len(body[0][start:].lstrip())
    avail = body[0].rindex("│") - 1 - start
    rows: list[list[str]] = []
    for ln in body:
        text = ln[start:ln.rindex("│")].strip()
        if ln[1:start].strip():  # a new command's name: a new row
            rows.append([text])
        else:
            rows[-1].append(text)
    return [r + [str(avail)] for r in rows]


@pytest.mark.parametrize("width", WIDTHS)
def test_every_help_wraps_where_the_terminal_does(width: int):
    """Each paragraph of a command's docstring is in its ``--help`` (whitespace aside), and neither the
    description nor a group's command list breaks a line before the terminal's edge."""
    problems = []
    for path in _commands():
        lines = _help(path, width)
        where = "mslam " + " ".join(path) + " --help"
        cmd = _command(path)
        doc = inspect.getdoc(getattr(cmd, "callback", None)) or cmd.help or ""
        shown = " ".join(" ".join(lines).split())
        for paragraph in re.split(r"\n\s*\n", doc.partition("\f")[0].strip()):
            if paragraph and " ".join(paragraph.split()) not in shown:
                problems.append(f"{where}: paragraph missing: {paragraph[:60]!r}…")
        for paragraph in _description(lines):
            problems += [f"{where}: early break {b}" for b in _early_breaks(paragraph, width - 2)]
        for row in _command_panel_rows(lines):
            problems += [f"{where} (commands): early break {b}" for b in _early_breaks(row[:-1], int(row[-1]))]
    assert not problems, "\n".join(problems)


def test_the_check_sees_a_hard_break():
    """The checker itself: a break that leaves room for the next word is named, a full line is not."""
    assert _early_breaks(["the sequences, the results", "folder (with its _cache/)"], 78)
    assert not _early_breaks(["a" * 70, "folder"], 76)

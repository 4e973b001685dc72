"""What every ``mslam`` command shares: the typer app with the one error boundary
(:class:`~mutualslam_cli.errors.MslamError` → one red line and exit code 1; anything else, including
the programming errors :class:`~mutualslam_cli.errors.ShapeError` and
:class:`~mutualslam_cli.errors.TransitionError`, keeps its traceback), the rich consoles, the common
options, the progress bar and value formatting."""

from __future__ import annotations

import inspect
import logging
import re
import unicodedata
from pathlib import Path
from typing import Any

import typer
from rich.console import Console, ConsoleDimensions
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from typer.core import TyperGroup

from mutualslam_cli.config import RunConfig, load_config, with_overrides
from mutualslam_cli.errors import MslamError

#: Columns of output that goes to a file or a pipe, where rich would otherwise use 80 and wrap wide
#: tables (the paper's tables are up to ~250 columns); ``$COLUMNS``, when set, wins.
PIPED_WIDTH = 400


class _Console(Console):
    """A rich Console that is :data:`PIPED_WIDTH` columns wide while its stream is not a terminal
    (checked at each print, so a redirected or captured ``sys.stdout`` counts) and ``$COLUMNS`` is unset.
    Only the getter of ``Console.size`` is replaced; its setter stays."""

    @Console.size.getter  # type: ignore[attr-defined]
    def size(self) -> ConsoleDimensions:
        dims = Console.size.fget(self)  # type: ignore[attr-defined]
        return ConsoleDimensions(PIPED_WIDTH, dims.height) if self._width is None and not self.is_terminal else dims


console = _Console(stderr=False)
err_console = _Console(stderr=True)

ConfigOpt = typer.Option(None, "--config", "-c",
                         help="YAML config (default configs/default.yaml; the paper's values: configs/paper.yaml).")
SetOpt = typer.Option(None, "--set", "-s", help="Override one field: section.key=value (repeatable).")
DataRootOpt = typer.Option(None, "--data-root", help="Root of relative datasets.yaml paths (default $MSLAM_DATA).")
RegistryOpt = typer.Option(None, "--registry", help="Another datasets.yaml.")
DeviceOpt = typer.Option(None, "--device", help="Where the depth network runs: auto (CUDA when available), cpu, "
                                                "cuda or cuda:N (default from config: auto).")
ResultsOutOpt = typer.Option(None, "--out", help="Results root (default results/).")


_LINE_BREAKS = re.compile(r"\s*[\r\n\x0b\x0c\x85\u2028\u2029]+\s*")


def one_line(text: str) -> str:
    """``text`` as one line with every character visible: line breaks (an upstream library's multi-line
    message) folded into `` | ``, other control and format characters (escape sequences, tabs, bidi
    overrides, NUL) written as ``\\xNN`` / ``\\uNNNN``."""
    text = _LINE_BREAKS.sub(" | ", text.strip())
    return "".join(c if unicodedata.category(c) not in ("Cc", "Cf") else
                   (f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}") for c in text)


def shown(text: object) -> str:
    """The one rule for printing text that may come from outside (URLs, server reasons, ETags, archive member
    names, file contents quoted in a message): :func:`one_line`, then rich markup escaped, so that ``[/x]``
    prints as itself instead of raising ``MarkupError`` or styling the line."""
    return escape(one_line(str(text)))


def reflowed(text: str | None) -> str | None:
    """A command's help as typer should get it: each paragraph (blank-line separated) on one line.

    Docstrings wrap at the source's line length, but typer in rich markup mode keeps a single line break
    everywhere except in the first paragraph of a command's own ``--help``, so a later paragraph, and the
    first one in a group's command list, would break mid-sentence wherever the source did. A paragraph that
    starts with ``\\b`` (click's "do not rewrap" mark) keeps its lines; text after ``\\f`` is left as it is."""
    if not text:
        return text
    body, cut, rest = inspect.cleandoc(text).partition("\f")
    paragraphs = [p if p.startswith("\b") else " ".join(line.strip() for line in p.splitlines())
                  for p in re.split(r"\n\s*\n", body.strip())]
    return "\n\n".join(paragraphs) + (("\n" + cut + rest) if cut else "")


class Commands(TyperGroup):
    """The command group with the one error boundary: a user error (:class:`MslamError`) raised by any
    command becomes one red line and exit code 1; anything else (a bug) keeps its traceback. Its own help and
    its commands' are :func:`reflowed`, so the terminal, not the source, decides where a line breaks."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.help = reflowed(self.help)
        for command in self.commands.values():
            command.help = reflowed(command.help)

    def invoke(self, ctx: Any) -> Any:  # the Context of typer's click: typer >= 0.2x vendors one (typer._click)
        try:
            return super().invoke(ctx)
        except MslamError as e:
            err_console.print(f"[bold red]error:[/] {shown(e)}", highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None


app = typer.Typer(cls=Commands, add_completion=False, no_args_is_help=True,
                  help="Monocular SLAM with an online-adapted depth network: runs, ablations, paper tables.")


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details.")) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
                        handlers=[RichHandler(console=err_console, show_path=False, show_time=False)])


def config_from(config: Path | None, sets: list[str] | None, data_root: str | None = None,
                device: str | None = None) -> RunConfig:
    """The run config of a command: ``--config`` (default the paper's), ``--set`` overrides, ``--data-root``,
    ``--device``."""
    cfg = load_config(config, sets or [])
    if data_root:
        cfg = with_overrides(cfg, data={"data_root": data_root})
    if device:
        cfg = with_overrides(cfg, device=device)
    return cfg


def progress_bar() -> Progress:
    """The progress display every long command uses (a bar per task, with a text field ``info``)."""
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console, transient=False)


def progress_figure(v: object) -> float | None:
    """A progress callback's figure (frames done, a total) as a bar takes it; ``None`` where the stage gave none
    (the bar keeps its own)."""
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def fmt_value(v: object, nd: int = 3) -> str:
    """A value of a run's summary for the terminal: ``—`` for none, a float with ``nd`` decimals."""
    if v is None:
        return "—"
    if isinstance(v, float):  # a count averaged over seeds stays a count when it is whole
        return str(int(v)) if v.is_integer() and abs(v) >= 10 else f"{v:.{nd}f}"
    return str(v)



"""The figure of ``mslam report`` a reader looks at first: depth accuracy over frames, and the
plotting helpers the report's figures share.

:func:`accuracy_figure` is the paper's Fig. ``ablation_err``: one panel per sequence, x the frame
index, y the running mean over frames ``0..t`` of the adapted model's percent correct depth, each
frame scored by the model of its time (``per_frame.csv``'s ``online_pcd_lsq_running``: δ < 0.1,
per-frame least-squares scaling; :mod:`~mutualslam_cli.online.scores`) — the final model's
``adapted_pcd_lsq_running`` for runs without online scores, said in the legend — one line per
scheme (and config) = the mean over seeds with a min–max band over seeds, and the pre-trained
model dashed grey. Each scheme keeps its colour (:data:`SCHEME_COLOURS`) in every figure.

The trajectory figures: :mod:`mutualslam_cli.report.trajectories`.
"""

from __future__ import annotations

import hashlib
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_path

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn (:func:`pyplot`)
    from matplotlib.artist import Artist
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.typing import LineStyleType

#: Fixed colour of each scheme (paper Fig. ablation_err: methods 1-4 are recent, replay, ewc, replay+ewc).
SCHEME_COLOURS: dict[str, str] = {
    "none": "#000000", "recent": "#d62728", "replay": "#1f77b4", "ewc": "#ff7f0e",
    "replay+ewc": "#2ca02c", "replay+mas": "#9467bd", "replay+si": "#8c564b",
}
#: Colours of scheme names not in :data:`SCHEME_COLOURS` (picked by a hash of the name).
EXTRA_COLOURS = ("#e377c2", "#17becf", "#bcbd22", "#393b79", "#ad494a", "#637939")
PRETRAINED_COLOUR = "#7f7f7f"
#: Line styles of the configs of one scheme (first config solid); the pre-trained model is dashed.
LINE_STYLES: tuple[LineStyleType, ...] = ("-", "-.", ":", (0, (3, 1, 1, 1, 1, 1)))


def scheme_colour(name: str) -> str:
    """The colour of scheme ``name``: :data:`SCHEME_COLOURS`, else one of :data:`EXTRA_COLOURS`
    chosen by the name's MD5 (the same in every run of the program)."""
    if name in SCHEME_COLOURS:
        return SCHEME_COLOURS[name]
    return EXTRA_COLOURS[int(hashlib.md5(name.encode()).hexdigest(), 16) % len(EXTRA_COLOURS)]


def by_scheme(runs: pd.DataFrame) -> list[tuple[tuple[str, str], pd.DataFrame]]:
    """``runs`` grouped by (scheme, config), schemes in the order of :data:`SCHEME_COLOURS` first."""
    order = list(SCHEME_COLOURS)
    return sorted(runs.groupby(["scheme", "config"]),
                  key=lambda kv: (order.index(kv[0][0]) if kv[0][0] in order else len(order), kv[0][0], kv[0][1]))


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (imported on the first figure; a module has no type to name)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig: Figure, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    pyplot().close(fig)


#: Share of a figure's width that a caption line or a legend row may take (the rest: margins).
TEXT_WIDTH_SHARE = 0.96


def text_width(fig: Figure, text: str, fontsize: float) -> float:
    """Width of ``text``'s widest line at ``fontsize`` points, in pixels of ``fig`` at its dpi (as its
    ``bbox``), measured by the figure's renderer."""
    from matplotlib.font_manager import FontProperties

    canvas = cast("FigureCanvasAgg", fig.canvas)  # every figure is drawn on Agg (:func:`pyplot`); stubs say only Base
    renderer, font = canvas.get_renderer(), FontProperties(size=fontsize)
    return max(renderer.get_text_width_height_descent(line, font, ismath=False)[0] for line in text.split("\n"))


def fit_width(fig: Figure, text: str, fontsize: float, share: float = TEXT_WIDTH_SHARE) -> str:
    """``text`` re-wrapped at its spaces so that every line fits in ``share`` of ``fig``'s width at ``fontsize``
    (a word longer than that stays whole on its own line). The ratio of text to figure width does not change
    with the dpi, so a caption fitted here fits in the PNG saved at any dpi."""
    room = share * fig.bbox.width
    lines: list[str] = []
    for word in text.split():
        if lines and text_width(fig, f"{lines[-1]} {word}", fontsize) <= room:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return "\n".join(lines)


def legend_columns(fig: Figure, labels: list[str], fontsize: float, most: int,
                   share: float = TEXT_WIDTH_SHARE) -> int:
    """How many columns (at most ``most``) a figure legend of ``labels`` at ``fontsize`` may have so that a
    row fits in ``share`` of ``fig``'s width: every column as wide as the widest entry, with matplotlib's
    default handle (2 em), handle-text pad (0.8 em), column spacing (2 em) and border (2 × 0.4 em)."""
    if not labels:
        return 1
    em = fontsize * fig.dpi / 72.0
    column = 2.8 * em + max(text_width(fig, label, fontsize) for label in labels)
    fits = int((share * fig.bbox.width - 0.8 * em + 2.0 * em) // (column + 2.0 * em))
    return max(1, min(most, len(labels), fits))


def with_config(runs: pd.DataFrame) -> pd.DataFrame:
    seed = pd.to_numeric(runs["seed"], errors="coerce") if "seed" in runs else pd.Series(np.nan, index=runs.index)
    return runs.assign(config=runs["config"].fillna("") if "config" in runs else "", _seed=seed)


# --------------------------------------------------------------------------- accuracy over frames


def _running(run: pd.Series, model: str) -> pd.Series | None:
    """``<model>_pcd_lsq_running`` of a run indexed by frame (None without it): its ``curve.<model>`` column where
    the row carries one (a results book's record), else from its folder's ``per_frame.csv``."""
    kept = run.get(f"curve.{model}")
    if isinstance(kept, pd.Series):
        return kept
    f = Path(run["folder"]) / "per_frame.csv"
    if not f.is_file():
        return None
    pf = pd.read_csv(f)
    col = f"{model}_pcd_lsq_running"
    if col not in pf or "frame" not in pf:
        return None
    return pd.Series(pd.to_numeric(pf[col], errors="coerce").to_numpy(), index=pf["frame"].to_numpy())


def accuracy_figure(runs: pd.DataFrame) -> Figure | None:
    """The running-accuracy figure of :func:`collect`'s runs (see the module docstring).

    Returns:
        A matplotlib Figure with one axes per sequence (row-major, at most 3 columns; each
        line's ``gid`` is ``"<scheme>|<config>"`` or ``"pretrained"``), or None when no run has
        a ``per_frame.csv`` with the running columns.
    """
    runs = with_config(runs)
    seqs = [s for s in sorted(runs["sequence.name"].unique())
            if any(_running(r, "adapted") is not None for _, r in runs[runs["sequence.name"] == s].iterrows())]
    if not seqs:
        return None
    plt = pyplot()
    ncols = 2 if len(seqs) == 4 else min(len(seqs), 3)
    nrows = -(-len(seqs) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.7 * nrows + 1.0), squeeze=False,
                             layout="constrained")
    handles: dict[str, Artist] = {}
    drawn: set[str] = set()  # "online" (model of each frame's time) and/or "final" (runs without online scores)
    max_seeds = 1
    styles: dict[tuple[str, str], LineStyleType] = {}  # one line style per (scheme, config) in every panel
    for (scheme, config), _ in by_scheme(runs):
        styles[(scheme, config)] = LINE_STYLES[sum(k[0] == scheme for k in styles) % len(LINE_STYLES)]
    for ax, seq in zip(axes.flat, seqs):
        sub = runs[runs["sequence.name"] == seq]
        pre = [c for c in (_running(r, "pretrained") for _, r in sub.iterrows()) if c is not None]
        if pre:
            m = pd.concat(pre, axis=1).mean(axis=1)
            (h,) = ax.plot(m.index, m.to_numpy(), "--", color=PRETRAINED_COLOUR, lw=1.6, gid="pretrained",
                           label="pre-trained")
            handles.setdefault("pre-trained", h)
        for (scheme, config), g in by_scheme(sub):
            online = [_running(r, "online") for _, r in g.iterrows()]
            curves = [c for c in online if c is not None]
            if not curves:
                curves = [c for c in (_running(r, "adapted") for _, r in g.iterrows()) if c is not None]
                drawn.add("final")
            else:
                drawn.add("online")
            if not curves:
                continue
            both = pd.concat(curves, axis=1)
            mean = both.mean(axis=1)
            label = textwrap.fill(scheme + (f" [{config}]" if config else ""), 70, subsequent_indent="    ")
            colour = scheme_colour(scheme)
            (h,) = ax.plot(mean.index, mean.to_numpy(), linestyle=styles[(scheme, config)], color=colour, lw=1.6,
                           gid=f"{scheme}|{config}", label=label)
            if len(curves) > 1:
                ax.fill_between(mean.index, both.min(axis=1).to_numpy(), both.max(axis=1).to_numpy(),
                                color=colour, alpha=0.18, linewidth=0)
                max_seeds = max(max_seeds, len(curves))
            handles.setdefault(label, h)
        ax.set_title(seq, fontsize=11)
        ax.set_xlabel("frame")
        ax.set_ylabel("running mean PCD (%)")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(seqs):]:
        ax.set_visible(False)
    what = (f"line: mean over seeds, band: min–max over seeds (up to {max_seeds})" if max_seeds > 1
            else "one seed per line")
    widest = max(len(line) for label in handles for line in label.splitlines())
    ncol = legend_columns(fig, list(handles), 9, most=4 if widest < 30 else 2 if widest < 60 else 1)
    caption = f"{_drawn(drawn)}, PCD δ<0.1 (per-frame lsq scaling) averaged over frames 0..t; {what}"
    fig.legend(list(handles.values()), list(handles), loc="outside lower center", ncol=ncol,
               fontsize=9, frameon=False, title=fit_width(fig, caption, 9), title_fontsize=9)
    fig.suptitle("Depth accuracy over frames per adaptation scheme", fontsize=12)
    return fig


def _drawn(drawn: set[str]) -> str:
    """The legend's words for what the adapted lines show."""
    if drawn == {"final"}:
        return "final model on every frame"
    if drawn == {"online"}:
        return "each frame by the model of its time (online)"
    return "online where the run has it, else the final model"


def plot_accuracy(runs: pd.DataFrame, path: Path) -> bool:
    """:func:`accuracy_figure` saved as a PNG at ``path``; False (nothing written) without data."""
    fig = accuracy_figure(runs)
    if fig is None:
        return False
    save_png(fig, Path(path))
    return True

"""Paper-style tables and plots from result folders (DESIGN §8).

``collect`` (:mod:`~mutualslam_cli.report.runs`) finds complete runs (folders with ``summary.json``)
and their ``config.yaml``, skipping damaged ones with a note, ``build_tables`` turns them into pandas
DataFrames shaped like the paper's tables (mean over seeds, with the seed count), and ``write_report``
saves each table as Markdown, LaTeX and CSV plus PNG plots, and the notes in ``report.md``. Values that a
run could not compute stay empty (``NaN`` → "—", an empty CSV cell), never 0; so does a value that is
not a finite number, with a note.

Runs whose resolved configs differ (other than seed, scheme and output; thread counts count) are
never averaged together: every table gets a ``config`` column naming the settings that differ
(e.g. ``ba.culling=False``). Nor are runs from different devices (``run.device_label`` of their
summary, e.g. ``cuda · NVIDIA H100`` or ``cpu · AVX2``: the ``run_device`` column of the config label),
whatever their ``device`` setting said (``auto`` resolves per machine).
Paper Table 4 (``ate_ba``: ATE of the front end, bridged, after BA) and
Table 5 (``map_ba``: map points and e_si with and without BA and culling, per ``vo.max_fts``)
are built by :func:`table_ate_ba` and :func:`table_map_ba`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.report.budget import BUDGET_TITLE, budget_table, frontier_figure
from mutualslam_cli.report.columns import cell_text, numeric
from mutualslam_cli.report.dense import TITLE as DENSE_TITLE
from mutualslam_cli.report.dense import dense_figures, dense_table
from mutualslam_cli.report.forgetting import FORGETTING_TABLE
from mutualslam_cli.report.maps import map_figures
from mutualslam_cli.report.paper import paper_tables
from mutualslam_cli.report.pictures import run_pictures
from mutualslam_cli.report.plots import plot_accuracy
from mutualslam_cli.report.runs import IGNORED_CONFIG, collect, config_labels  # noqa: F401 - collect: re-exported
from mutualslam_cli.report.slam_tables import SLAM_TABLES, shown
from mutualslam_cli.report.trajectories import trajectory_figures
from mutualslam_cli.types import Scalar

if TYPE_CHECKING:
    from mutualslam_cli.report.paired import PairedResult

log = logging.getLogger(__name__)

#: table name → (title, [(column label, summary key)])
TABLES: dict[str, tuple[str, list[tuple[str, str]]]] = {
    "depth": ("Percent correct depth (%, δ<0.1) and e_si of depth maps, final model on every frame with GT depth", [
        ("PCD lsq pre", "depth.pcd.lsq.pretrained"), ("PCD lsq adapt", "depth.pcd.lsq.adapted"),
        ("PCD med pre", "depth.pcd.median.pretrained"), ("PCD med adapt", "depth.pcd.median.adapted"),
        ("e_si pre", "depth.esi.pretrained"), ("e_si adapt", "depth.esi.adapted"),
    ]),
    "depth_nonkf": ("What generalises: the same metrics over frames the adaptation never saw (non-keyframes)", [
        ("PCD lsq pre", "depth.pcd_nonkf.lsq.pretrained"), ("PCD lsq adapt", "depth.pcd_nonkf.lsq.adapted"),
        ("PCD med pre", "depth.pcd_nonkf.median.pretrained"), ("PCD med adapt", "depth.pcd_nonkf.median.adapted"),
        ("e_si pre", "depth.esi_nonkf.pretrained"), ("e_si adapt", "depth.esi_nonkf.adapted"),
    ]),
    **FORGETTING_TABLE,  # backward transfer by quarter
    "trajectory": ("ATE RMSE (m), one Sim(3) over the whole trajectory (KF: keyframes); 'per segment': each "
                   "tracking segment aligned on its own (a secondary figure); segments the front end started, "
                   "relocalisations it made, frames it lost by reason, segments the adaptation bridged or merged, "
                   "the map units the run ended in", [
        ("KF, VO", "trajectory.ate_rmse_m.vo"), ("KF, bridged", "trajectory.ate_rmse_m.bridged"),
        ("KF, after BA", "trajectory.ate_rmse_m.ba"), ("all frames", "trajectory.ate_rmse_m.all_frames"),
        ("KF, VO per segment", "trajectory.ate_rmse_m_per_segment.vo"), ("tracked", "vo.tracked_fraction"),
        ("segments", "vo.segments"), ("relocalised", "vo.relocalisations"),
        ("lost: tracks", "vo.frames_lost.too_few_tracks"), ("lost: alignment", "vo.frames_lost.failed_alignment"),
        ("lost: init", "vo.frames_lost.failed_init"), ("bridged", "vo.bridges"), ("merged", "vo.merges"),
        ("map units", "vo.live.map_units"), ("keyframes", "vo.keyframes"),
        ("scale max/min VO", "trajectory.local_scale.vo.max_over_min"),
    ]),
    **SLAM_TABLES,  # scale drift, loop recall
    "map": ("Map points and their e_si", [
        ("points VO", "map.points.vo"), ("points culled", "map.points.culled"), ("points BA", "map.points.ba"),
        ("e_si VO", "map.esi.vo"), ("e_si culled", "map.esi.culled"), ("e_si BA", "map.esi.ba"),
    ]),
    "runtime": ("Runtime; an optimiser step's wall time (median, p99, max) and the steps' sum over steps × median "
                "(1.0 without a stall)", [
        ("VO fps", "timing.vo_fps"), ("depth ms", "timing.depth_ms"), ("fine-tune ms/step", "timing.finetune_ms"),
        ("step p99 ms", "timing.step_ms.p99"), ("step max ms", "timing.step_ms.max"),
        ("steps / (n × median)", "timing.steps_over_median"), ("fine-tune ms/keyframe", "timing.finetune_kf_ms"),
        ("BA s", "timing.ba_s"), ("total s", "timing.total_s"),
    ]),
}


@dataclass
class Report:
    """Collected runs and the tables built from them."""

    runs: pd.DataFrame
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    titles: dict[str, str] = field(default_factory=dict)
    bold: dict[str, set[tuple[int, str]]] = field(default_factory=dict)  # (row, column) bold in LaTeX
    csv: dict[str, pd.DataFrame] = field(default_factory=dict)  # numeric CSV where the table shows text
    notes: list[str] = field(default_factory=list)  # runs skipped, values left empty (report.md's Notes)
    extra_csv: dict[str, pd.DataFrame] = field(default_factory=dict)  # <name>.csv only (e.g. every pair)


def build_tables(runs: pd.DataFrame, notes: list[str] | None = None) -> Report:
    """Mean over seeds per (sequence, scheme, config) for every table in :data:`TABLES`, the scheme
    ablation, and paper Tables 4 (``ate_ba``) and 5 (``map_ba``); ``notes``: :func:`collect`'s."""
    rep = Report(runs=runs, notes=list(notes or []))
    runs = runs.assign(config=runs.get("config", ""))
    varied = bool((runs["config"] != "").any())
    g = runs.groupby(["sequence.name", "scheme", "config"], sort=True)
    for name, (title, cols) in ((n, tc) for n, tc in TABLES.items() if shown(n, runs)):
        data = {}
        for label, key in cols:
            if key in runs:
                data[label] = g[key].apply(lambda s: pd.to_numeric(s, errors="coerce").mean())
            else:
                data[label] = g.size() * np.nan
        t = pd.DataFrame(data)
        t["seeds"] = g.size()
        t.index.names = ["sequence", "scheme", "config"]
        t = t.reset_index()
        rep.tables[name] = t if varied else t.drop(columns="config")
        rep.titles[name] = title
    budget = budget_table(runs)  # only when configs differ
    if budget is not None:
        rep.tables["budget"], rep.titles["budget"] = budget, BUDGET_TITLE
    dense = dense_table(runs)  # only when some run ran the dense stage
    if dense is not None:
        rep.tables["dense"], rep.titles["dense"] = dense if varied else dense.drop(columns="config"), DENSE_TITLE
    for name, key, what in (("ablation", "depth.pcd.lsq.adapted", "every frame"),
                            ("ablation_nonkf", "depth.pcd_nonkf.lsq.adapted", "non-keyframes only")):
        if key not in runs:
            continue
        abl = runs.assign(v=pd.to_numeric(runs[key], errors="coerce")).pivot_table(
            index=["scheme", "config"] if varied else "scheme", columns="sequence.name", values="v",
            aggfunc="mean", dropna=False)
        abl.columns.name = None
        rep.tables[name] = abl.reset_index()
        rep.titles[name] = f"Scheme ablation: PCD (%, lsq scaling) of the final model per sequence, {what}"
    for name, build in (("ate_ba", table_ate_ba), ("map_ba", table_map_ba)):
        rep.tables[name], rep.titles[name], rep.bold[name] = build(runs)
    paper = paper_tables(runs)  # the paper's Tables 1-6 first, in the paper's shape
    rep.tables = {**{t.name: t.display for t in paper}, **rep.tables}
    for t in paper:
        rep.titles[t.name], rep.bold[t.name], rep.csv[t.name] = t.title, t.bold, t.numeric
    return rep


def _mean(v: pd.Series) -> float:
    return float(v.mean()) if v.notna().any() else float("nan")


#: Table 4's columns: each part of the system credited on its own (``trajectory.credit.*``, the same frames).
CREDIT = (("VO", "vo"), ("bridged", "bridged"), ("+ culling + BA", "ba"))
#: ... and the column from the runs of the same config with ``loop.enabled``: their map after BA and loop closure.
LOOP_COLUMN = "+ loop closure"


def _seeded(r: pd.DataFrame, cols: dict[str, str]) -> pd.DataFrame:
    """Per seed (the run's seed, else its folder), the ``{column: summary key}`` values, mean over duplicates."""
    seed = r["seed"].fillna(r["folder"]) if "seed" in r else r["folder"]
    return pd.DataFrame({c: numeric(r, k) for c, k in cols.items()}).assign(_seed=seed.values).groupby("_seed").mean()


def table_ate_ba(runs: pd.DataFrame) -> tuple[pd.DataFrame, str, set[tuple[int, str]]]:
    """Paper Table 4, crediting each part: the ATE (m, one Sim(3)) of the frames every column tracked, for
    the front end on its own (``VO``), joined by the run's bridges and nothing else (``bridged``), after
    culling + global BA (``trajectory.credit.*``) and, from the runs of the same config with
    ``loop.enabled`` (paired by seed), after BA and loop closure; per sequence, then their Average.

    One block of rows per (scheme, config) (columns ``scheme`` / ``config`` only when there are several;
    ``loop.enabled`` does not split blocks, it makes the last column). Cells are paired by seed: every
    column of a row is the mean over the same seeds — those that have every column; when none has an
    after-BA value (no BA requested), that cell is "—" and the others are over all seeds. ``n`` counts
    the seeds averaged. The Average row averages the sequences that have every value.

    Returns:
        ``(table, title, bold)``; ``bold``: ``(row, column)`` of the lowest ATE of each row.
    """
    # config.yaml's flag as YAML read it: True, False, or NaN where a run's config has no loop section
    looped = runs["config.loop.enabled"].eq(True) if "config.loop.enabled" in runs else \
        pd.Series(False, index=runs.index)
    labels = config_labels(runs, exclude=("loop.enabled",)) if any(c.startswith("config.") for c in runs) else \
        runs.get("config", pd.Series("", index=runs.index))
    runs = runs.assign(config=labels.values)
    cols = [c for c, _ in CREDIT] + ([LOOP_COLUMN] if looped.any() else [])
    rows: list[dict[str, Scalar]] = []
    for (scheme, config), b in runs.groupby(["scheme", "config"], sort=True):
        seqs: list[dict[str, float]] = []  # per sequence of the block: column → mean
        for seq, r in b.groupby("sequence.name", sort=True):
            on = looped.loc[r.index]
            base = r[~on] if (~on).any() else r
            vals = _seeded(base, {c: f"trajectory.credit.{k}" for c, k in CREDIT})
            if LOOP_COLUMN in cols:
                vals = vals.join(_seeded(r[on], {LOOP_COLUMN: "trajectory.credit.ba"}), how="left") if on.any() \
                    else vals.assign(**{LOOP_COLUMN: np.nan})
            paired = vals.dropna()
            use = paired if len(paired) else vals.dropna(subset=["VO", "bridged"])
            seqs.append({c: _mean(use[c]) for c in cols})
            rows.append({"Sequence": seq, "scheme": scheme, "config": config, "n": len(use), **seqs[-1]})
        full = [x for x in seqs if all(np.isfinite(x[c]) for c in cols)]
        avg: dict[str, Scalar] = {"scheme": scheme, "config": config, "n": ""}
        for c in cols:  # no sequence with every value: each column over its own
            have = full or [x for x in seqs if np.isfinite(x[c])]
            avg[c] = float(np.mean([x[c] for x in have])) if have else float("nan")
        k = len(full) if full else max(sum(np.isfinite(x[c]) for x in seqs) for c in cols)
        rows.append({"Sequence": "Average" if k == len(seqs) else f"Average ({k} of {len(seqs)})", **avg})
    t = pd.DataFrame(rows, columns=["Sequence", "scheme", "config", *cols, "n"])
    bold = set()
    for i, x in t.iterrows():
        present = [c for c in cols if np.isfinite(x[c])]
        if len(present) > 1:
            best = min(x[c] for c in present)
            bold |= {(int(i), c) for c in present if cell_text(x[c]) == cell_text(best)}
    schemes = sorted(runs["scheme"].unique())
    t = t.drop(columns=[c for c, keep in (("scheme", len(schemes) > 1), ("config", (runs["config"] != "").any()))
                        if not keep])
    title = ("Paper Table 4, each part credited: ATE RMSE (m, one Sim(3) each) of the frames every column "
             "tracked — the front end alone, joined by its bridges, after culling + global BA"
             + (", after BA and loop closure (loop.enabled runs)" if LOOP_COLUMN in cols else "")
             + (f", scheme {schemes[0]}" if len(schemes) == 1 else "")
             + "; mean over the n seeds that have every column; — : no BA requested")
    return t, title, bold


#: Paper Table 5's rows: (BA, MP culling, summary stage, which runs).
MAP_ROWS = (("", "", "vo", "all"), ("", "✓", "culled", "culled"), ("✓", "", "ba", "ba_only"),
            ("✓", "✓", "ba", "ba_culled"))


def _fts_key(v: str) -> tuple[int, float, str]:
    try:
        return (0, float(v), "")
    except (TypeError, ValueError):
        return (1, 0.0, str(v))


def table_map_ba(runs: pd.DataFrame) -> tuple[pd.DataFrame, str, set[tuple[int, str]]]:
    """Paper Table 5: number of map points and map e_si per sequence, rows (BA, MP culling,
    ``vo.max_fts``).

    Rows per ``max_fts`` (from each run's ``config.yaml``; ``?`` without one): no BA, no culling =
    ``map.{points,esi}.vo`` (the front end's map, one value per seed even when runs with and
    without culling share it); culling only = ``map.*.culled``; BA without culling =
    ``map.*.ba`` of runs that culled nothing (``ba.culling=false``, or scheme ``none``);
    BA + culling = ``map.*.ba`` of runs that culled. Separate blocks per scheme and per any
    other config difference (``config``). A cell is the mean over seeds that have it; ``n``:
    seeds per sequence ("a/b" when sequences differ).
    """
    cull = numeric(runs, "map.points.culled").notna()
    ba = numeric(runs, "map.points.ba").notna()
    member = {"all": ba | ~ba, "culled": cull, "ba_only": ba & ~cull, "ba_culled": ba & cull}
    fts = runs["config.vo.max_fts"] if "config.vo.max_fts" in runs else pd.Series(None, index=runs.index)
    runs = runs.assign(_rest=config_labels(runs, exclude=("ba.culling", "ba.enabled", "vo.max_fts")),
                       _fts=fts.map(lambda v: "?" if v is None or v != v else str(v)),
                       _seed=runs["seed"].fillna(runs["folder"]) if "seed" in runs else runs["folder"])
    seqs = sorted(runs["sequence.name"].unique())
    blocks = sorted(runs.groupby(["scheme", "_rest", "_fts"]).groups,
                    key=lambda k: (k[0], k[1], _fts_key(k[2])))
    rows = []
    for scheme, rest, f in blocks:
        b = runs[(runs["scheme"] == scheme) & (runs["_rest"] == rest) & (runs["_fts"] == f)]
        for ba_mark, cull_mark, stage, who in MAP_ROWS:
            sel = b[member[who].loc[b.index]]
            row: dict[str, Scalar] = {"scheme": scheme, "config": rest, "BA": ba_mark, "MP culling": cull_mark,
                                   "max_fts": f}
            ns = []
            for seq in seqs:
                r = sel[sel["sequence.name"] == seq]
                per_seed = pd.DataFrame({"points": numeric(r, f"map.points.{stage}"),
                                         "esi": numeric(r, f"map.esi.{stage}"), "seed": r["_seed"]})
                per_seed = per_seed.groupby("seed").mean()
                row[f"{seq} points"], row[f"{seq} e_si"] = _mean(per_seed["points"]), _mean(per_seed["esi"])
                ns.append(len(per_seed))
            row["n"] = str(ns[0]) if len(set(ns)) == 1 else "/".join(map(str, ns))
            rows.append(row)
    t = pd.DataFrame(rows)
    schemes = sorted(runs["scheme"].unique())
    t = t.drop(columns=[c for c, keep in (("scheme", len(schemes) > 1), ("config", (runs["_rest"] != "").any()))
                        if not keep])
    title = ("Paper Table 5: number of map points and map e_si (log depth vs GT at the host pixel) without and "
             "with BA and map-point culling, per vo.max_fts" + (f", scheme {schemes[0]}" if len(schemes) == 1 else "")
             + "; mean over n seeds")
    return t, title, set()


def to_markdown(t: pd.DataFrame) -> str:
    """GitHub Markdown table ("—" for values a run could not compute)."""
    head = "| " + " | ".join(map(str, t.columns)) + " |"
    sep = "|" + "|".join("---" for _ in t.columns) + "|"
    body = ["| " + " | ".join(cell_text(v) for v in row) + " |" for row in t.itertuples(index=False)]
    return "\n".join([head, sep, *body]) + "\n"


def _align(col: pd.Series) -> str:
    """``c`` for check-mark columns, ``r`` for numbers (empty cells allowed), else ``l``."""
    vals = [v for v in col if not (isinstance(v, str) and v == "")]
    if all(v == "✓" for v in vals):
        return "c"
    return "r" if all(isinstance(v, (int, float, np.number)) for v in vals) else "l"


def to_latex(t: pd.DataFrame, caption: str, bold: set[tuple[int, str]] | None = None) -> str:
    """A booktabs ``tabular`` ("--" for missing values; ``bold``: ``(row, column)`` cells in bold;
    a rule above an ``Average`` row)."""
    def esc(s: str) -> str:
        return (str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&").replace("—", "--")
                .replace("✓", r"\checkmark").replace("±", r"$\pm$").replace("δ", r"$\delta$"))

    bold = bold or set()
    lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{esc(caption)}}}",
             r"\begin{tabular}{" + "".join(_align(t[c]) for c in t.columns) + "}", r"\toprule",
             " & ".join(esc(c) for c in t.columns) + r" \\", r"\midrule"]
    for i, row in enumerate(t.itertuples(index=False)):
        if str(row[0]).startswith("Average"):
            lines.append(r"\midrule")
        cells = [esc(cell_text(v)) for v in row]
        lines.append(" & ".join(rf"\textbf{{{x}}}" if (i, c) in bold else x for x, c in zip(cells, t.columns))
                     + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def _finite_csv(t: pd.DataFrame, name: str, notes: list[str]) -> str:
    """``t`` as CSV, a number that is not finite (a mean that overflowed) as an empty cell, with a note."""
    num = t.select_dtypes("number")
    bad = num.apply(lambda c: ~np.isfinite(c) & c.notna())
    if not bad.any().any():
        return t.to_csv(index=False)
    for col in bad.columns[bad.any()]:
        notes.append(f"{name}: column {col!r} had a value that is not a finite number; its cell is left empty")
    return t.mask(bad.reindex(columns=t.columns, fill_value=False)).to_csv(index=False)


def write_report(rep: Report, out_dir: Path) -> list[Path]:
    """Write every table as ``<name>.md``, ``<name>.tex``, ``<name>.csv``, the figures (accuracy over
    frames, trajectories, maps, dense, depth of chosen frames), and ``report.md``
    with every table and figure; return the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    md = []
    for name, t in rep.tables.items():
        atomic_write_text(out_dir / f"{name}.csv", _finite_csv(rep.csv.get(name, t), f"{name}.csv", rep.notes))
        atomic_write_text(out_dir / f"{name}.tex", to_latex(t, rep.titles[name], rep.bold.get(name)))
        atomic_write_text(out_dir / f"{name}.md", f"### {rep.titles[name]}\n\n" + to_markdown(t))
        md.append(f"## {rep.titles[name]}\n\n" + to_markdown(t))
        written += [out_dir / f"{name}.{e}" for e in ("csv", "tex", "md")]
    for name, t in rep.extra_csv.items():
        atomic_write_text(out_dir / f"{name}.csv", _finite_csv(t, f"{name}.csv", rep.notes))
        written.append(out_dir / f"{name}.csv")
    acc = out_dir / "accuracy_over_frames.png"
    figures = [acc] if plot_accuracy(rep.runs, acc) else []
    traj, notes = trajectory_figures(rep.runs, out_dir)
    figures += traj + map_figures(rep.runs, out_dir)
    figures += dense_figures(rep.runs, out_dir) + run_pictures(rep.runs, out_dir, "depth")
    figures += run_pictures(rep.runs, out_dir, "scale_drift")
    if frontier_figure(rep.tables.get("budget"), out_dir / "frontier.png"):
        figures.append(out_dir / "frontier.png")
    md.append("## Figures\n\n" + "".join(f"{n}\n\n" for n in notes)
              + "".join(f"![{f.stem}]({f.relative_to(out_dir).as_posix()})\n\n" for f in figures))
    if rep.notes:
        md.append("## Notes\n\n" + "".join(f"- {n}\n" for n in rep.notes))
    atomic_write_text(out_dir / "report.md", "# mslam report\n\n" + "\n".join(md))
    return written + [out_dir / "report.md"] + figures


def add_paired(rep: Report, comparisons: list[str], metric: str, better: str | None = None,
               broadcast: bool = False) -> list[PairedResult]:
    """``mslam report --pair``: the paired comparisons (:mod:`~mutualslam_cli.report.paired`, ``"A vs B"`` each)
    as table ``paired`` and every pair as ``paired_pairs.csv``; returns the results.

    Raises:
        ConfigError: a malformed comparison, or one with no pair of runs.
    """
    from mutualslam_cli.report.paired import RULE, paired_table, parse_pair

    table, pairs, results = paired_table(rep.runs, [parse_pair(c, metric) for c in comparisons], better, broadcast)
    rep.tables["paired"] = table
    rep.titles["paired"] = ("Paired comparisons: a − b over runs of the same sequence and seed (identical pairs once; "
                            "wins: a better), exact two-sided sign test, seeded paired-bootstrap 95 % CI; " + RULE)
    rep.extra_csv["paired_pairs"] = pairs
    return results

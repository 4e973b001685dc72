"""Paper-style tables and plots from result folders (DESIGN §8).

``collect`` finds complete runs (folders with ``summary.json``), ``build_tables`` turns them into
pandas DataFrames shaped like the paper's tables (mean over seeds, with the seed count), and
``write_report`` saves each table as Markdown, LaTeX and CSV plus PNG plots. Values that a run
could not compute stay empty (``NaN`` → "—"), never 0.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mutualslam_cli import results as res
from mutualslam_cli.errors import DatasetError

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
    "trajectory": ("ATE RMSE (m), Sim(3)-aligned", [
        ("KF, VO", "trajectory.ate_rmse_m.vo"), ("KF, after BA", "trajectory.ate_rmse_m.ba"),
        ("all frames", "trajectory.ate_rmse_m.all_frames"), ("tracked", "vo.tracked_fraction"),
        ("keyframes", "vo.keyframes"),
    ]),
    "map": ("Map points and their e_si", [
        ("points VO", "map.points.vo"), ("points culled", "map.points.culled"), ("points BA", "map.points.ba"),
        ("e_si VO", "map.esi.vo"), ("e_si culled", "map.esi.culled"), ("e_si BA", "map.esi.ba"),
    ]),
    "runtime": ("Runtime", [
        ("VO fps", "timing.vo_fps"), ("depth ms", "timing.depth_ms"), ("fine-tune ms/step", "timing.finetune_ms"),
        ("fine-tune ms/keyframe", "timing.finetune_kf_ms"),
        ("BA s", "timing.ba_s"), ("total s", "timing.total_s"),
    ]),
}


@dataclass
class Report:
    """Collected runs and the tables built from them."""

    runs: pd.DataFrame
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    titles: dict[str, str] = field(default_factory=dict)


def collect(paths: list[str | Path]) -> pd.DataFrame:
    """One row per complete run found under ``paths`` (flattened summary keys + ``folder``).

    Raises:
        DatasetError: a path does not exist, or no complete run is found.
    """
    rows: list[dict[str, Any]] = []
    for p in map(Path, paths):
        if not p.exists():
            raise DatasetError(f"{p}: no such results folder")
        for s in sorted(p.rglob("summary.json")):
            d = res.flatten(res.read_summary(s.parent))
            d["folder"] = str(s.parent)
            parts = s.parent.parts
            d.setdefault("sequence.name", parts[-3] if len(parts) >= 3 else "?")
            d.setdefault("scheme", parts[-2] if len(parts) >= 2 else "?")
            rows.append(d)
    if not rows:
        raise DatasetError(f"{', '.join(map(str, paths))}: no complete run (no summary.json found)")
    return pd.DataFrame(rows)


def build_tables(runs: pd.DataFrame) -> Report:
    """Mean over seeds per (sequence, scheme) for every table in :data:`TABLES`, plus the scheme ablation."""
    rep = Report(runs=runs)
    g = runs.groupby(["sequence.name", "scheme"], sort=True)
    for name, (title, cols) in TABLES.items():
        data = {}
        for label, key in cols:
            if key in runs:
                data[label] = g[key].apply(lambda s: pd.to_numeric(s, errors="coerce").mean())
            else:
                data[label] = g.size() * np.nan
        t = pd.DataFrame(data)
        t["seeds"] = g.size()
        t.index.names = ["sequence", "scheme"]
        rep.tables[name] = t.reset_index()
        rep.titles[name] = title
    for name, key, what in (("ablation", "depth.pcd.lsq.adapted", "every frame"),
                            ("ablation_nonkf", "depth.pcd_nonkf.lsq.adapted", "non-keyframes only")):
        if key not in runs:
            continue
        abl = runs.assign(v=pd.to_numeric(runs[key], errors="coerce")).pivot_table(
            index="scheme", columns="sequence.name", values="v", aggfunc="mean", dropna=False)
        abl.columns.name = None
        rep.tables[name] = abl.reset_index()
        rep.titles[name] = f"Scheme ablation: PCD (%, lsq scaling) of the final model per sequence, {what}"
    return rep


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    if isinstance(v, (float, np.floating)):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def to_markdown(t: pd.DataFrame) -> str:
    """GitHub Markdown table ("—" for values a run could not compute)."""
    head = "| " + " | ".join(map(str, t.columns)) + " |"
    sep = "|" + "|".join("---" for _ in t.columns) + "|"
    body = ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in t.itertuples(index=False)]
    return "\n".join([head, sep, *body]) + "\n"


def to_latex(t: pd.DataFrame, caption: str) -> str:
    """A booktabs ``tabular`` ("--" for missing values)."""
    def esc(s: str) -> str:
        return str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&").replace("—", "--")

    lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{esc(caption)}}}",
             r"\begin{tabular}{" + "l" * 2 + "r" * (len(t.columns) - 2) + "}", r"\toprule",
             " & ".join(esc(c) for c in t.columns) + r" \\", r"\midrule"]
    lines += [" & ".join(esc(_fmt(v)) for v in row) + r" \\" for row in t.itertuples(index=False)]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def plot_accuracy(runs: pd.DataFrame, path: Path) -> bool:
    """Running PCD (lsq) over frames per run, one panel per sequence. Returns False if nothing to plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seqs = sorted(runs["sequence.name"].unique())
    fig, axes = plt.subplots(1, len(seqs), figsize=(5 * len(seqs), 3.6), squeeze=False)
    drawn = False
    for ax, s in zip(axes[0], seqs):
        for _, r in runs[runs["sequence.name"] == s].iterrows():
            f = Path(r["folder"]) / "per_frame.csv"
            if not f.is_file():
                continue
            pf = pd.read_csv(f)
            for model, style in (("adapted", "-"), ("pretrained", ":")):
                col = f"{model}_pcd_lsq_running"
                if col in pf and not (model == "pretrained" and r["scheme"] != runs["scheme"].iloc[0]):
                    ax.plot(pf["frame"], pf[col], style, label=f"{r['scheme']} {model}")
                    drawn = True
        ax.set_title(s)
        ax.set_xlabel("frame")
        ax.set_ylabel("running PCD (%, lsq)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    if drawn:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drawn


def plot_trajectories(runs: pd.DataFrame, path: Path) -> bool:
    """Top view (x–z) of each run's keyframe trajectory (map frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seqs = sorted(runs["sequence.name"].unique())
    fig, axes = plt.subplots(1, len(seqs), figsize=(4 * len(seqs), 4), squeeze=False)
    drawn = False
    for ax, s in zip(axes[0], seqs):
        r = runs[runs["sequence.name"] == s].iloc[0]
        f = Path(r["folder"]) / "traj_all.txt"
        if f.is_file() and f.stat().st_size:
            xyz = np.loadtxt(f, comments="#", ndmin=2)[:, 1:4]
            ax.plot(xyz[:, 0], xyz[:, 2], "-", lw=1)
            drawn = True
        ax.set_title(s)
        ax.set_aspect("equal", adjustable="datalim")
    fig.tight_layout()
    if drawn:
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drawn


def write_report(rep: Report, out_dir: Path) -> list[Path]:
    """Write every table as ``<name>.md``, ``<name>.tex``, ``<name>.csv`` and the plots; return the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    md = []
    for name, t in rep.tables.items():
        res.atomic_write_text(out_dir / f"{name}.csv", t.to_csv(index=False))
        res.atomic_write_text(out_dir / f"{name}.tex", to_latex(t, rep.titles[name]))
        res.atomic_write_text(out_dir / f"{name}.md", f"### {rep.titles[name]}\n\n" + to_markdown(t))
        md.append(f"## {rep.titles[name]}\n\n" + to_markdown(t))
        written += [out_dir / f"{name}.{e}" for e in ("csv", "tex", "md")]
    res.atomic_write_text(out_dir / "report.md", "# mslam report\n\n" + "\n".join(md))
    written.append(out_dir / "report.md")
    if plot_accuracy(rep.runs, out_dir / "accuracy_over_frames.png"):
        written.append(out_dir / "accuracy_over_frames.png")
    if plot_trajectories(rep.runs, out_dir / "trajectories.png"):
        written.append(out_dir / "trajectories.png")
    return written

"""The fine-tuning budget across configs: what each config cost beside the depth it gave, and the
speed/accuracy frontier figure (``mslam ablate --config configs/frontier.yaml``).

Cost is the adaptation stage's: its optimiser steps (``adaptation.steps``), the median step
(``timing.finetune_ms``), their product, and the stage's and the run's seconds. A config is on the
frontier when no other config of the same scheme is both cheaper (adaptation seconds) and better
(PCD, lsq scaling, every frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.report.plots import pyplot, save_png

BUDGET_TITLE = ("Fine-tuning budget per config: PCD (%, final model; mean over sequences of the mean over seeds) and "
                "cost (seconds summed over sequences, mean over seeds; step ms: median over runs)")

#: Columns of the budget table: label → (summary key, how sequences combine: mean or sum).
PCD_COLUMNS = {"PCD lsq": "depth.pcd.lsq.adapted", "PCD median": "depth.pcd.median.adapted",
               "PCD non-kf lsq": "depth.pcd_nonkf.lsq.adapted", "PCD non-kf median": "depth.pcd_nonkf.median.adapted",
               "PCD online lsq": "depth.pcd_online.lsq"}
COST_COLUMNS = {"steps": "adaptation.steps", "adaptation s": "timing.stage_s.adaptation", "total s": "timing.total_s"}


def _per_sequence(sub: pd.DataFrame, key: str) -> pd.Series:
    """Mean over seeds per sequence of ``key`` (NaN where absent)."""
    if key not in sub:
        return pd.Series(dtype=float)
    return sub.assign(v=pd.to_numeric(sub[key], errors="coerce")).groupby("sequence.name")["v"].mean()


def budget_table(runs: pd.DataFrame) -> pd.DataFrame | None:
    """One row per (scheme, config) of the fine-tuning schemes (not ``none``), when the configs differ;
    ``None`` otherwise. Only sequences every config of the scheme ran are counted, so rows compare."""
    if "adaptation.steps" not in runs or "config" not in runs or runs["config"].nunique() < 2:
        return None
    runs = runs[runs["scheme"] != "none"]  # a run with 0 steps (realtime, keyframes too close) still counts
    rows = []
    for scheme, by_scheme in runs.groupby("scheme"):
        common = set.intersection(*(set(g["sequence.name"]) for _, g in by_scheme.groupby("config")))
        for config, sub in by_scheme[by_scheme["sequence.name"].isin(common)].groupby("config"):
            row = {"scheme": scheme, "config": short_label(config) if config else "(as configured)",
                   "sequences": len(common), "runs": len(sub)}
            row.update({label: _per_sequence(sub, key).mean() for label, key in PCD_COLUMNS.items()})
            row["step ms"] = float(pd.to_numeric(sub["timing.finetune_ms"], errors="coerce").median())
            row.update({label: _per_sequence(sub, key).sum() for label, key in COST_COLUMNS.items()})
            row["step ms × steps (s)"] = row["step ms"] * row["steps"] / 1000.0
            rows.append(row)
    if not rows:
        return None
    t = pd.DataFrame(rows)
    t["frontier"] = False
    for _, g in t.groupby("scheme"):
        for i, r in g.iterrows():
            beaten = ((g["adaptation s"] <= r["adaptation s"]) & (g["PCD lsq"] > r["PCD lsq"])).any()
            t.loc[i, "frontier"] = not beaten
    return t.sort_values(["scheme", "adaptation s"]).reset_index(drop=True)


def short_label(config: str) -> str:
    """A config label without the keys at their default (the paper's) value and without ``adapt.``:
    ``"adapt.lr=0.0002, adapt.steps_per_keyframe=4, adapt.train_width=0"`` → ``"lr=0.0002 steps_per_keyframe=4"``."""
    defaults = to_dict(RunConfig())
    kept = []
    for pair in filter(None, (p.strip() for p in config.split(", "))):
        key, _, value = pair.partition("=")
        node: object = defaults
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if str(node) != value:
            kept.append(pair.removeprefix("adapt."))
    return " ".join(kept) or "paper values"


def frontier_figure(table: pd.DataFrame | None, path: Path) -> bool:
    """PCD (lsq, every frame) against adaptation seconds, one point per config, the frontier joined;
    ``False`` (nothing written) without a budget table."""
    if table is None or table.empty:
        return False
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for scheme, g in table.groupby("scheme"):
        pts = ax.scatter(g["adaptation s"], g["PCD lsq"], label=scheme, zorder=3)
        front = g[g["frontier"]].sort_values("adaptation s")
        ax.plot(front["adaptation s"], front["PCD lsq"], color=pts.get_facecolor()[0], lw=1, zorder=2)
    middle = table["adaptation s"].max() / 2  # the x axis starts at 0
    for _, r in table.iterrows():  # a label reads away from the nearer side edge, so it stays in the figure
        right = r["adaptation s"] <= middle
        ax.annotate(r["config"], (r["adaptation s"], r["PCD lsq"]), fontsize=6, xytext=(3 if right else -3, 3),
                    textcoords="offset points", ha="left" if right else "right")
    ax.set_xlabel(f"adaptation stage, seconds (sum over {int(table['sequences'].max())} sequences)")
    ax.set_ylabel("PCD % (lsq scaling, final model)")
    ax.set_title("Fine-tuning budget: speed/accuracy frontier")
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_png(fig, path)
    plt.close(fig)
    return bool(np.isfinite(table["PCD lsq"]).any())

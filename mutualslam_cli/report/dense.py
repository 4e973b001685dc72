"""The dense reconstruction's place in ``mslam report``.

:func:`dense_table` averages, per (sequence, scheme, config), the ``dense.*`` scores of the runs that
ran the dense stage (``mslam run --set dense.enabled=true`` or ``mslam fuse``); :func:`dense_figures`
copies the ``dense.png`` of the lowest seed of each into ``<report>/dense/``. Runs without the stage
are left out of both (no table when none has it).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.report.columns import numeric, slug

#: (column label, summary key) of the dense table.
COLUMNS = (
    ("acc pre m", "dense.accuracy_m.pretrained"), ("acc adapt m", "dense.accuracy_m.adapted"),
    ("comp pre m", "dense.completeness_m.pretrained"), ("comp adapt m", "dense.completeness_m.adapted"),
    ("F@5cm pre", "dense.fscore_5cm.pretrained"), ("F@5cm adapt", "dense.fscore_5cm.adapted"),
    ("P@5cm adapt", "dense.precision_5cm.adapted"), ("R@5cm adapt", "dense.recall_5cm.adapted"),
    ("frames", "dense.frames"), ("dense s", "dense.time_s"),
)
TITLE = ("Dense reconstruction: TSDF meshes of each model's depth along the run's poses (Sim(3) to GT, metres) "
         "against GT depth fused with GT poses; accuracy / completeness = mean distance (m), F-score, precision "
         "and recall at 5 cm (Tanks and Temples); mean over seeds")


def dense_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs that ran the dense stage (``dense.time_s`` set)."""
    return runs[numeric(runs, "dense.time_s").notna()]


def dense_table(runs: pd.DataFrame) -> pd.DataFrame | None:
    """One row per (sequence, scheme, config): the mean of each column of :data:`COLUMNS` over the seeds
    that have it, and ``seeds`` (runs with the stage); ``None`` when no run has the stage."""
    runs = dense_runs(runs.assign(config=runs["config"] if "config" in runs else ""))
    if runs.empty:
        return None
    rows = []
    for (seq, scheme, config), g in runs.groupby(["sequence.name", "scheme", "config"], sort=True):
        row = {"sequence": seq, "scheme": scheme, "config": config}
        for label, key in COLUMNS:
            v = numeric(g, key)
            row[label] = float(v.mean()) if v.notna().any() else float("nan")
        row["seeds"] = len(g)
        rows.append(row)
    return pd.DataFrame(rows)


def dense_figures(runs: pd.DataFrame, out_dir: Path) -> list[Path]:
    """``dense.png`` of the lowest seed of every (sequence, scheme, config) with the stage, copied to
    ``out_dir/dense/dense_<sequence>_<scheme>[_<config>]_seed<k>.png``; returns the files written."""
    runs = dense_runs(runs.assign(config=runs["config"] if "config" in runs else ""))
    runs = runs.assign(_seed=numeric(runs, "seed"))
    written = []
    for (seq, scheme, config), g in runs.groupby(["sequence.name", "scheme", "config"], sort=True):
        r = g.sort_values("_seed", na_position="last").iloc[0]
        src = Path(r["folder"]) / "dense.png"
        if not src.is_file():
            continue
        seed = "" if r["_seed"] != r["_seed"] else f"seed{int(r['_seed'])}"
        name = "_".join(x for x in ("dense", slug(seq), slug(scheme), slug(config)[:60], seed) if x)
        dst = Path(out_dir) / "dense" / f"{name}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
        written.append(dst)
    return written

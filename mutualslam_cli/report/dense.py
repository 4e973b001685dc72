"""The dense reconstruction's place in ``mslam report``.

:func:`dense_table` averages, per (sequence, scheme, config) and depth scaling, the ``dense.*`` scores of
the runs that ran the dense stage (``mslam run --set dense.enabled=true`` or ``mslam fuse``): one row per
scaling (:mod:`~mutualslam_cli.dense.scaling`: one VO scale per sequence, each frame's VO scale, each
frame scaled to GT as an oracle), next to each other, so shape and scale consistency can be told apart.
:func:`dense_figures` copies the ``dense.png`` of the lowest seed of each into ``<report>/dense/``. Runs
without the stage are left out of both (no table when none has it).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from mutualslam_cli.report.columns import numeric
from mutualslam_cli.report.pictures import run_pictures

#: Summary key prefix of each depth scaling, in the order of the rows: the keys the dense stage writes
#: (:data:`mutualslam_cli.dense.scaling.PREFIX`; the report reads files, it does not import the domain).
PREFIX = {"sequence": "dense.", "frame": "dense.frame_scale.", "gt": "dense.gt_scale."}
#: (column label, summary key after the scaling's :data:`PREFIX`) of the dense table: ``dense.<key>`` for
#: the sequence scaling, ``dense.frame_scale.<key>``, ``dense.gt_scale.<key>``.
COLUMNS = (
    ("acc pre m", "accuracy_m.pretrained"), ("acc adapt m", "accuracy_m.adapted"),
    ("comp pre m", "completeness_m.pretrained"), ("comp adapt m", "completeness_m.adapted"),
    ("F@5cm pre", "fscore_5cm.pretrained"), ("F@5cm adapt", "fscore_5cm.adapted"),
    ("P@5cm adapt", "precision_5cm.adapted"), ("R@5cm adapt", "recall_5cm.adapted"),
    ("ln-scale std pre", "metric_scale_log_std.pretrained"), ("ln-scale std adapt", "metric_scale_log_std.adapted"),
    ("fallback frames", "fallback_frames.adapted"),
)
#: (column label, summary key) of the whole stage, the same in every scaling's row.
RUN_COLUMNS = (("frames", "dense.frames"), ("dense s", "dense.time_s"))
#: The ``scaling`` column's text for each scaling.
SCALING_LABELS = {"sequence": "sequence (VO)", "frame": "per frame (VO)", "gt": "per frame to GT (oracle)"}
TITLE = ("Dense reconstruction: TSDF meshes of each model's depth along the run's poses (Sim(3) to GT, metres) "
         "against GT depth fused with GT poses, one row per depth scaling: 'sequence (VO)' = one scale per "
         "model and sequence from the VO's sparse points (the headline); 'per frame (VO)' = each frame's own "
         "sparse-point scale (frames without map points take the sequence scale: 'fallback frames'); "
         "'per frame to GT (oracle)' = each frame scaled by median(GT / prediction), not available to SLAM. "
         "Sequence vs per frame: scale consistency; per frame to GT: shape. Accuracy / completeness = mean "
         "distance (m), F-score, precision and recall at 5 cm (Tanks and Temples); ln-scale std = spread of "
         "the per-frame scales (log); mean over seeds")


def dense_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs that ran the dense stage (``dense.time_s`` set)."""
    return runs[numeric(runs, "dense.time_s").notna()]


def dense_table(runs: pd.DataFrame) -> pd.DataFrame | None:
    """One row per (sequence, scheme, config) and scaling (``scaling`` column, :data:`SCALING_LABELS`): the
    mean of each column of :data:`COLUMNS` and :data:`RUN_COLUMNS` over the seeds that have it, and
    ``seeds`` (runs with the stage). A per-frame scaling no run of the group scored (left out of
    ``dense.scalings``, or a run from before them) has no row; ``None`` when no run has the stage."""
    runs = dense_runs(runs.assign(config=runs.get("config", "")))
    if runs.empty:
        return None

    def mean(g: pd.DataFrame, key: str) -> float:
        v = numeric(g, key)
        return float(v.mean()) if v.notna().any() else float("nan")

    rows = []
    for (seq, scheme, config), g in runs.groupby(["sequence.name", "scheme", "config"], sort=True):
        for s in PREFIX:
            row = {"sequence": seq, "scheme": scheme, "config": config, "scaling": SCALING_LABELS[s]}
            row.update({label: mean(g, PREFIX[s] + key) for label, key in COLUMNS})
            if s != "sequence" and all(row[label] != row[label] for label, _ in COLUMNS[:8]):
                continue  # no score of this scaling in any seed
            row.update({label: mean(g, key) for label, key in RUN_COLUMNS})
            row["seeds"] = len(g)
            rows.append(row)
    return pd.DataFrame(rows)


def dense_figures(runs: pd.DataFrame, out_dir: Path) -> list[Path]:
    """``dense.png`` of the lowest seed of every (sequence, scheme, config) with the stage, copied to
    ``out_dir/dense/dense_<sequence>_<scheme>[_<config>]_seed<k>.png``; returns the files written."""
    return run_pictures(dense_runs(runs), out_dir, "dense")

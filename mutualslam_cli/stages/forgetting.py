"""Forgetting as a figure (DESIGN §10, issue 46): the final model's PCD over each quarter of the sequence beside
the pre-trained model's and the model of each frame's time (the online score).

Continual learning reports *backward transfer*: how a model that has learnt on later data does on earlier data
(Lopez-Paz & Ranzato 2017, "Gradient Episodic Memory", §4: BWT = R_T,i − R_i,i). Here the "tasks" are the
sequence's quarters, by frame index (frames ``[q·N/4, (q+1)·N/4)`` of the N frames), and two figures are kept
per run, PCD lsq in percentage points (mean over the quarter's evaluated frames):

* ``depth.bwt.vs_online`` = final − online on the first quarter: the final model against the models that had
  just learnt those frames (negative: it forgot some of it);
* ``depth.bwt.vs_pretrained`` = final − pre-trained on the first quarter: negative means the final model ends
  *below where it started* on the place it saw first; the run's notes say so.

The online score of a frame is that of the model of its time (:mod:`~mutualslam_cli.online.scores`), so on the
first quarter it is the early models' score; a flattering choice it is not (it is the lower baseline for BWT
when the model improves with time).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mutualslam_cli.results.summary import Summary

#: The models whose quarters are summarised, and their per-frame PCD lsq column in ``per_frame.csv``.
COLUMNS = {"pretrained": "pretrained_pcd_lsq", "adapted": "adapted_pcd_lsq", "online": "online_pcd_lsq"}
QUARTERS = ("q1", "q2", "q3", "q4")


def quarter_means(table: pd.DataFrame, column: str, n_frames: int) -> list[float | None]:
    """Mean of ``table[column]`` over the rows whose ``frame`` lies in each quarter of ``n_frames`` frames.

    Args:
        table: per-frame rows with a ``frame`` column (the sequence's frame index).
        column: the per-frame value (e.g. ``adapted_pcd_lsq``, percent).
        n_frames: the sequence's length in frames (the quarters are of the sequence, not of the evaluated rows).

    Returns:
        Four means; ``None`` for a quarter without a finite value (no evaluated frame with GT depth there).

    >>> t = pd.DataFrame({"frame": [0, 1, 2, 3, 4, 5, 6, 7], "x": [1.0, 3.0, 5.0, 5.0, 6.0, np.nan, 8.0, 10.0]})
    >>> quarter_means(t, "x", 8)
    [2.0, 5.0, 6.0, 9.0]
    """
    if column not in table or not len(table) or n_frames <= 0:
        return [None] * 4
    q = np.minimum((table["frame"].to_numpy() * 4) // max(n_frames, 1), 3)
    vals = table[column].to_numpy(dtype=float)
    out: list[float | None] = []
    for i in range(4):
        v = vals[(q == i) & np.isfinite(vals)]
        out.append(float(v.mean()) if v.size else None)
    return out


def summarise_forgetting(summary: Summary, table: pd.DataFrame, n_frames: int, scheme: str,
                         no_depth: str | None = None) -> None:
    """``depth.quarter_pcd_lsq.{pretrained,adapted,online}.{q1..q4}`` and ``depth.bwt.{vs_online,vs_pretrained}``
    (module docstring); a note when the final model ends below the pre-trained one on the first quarter."""
    means = {m: quarter_means(table, col, n_frames) for m, col in COLUMNS.items()}
    for model, vals in means.items():
        why = (no_depth or ("no online score in this run (eval.online off, or a scheme without a keyframe loop)"
                            if model == "online" and COLUMNS["online"] not in table else
                            "no evaluated frame with GT depth in this quarter"))
        for name, v in zip(QUARTERS, vals):
            summary.set(f"depth.quarter_pcd_lsq.{model}.{name}", v, why)
    first = {m: v[0] for m, v in means.items()}
    trained = scheme not in ("none",)
    for ref in ("online", "pretrained"):
        key = f"depth.bwt.vs_{ref}"
        final, before = first["adapted"], first[ref]
        if not trained:
            summary.absent(key, f"scheme {scheme!r} does not adapt the model")
        elif final is None or before is None:
            summary.absent(key, no_depth or f"no {ref} and final score on the first quarter")
        else:
            summary.set(key, final - before)
    vs_pre = summary.number("depth.bwt.vs_pretrained")
    if vs_pre is not None and vs_pre < 0:
        summary.notes["depth.bwt.vs_pretrained"] = (
            f"the final model ends below the pre-trained model on the sequence's first quarter "
            f"({first['adapted']:.1f} vs {first['pretrained']:.1f} % PCD lsq): it forgot that part of the sequence")

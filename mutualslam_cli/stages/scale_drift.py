"""Scale drift of a run's maps against GT (issue 39, "one map that holds its scale"): the keys
``trajectory.local_scale.<map>.{max,min,max_over_min}`` and ``trajectory.local_ate_m.<map>``, the table
``scale_drift.csv`` and the figure ``scale_drift.png`` (:mod:`~mutualslam_cli.metrics.scale_drift`).

Maps: ``vo`` (the front end on its own, each segment in its own unit) and ``ba`` (the final map: after the
loop closures when ``loop.enabled``, then culling + global BA), as the ATE keys name them. A map the run did
not make, a sequence without GT poses, or fewer keyframes with GT than one window: the keys are null with the
reason, never 0.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_path, atomic_write_text
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.errors import MslamError
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.scale_drift import STRIDE, WINDOW, ScaleDrift, scale_drift
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.context import RunContext

log = logging.getLogger(__name__)

#: The maps whose scale drift a run reports, in table order.
MAPS = ("vo", "ba")
#: CSV columns of ``scale_drift.csv``, one row per window.
COLUMNS = ("map", "start_kf", "end_kf", "start_frame", "start_timestamp", "start_s", "segment", "relative_scale",
           "local_rmse_m", "ref_scale", "global_scale", "global_rmse_m")


def keys(name: str) -> tuple[str, ...]:
    """The summary keys of map ``name``."""
    return tuple(f"trajectory.local_scale.{name}.{k}" for k in ("max", "min", "max_over_min")) + (
        f"trajectory.local_ate_m.{name}",)


def set_scale_drift(summary: Summary, name: str, r: ScaleDrift | None, why: str = "not computed") -> None:
    """Map ``name``'s keys from ``r`` (``None``: null with ``why``)."""
    k_max, k_min, k_ratio, k_ate = keys(name)
    if r is None:
        for k in keys(name):
            summary.absent(k, why)
        return
    summary.set(k_max, r.max)
    summary.set(k_min, r.min)
    summary.set(k_ratio, r.max_over_min)
    summary.set(k_ate, r.local_ate)
    ref = ("its segment's own Sim(3) scale (a restart has its own unit)" if r.per_segment else
           "s_glob (one Sim(3) over the run)")
    summary.notes[k_ratio] = (f"s_loc over {ref}, {len(r.rel_scale)} windows of {r.window} keyframes (stride "
                              f"{r.stride}), one Sim(3) each; {r.n_crossing} windows across a segment boundary and "
                              f"{r.n_degenerate} degenerate ones skipped")
    summary.notes[k_ate] = (f"median over windows of the RMSE after each window's own Sim(3); one Sim(3) over the "
                            f"whole: {r.global_rmse:.4g} m")


def evaluate(seq: Sequence, vo: VOResult, max_dt: float, window: int = WINDOW) -> ScaleDrift:
    """:func:`~mutualslam_cli.metrics.scale_drift.scale_drift` of ``vo``'s keyframes against the sequence's GT,
    windows within one map unit: a segment, or the segments a bridge or a merge joined
    (:attr:`~mutualslam_cli.map.result.VOResult.units`). Raises :class:`MslamError` with the reason when it cannot
    be computed."""
    if seq.gt is None or len(seq.gt) == 0:
        raise MslamError("sequence has no GT poses")
    unit = vo.unit_of_segment()  # the map's own units: bridges and merges (VOResult.units)
    seg = np.array([unit[k.segment] for k in vo.keyframes], np.int64)
    return scale_drift(seq.gt, vo.traj_kf, seg, window=window, stride=STRIDE, max_dt=max_dt)


def rows(seq: Sequence, name: str, vo: VOResult, r: ScaleDrift) -> pd.DataFrame:
    """``scale_drift.csv``'s rows of map ``name`` (:data:`COLUMNS`)."""
    frames = np.array([vo.keyframes[i].frame_index for i in r.start], np.int64)
    t0 = seq.seconds(0) if len(seq) else 0.0
    return pd.DataFrame({
        "map": name, "start_kf": [vo.keyframes[i].id for i in r.start], "end_kf": [vo.keyframes[i].id for i in r.end],
        "start_frame": frames, "start_timestamp": r.start_time,
        "start_s": [seq.seconds(int(f)) - t0 for f in frames], "segment": r.segment,
        "relative_scale": r.rel_scale, "local_rmse_m": r.local_rmse, "ref_scale": r.ref_scale,
        "global_scale": r.global_scale,
        "global_rmse_m": r.global_rmse}, columns=list(COLUMNS))


def run_stage(run: RunContext, maps: dict[str, VOResult | None], why: dict[str, str] | None = None,
              ) -> dict[str, ScaleDrift]:
    """Every map's keys; ``scale_drift.csv`` and ``scale_drift.png`` when at least one map has a value.

    Args:
        maps: ``{name: map or None}`` (:data:`MAPS`), each with its own map units; why: ``{name: why the map is
            None}``.

    Returns:
        ``{name: ScaleDrift}`` of the maps that have one.
    """
    why = why or {}
    out: dict[str, ScaleDrift] = {}
    tables = []
    for name, vo in maps.items():
        if vo is None:
            set_scale_drift(run.summary, name, None, why.get(name, "no such map in this run"))
            continue
        try:
            r = evaluate(run.seq, vo, run.cfg.eval.ate_max_dt)
        except MslamError as e:
            set_scale_drift(run.summary, name, None, str(e))
            continue
        set_scale_drift(run.summary, name, r)
        out[name] = r
        tables.append(rows(run.seq, name, vo, r))
        log.info("scale drift of %s: local scale %.3f..%.3f of the global (max/min %.3f), local ATE %.4f m, "
                 "global %.4f m", name, r.min, r.max, r.max_over_min, r.local_ate, r.global_rmse)
    if tables:
        table = pd.concat(tables, ignore_index=True)
        atomic_write_text(run.folder / "scale_drift.csv", table.to_csv(index=False))
        figure(table, run.folder / "scale_drift.png", f"{run.seq.name} · {run.cfg.adapt.scheme} · seed {run.cfg.seed}")
    return out


#: Line colour of each map in ``scale_drift.png``.
COLOURS = {"vo": "#1f77b4", "ba": "#d62728"}


def figure(table: pd.DataFrame, path: Path, heading: str) -> None:
    """``scale_drift.png``: top, ``s_loc / s_glob`` over time, one line per map; bottom, each window's RMSE
    after its own Sim(3) (solid) and the whole trajectory's under one Sim(3) (dashed), per map.

    Args:
        table: ``scale_drift.csv``'s rows (:data:`COLUMNS`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.5, 6.0), sharex=True, layout="constrained")
    for name, g in table.groupby("map", sort=False):
        colour = COLOURS.get(str(name), "#2ca02c")
        ratio = g["relative_scale"].max() / g["relative_scale"].min()
        for i, (_, s) in enumerate(g.groupby("segment", sort=True)):  # no line across a restart
            top.plot(s["start_s"], s["relative_scale"], color=colour, lw=1.4,
                     label=f"{name}: max/min {ratio:.3f}" if i == 0 else None)
            bottom.plot(s["start_s"], s["local_rmse_m"], color=colour, lw=1.4,
                        label=f"{name} local, median {g['local_rmse_m'].median():.3g} m" if i == 0 else None)
        bottom.axhline(float(g["global_rmse_m"].iloc[0]), color=colour, ls="--", lw=1.2,
                       label=f"{name} global (one Sim(3)) {float(g['global_rmse_m'].iloc[0]):.3g} m")
    top.axhline(1.0, color="#7f7f7f", ls=":", lw=1.0)
    top.set_ylabel("local scale / global scale")
    top.set_title(f"{heading}\nlocal Sim(3) over windows of {WINDOW} keyframes vs one Sim(3) over the run",
                  fontsize=10)
    bottom.set_ylabel("ATE RMSE (m)")
    bottom.set_xlabel("time of the window's first keyframe (s from the first frame)")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)

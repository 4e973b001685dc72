"""The trajectory figures of ``mslam report``.

:func:`trajectory_figure` draws trajectories like evo's plots: one row per run, the top view
(the two horizontal GT axes, equal aspect) and the height over time, in metres, after a Sim(3)
alignment to GT (:func:`mutualslam_cli.metrics.trajectory.ate`, as ``summary.json``'s ATE): the GT
reference, the VO trajectory (``traj_all.txt``, else ``traj_kf.txt``) and, when the run has it,
the trajectory after the global BA (``traj_*_ba.txt``). GT comes from the sequence itself
(:func:`load_reference`). One figure per sequence with the lowest seed of each (scheme, config),
as the map figures; more than :data:`MAX_ROWS` rows go on further pages.
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import pandas as pd

from mutualslam_cli.datasets.associate import MAX_DT, read_tum_trajectory
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.errors import DatasetError, MslamError
from mutualslam_cli.metrics.trajectory import ate
from mutualslam_cli.report.columns import slug
from mutualslam_cli.report.plots import by_scheme, legend_columns, pyplot, save_png, with_config
from mutualslam_cli.types import Trajectory

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.figure import Figure

_T = TypeVar("_T")

#: Rows (runs) of one trajectory figure; further runs of the sequence go on more pages.
MAX_ROWS = 6
#: Trajectory colours: GT reference, VO, after global BA.
TRAJ_STYLE = {"gt": ("GT reference", "#222222", "--"), "vo": ("VO (Sim(3)-aligned)", "#1f77b4", "-"),
              "bridged": ("bridged segments (Sim(3)-aligned)", "#9467bd", "-"),
              "ba": ("after global BA (Sim(3)-aligned)", "#ff7f0e", "-")}
#: Marks of the front end's events on the trajectories: kind → (legend label, colour, marker).
EVENT_STYLE = {"segment": ("new segment (re-initialised)", "#d62728", "x"),
               "bridge": ("new segment, bridged", "#9467bd", "s"),
               "relocalised": ("relocalised", "#2ca02c", "^")}
AXES = "xyz"
#: Colour of the loop edges (a closed loop's new and old keyframe joined).
LOOP_COLOUR = "#9467bd"


@dataclass
class Reference:
    """GT poses of a sequence: ``gt`` (``T_wc``, metres) and how its timestamps read (``time_label``)."""

    gt: Trajectory
    time_label: str


def _plain(v: _T) -> _T | None:
    """``v``, ``None`` for NaN (an empty cell of the runs' table)."""
    return None if v is None or (isinstance(v, float) and v != v) else v


def load_reference(run: pd.Series) -> Reference:
    """GT poses of a run's sequence, read where the run found them.

    Tries the ``sequence.root`` folder of the run's ``manifest.json``, then the ``sequence.name`` of
    ``summary.json`` in ``datasets.yaml`` (with the run's ``data.data_root``, else ``$MSLAM_DATA``),
    with :func:`~mutualslam_cli.datasets.registry.load_sequence`.

    Args:
        run: one row of :func:`~mutualslam_cli.report.collect` (``folder``, ``sequence.name``,
            ``config.data.data_root``).
    Raises:
        DatasetError: neither gives a sequence with GT poses (the message says why, shortened).
    """
    folder = Path(run["folder"])
    sources = [str(run["sequence.name"])]
    try:
        root = json.loads((folder / "manifest.json").read_text())["sequence"]["root"]
        sources = ([root] if root and Path(root).is_dir() else []) + sources  # the folder the run read, first
    except (OSError, ValueError, KeyError, TypeError):
        pass
    errors = []
    for src in dict.fromkeys(sources):
        try:
            seq = load_sequence(src, data_root=_plain(run.get("config.data.data_root")))
        except (MslamError, OSError) as e:
            errors.append(str(e).splitlines()[0])
            continue
        if seq.gt is None or len(seq.gt) < 3:
            errors.append(f"{src}: sequence has no GT poses")
            continue
        icl = seq.meta.get("format") in ("icl", "icl_loop")
        return Reference(seq.gt, "frames since the start (ICL-NUIM stamps)" if icl else "time since the start (s)")
    raise DatasetError(textwrap.shorten("; ".join(errors), 220, placeholder=" …"))


def vertical_axis(rotations: np.ndarray) -> tuple[int, float]:
    """The GT axis closest to vertical and the sign that points up: ``(k, ±1)``.

    Heuristic for cameras held or driven upright: the vertical axis is the world axis along
    which the cameras' up vector (−y of the camera) points most and their right vector (x)
    least. ICL-NUIM and 7-Scenes give y (down), TUM's motion-capture frame z (up).

    Args:
        rotations: ``(N, 3, 3)`` camera-to-world rotations.
    """
    up = -rotations[:, :, 1]
    score = np.abs(up).mean(0) - np.abs(rotations[:, :, 0]).mean(0)
    k = int(np.argmax(score))
    return k, 1.0 if up[:, k].mean() >= 0 else -1.0


@dataclass
class TrackRow:
    """One run's row of a trajectory figure: aligned positions ``(K, 3)`` (metres) with ``(K,)``
    timestamps per stage (``vo``, ``ba``), the GT window, the title and problems to show."""

    title: str
    gt_t: np.ndarray
    gt_p: np.ndarray
    stages: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    ate_text: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    events: list[tuple[float, str]] = field(default_factory=list)
    loops: list[tuple[float, float]] = field(default_factory=list)


def run_events(folder: Path) -> list[tuple[float, str]]:
    """``(timestamp, kind)`` of the front end's events of a run (``manifest.json``): the start of every
    segment after the first (``segment``, or ``bridge`` when the adaptation bridged it) and every
    relocalisation; ``[]`` when the manifest does not have them."""
    try:
        m = json.loads((Path(folder) / "manifest.json").read_text())
    except (OSError, ValueError):
        return []
    meta = m.get("vo_meta") or {}
    bridged = {b.get("segment") for b in m.get("bridges") or []}
    out = [(float(s["timestamp"]), "bridge" if s["segment"] in bridged else "segment")
           for s in meta.get("segment_starts", [])[1:]]
    out += [(float(r["timestamp"]), "relocalised") for r in meta.get("relocalisations", []) if "timestamp" in r]
    return sorted(out)


def run_loops(folder: Path) -> list[tuple[float, float]]:
    """``(timestamp of the new keyframe, timestamp of the old one it saw again)`` of each loop a run closed
    (``manifest.json``'s ``loops``); ``[]`` when there is none."""
    try:
        m = json.loads((Path(folder) / "manifest.json").read_text())
    except (OSError, ValueError):
        return []
    return [(float(x["timestamp"]), float(x["match_timestamp"])) for x in m.get("loops") or []
            if "timestamp" in x and "match_timestamp" in x]


def _read(folder: Path, name: str) -> Trajectory | None:
    f = folder / name
    return read_tum_trajectory(f) if f.is_file() and f.stat().st_size else None


def track_row(folder: Path, gt: Trajectory, max_dt: float = MAX_DT, title: str = "") -> TrackRow:
    """Align a run's trajectories to ``gt`` (Sim(3), per file, as the pipeline's ATE).

    Stage ``vo`` is ``traj_all.txt`` (else ``traj_kf.txt``), ``bridged`` ``traj_all_bridged.txt`` and
    ``ba`` ``traj_all_ba.txt`` (else their ``traj_kf`` files); ``ate_text`` gives each stage's ATE
    RMSE of keyframes and of all frames; ``events`` the run's :func:`run_events`. A file that cannot
    be aligned (no overlap, degenerate) becomes a ``problems`` line.
    """
    row = TrackRow(title, np.zeros(0), np.zeros((0, 3)), events=run_events(folder), loops=run_loops(folder))
    t_lo, t_hi = np.inf, -np.inf
    for stage, suffix, label in (("vo", "", "VO"), ("bridged", "_bridged", "bridged"), ("ba", "_ba", "after BA")):
        rmse = {}
        for which in ("kf", "all"):
            est = _read(folder, f"traj_{which}{suffix}.txt")
            if est is None:
                continue
            try:
                r = ate(gt, est, align="sim3", max_dt=max_dt)
            except MslamError as e:
                row.problems.append(f"{label} traj_{which}{suffix}.txt: {str(e).splitlines()[0]}")
                continue
            rmse[which] = r.rmse
            if which == "all" or stage not in row.stages:
                row.stages[stage] = (r.est_timestamps, r.est_aligned)
            t_lo, t_hi = min(t_lo, est.timestamps[0]), max(t_hi, est.timestamps[-1])
        if rmse:
            row.ate_text.append(f"{label} " + " / ".join(f"{rmse[w]:.4f}" if w in rmse else "—" for w in ("kf", "all")))
    if row.stages:
        keep = (gt.timestamps >= t_lo - max_dt) & (gt.timestamps <= t_hi + max_dt)
        row.gt_t, row.gt_p = gt.timestamps[keep], gt.positions[keep]
    return row


def unaligned_row(folder: Path, title: str = "") -> TrackRow:
    """A run's trajectories as estimated, in the front end's frame and units (a sequence without GT poses):
    stages as in :func:`track_row`, no GT, no ATE."""
    row = TrackRow(title, np.zeros(0), np.zeros((0, 3)), events=run_events(folder), loops=run_loops(folder))
    for stage, suffix in (("vo", ""), ("bridged", "_bridged"), ("ba", "_ba")):
        est = _read(folder, f"traj_all{suffix}.txt") or _read(folder, f"traj_kf{suffix}.txt")
        if est is not None:
            row.stages[stage] = (est.timestamps, est.positions)
    return row


def trajectory_figure(rows: list[TrackRow], heading: str, vertical: tuple[int, float], time_label: str,
                      aligned: bool = True) -> Figure:
    """One row per run: top view (equal aspect) and height over time, metres.

    Args:
        rows: :func:`track_row` of each run (a row without stages shows its problems instead).
        heading: the figure's title.
        aligned: the rows are aligned to GT (metres); ``False``: :func:`unaligned_row` (VO units, no GT).
        vertical: :func:`vertical_axis` of the GT.
        time_label: x label of the height panels (times are shown from the first GT pose drawn).
    Returns:
        A matplotlib Figure with ``2 * len(rows)`` axes (top view, height per row); lines carry
        ``gid`` ``gt``, ``vo``, ``bridged`` or ``ba``, event marks ``event-<kind>``, loop edges ``loop``.
    """
    plt = pyplot()
    k, sign = vertical
    h, v = [i for i in range(3) if i != k]
    fig = plt.figure(figsize=(12.0, 3.5 * len(rows) + 1.0), layout="constrained")
    subs = np.atleast_1d(fig.subfigures(len(rows), 1))
    handles: dict[str, Artist] = {}  # legend label → its first matplotlib artist
    for sf, row in zip(subs, rows):
        top, height = sf.subplots(1, 2, width_ratios=[1.0, 1.9])
        ate_line = ("ATE RMSE (m), keyframes / all frames: " + ", ".join(row.ate_text)) if row.ate_text else ""
        problems = [textwrap.shorten(p, 110) for p in row.problems] or ([] if row.stages else ["no trajectory file"])
        sf.suptitle("\n".join([row.title, ate_line, *problems]).replace("\n\n", "\n").strip(), fontsize=10)
        t0 = row.gt_t[0] if len(row.gt_t) else 0.0
        curves = [("gt", row.gt_t, row.gt_p)] * bool(len(row.gt_t)) + [(s, *row.stages[s]) for s in
                                                                   ("vo", "bridged", "ba") if s in row.stages]
        for stage, t, p in curves if row.stages else []:
            label, colour, ls = TRAJ_STYLE[stage]
            label = label if aligned else label.replace("Sim(3)-aligned", "as estimated, VO units")
            z, lw = (3, 1.1) if stage == "gt" else (2, 1.4)  # the dashed GT over the estimates, as evo
            (line,) = top.plot(p[:, h], p[:, v], ls, color=colour, lw=lw, zorder=z, gid=stage, label=label)
            height.plot(t - t0, sign * p[:, k], ls, color=colour, lw=lw, zorder=z, gid=stage, label=label)
            handles.setdefault(label, line)
        if len(row.gt_p):
            top.plot(row.gt_p[:1, h], row.gt_p[:1, v], "o", color=TRAJ_STYLE["gt"][1], ms=4, gid="start")
        est = row.stages.get("bridged") or row.stages.get("vo")
        for t_event, kind in row.events if est is not None and len(est[0]) else []:
            label, colour, marker = EVENT_STYLE[kind]
            assert est is not None  # the loop runs only then
            p = est[1][int(np.argmin(np.abs(est[0] - t_event)))]
            (mark,) = top.plot(p[h], p[v], marker, color=colour, ms=7, mew=1.6, zorder=4, gid=f"event-{kind}")
            height.axvline(t_event - t0, color=colour, lw=0.9, ls=":", zorder=1, gid=f"event-{kind}")
            handles.setdefault(label, mark)
        closed = row.stages.get("ba") or est
        for t_new, t_old in row.loops if closed is not None and len(closed[0]) else []:  # loop edges
            assert closed is not None  # the loop runs only then
            a, b = (closed[1][int(np.argmin(np.abs(closed[0] - x)))] for x in (t_new, t_old))
            (edge,) = top.plot([a[h], b[h]], [a[v], b[v]], "-", color=LOOP_COLOUR, lw=1.2, zorder=5, gid="loop")
            height.axvline(t_new - t0, color=LOOP_COLOUR, lw=0.9, ls="-.", zorder=1, gid="loop")
            handles.setdefault("loop closed (new ↔ old keyframe)", edge)
        top.set_aspect("equal", adjustable="datalim")
        unit = "m" if aligned else "VO units"
        top.set_xlabel(f"{AXES[h]} ({unit})")
        top.set_ylabel(f"{AXES[v]} ({unit})")
        height.set_xlabel(time_label)
        height.set_ylabel(f"height = {'' if sign > 0 else '−'}{AXES[k]} ({unit})")
        for ax in (top, height):
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=8)
    if aligned:
        handles["start (GT)"] = plt.Line2D([], [], color=TRAJ_STYLE["gt"][1], marker="o", lw=0, ms=4)
    fig.legend(list(handles.values()), list(handles), loc="outside lower center", fontsize=9, frameon=False,
               ncol=legend_columns(fig, list(handles), 9, most=len(handles)))
    fig.suptitle(heading, fontsize=12)
    return fig


def trajectory_figures(runs: pd.DataFrame, out_dir: Path) -> tuple[list[Path], list[str]]:
    """:func:`trajectory_figure` of every sequence into ``out_dir/trajectories/trajectories_<sequence>[_<page>].png``.

    Returns:
        The files written, and one line per sequence drawn without figure (GT not found).
    """
    runs = with_config(runs)
    written, notes = [], []
    for seq, g in runs.groupby("sequence.name", sort=True):
        picks = [grp.sort_values("_seed", na_position="last").iloc[0] for _, grp in by_scheme(g)]
        ref, why = None, ""
        for r in picks:
            try:
                ref = load_reference(r)
                break
            except MslamError as e:
                why = str(e)
        rows = []
        for r in picks:
            seed = "" if r["_seed"] != r["_seed"] else f"seed {int(r['_seed'])}"
            title = " · ".join(x for x in (str(r["scheme"]), seed or Path(r["folder"]).name, r["config"]) if x)
            max_dt = _plain(r.get("config.eval.ate_max_dt")) or MAX_DT
            rows.append(track_row(Path(r["folder"]), ref.gt, float(max_dt), title) if ref is not None
                        else unaligned_row(Path(r["folder"]), title))
        if ref is None:  # no GT: the trajectories as estimated, in the front end's frame and units
            notes.append(f"Trajectories of {seq}: as estimated, not aligned (GT poses not found: {why}).")
            kf = _read(Path(picks[0]["folder"]), "traj_kf.txt")
            if kf is None:
                continue
            vertical, time_label, aligned = vertical_axis(kf.poses[:, :3, :3]), "time (s)", False
        else:
            vertical, time_label, aligned = vertical_axis(ref.gt.poses[:, :3, :3]), ref.time_label, True
        pages = [rows[i:i + MAX_ROWS] for i in range(0, len(rows), MAX_ROWS)]
        for n, page in enumerate(pages, 1):
            part = f" (page {n} of {len(pages)})" if len(pages) > 1 else ""
            heading = (f"{seq}: trajectories against GT after Sim(3) alignment, lowest seed per scheme{part}"
                       if aligned else f"{seq}: trajectories as estimated (no GT), lowest seed per scheme{part}")
            path = Path(out_dir) / "trajectories" / (f"trajectories_{slug(str(seq))}"
                                                     + (f"_p{n}" if len(pages) > 1 else "") + ".png")
            save_png(trajectory_figure(page, heading, vertical, time_label, aligned), path)
            written.append(path)
    return written, notes

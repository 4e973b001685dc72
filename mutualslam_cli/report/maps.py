"""The map before and after culling and BA, as a picture (paper Fig. ``mp_culling_qualitative``).

:func:`plot_maps` draws one run's ``map_vo.ply``, ``map_culled.ply`` and ``map_ba.ply`` side by
side, each point in the colour :mod:`~mutualslam_cli.results.map_ply` stored for it (its log-depth error
against GT: blue too near, grey right, red too far, light grey without GT), seen from the
cameras (front view) and from above (top view). Every panel has the same view and axis limits;
its title gives the point count and e_si from ``summary.json``. :func:`map_figures` draws one
figure per (sequence, scheme, config) with the lowest seed.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.datasets.associate import read_tum_trajectory
from mutualslam_cli.report.columns import slug
from mutualslam_cli.report.plots import fit_width
from mutualslam_cli.results import map_ply

if TYPE_CHECKING:
    from matplotlib.axes import Axes

#: A map as :func:`~mutualslam_cli.results.map_ply.read_ply` reads it: ``(P, 3)`` points, ``(P, 3)`` colours in
#: [0, 1] and ``(P,)`` log-depth errors (each ``None`` in an xyz-only map).
Map = tuple[np.ndarray, np.ndarray | None, np.ndarray | None]

#: (file, summary stage, panel title) of the panels, left to right.
PANELS = (("map_vo.ply", "vo", "front-end map (no culling, no BA)"),
          ("map_culled.ply", "culled", "after map-point culling"),
          ("map_ba.ply", "ba", "after culling + global BA"))


def _view_basis(folder: Path) -> np.ndarray:
    """``(3, 3)`` rows right, up, forward: the keyframe cameras' mean axes (x, −y, z); the map
    frame's axes when there is no keyframe trajectory."""
    f = folder / "traj_kf.txt"
    if f.is_file() and f.stat().st_size:
        rot = read_tum_trajectory(f).poses[:, :3, :3]
        if len(rot):
            fwd = rot[:, :, 2].mean(0)
            up = -rot[:, :, 1].mean(0)
            if np.linalg.norm(fwd) > 1e-6:
                fwd /= np.linalg.norm(fwd)
                up -= up.dot(fwd) * fwd
                if np.linalg.norm(up) > 1e-6:
                    up /= np.linalg.norm(up)
                    return np.stack([np.cross(-up, fwd), up, fwd])
    return np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, 1]])


def _cameras(folder: Path, name: str) -> np.ndarray:
    """``(K, 3)`` keyframe positions of ``traj_kf<name>.txt`` (empty when absent)."""
    f = folder / f"traj_kf{name}.txt"
    if not (f.is_file() and f.stat().st_size):
        return np.zeros((0, 3))
    return read_tum_trajectory(f).poses[:, :3, 3]


def _limits(xy: np.ndarray, cams: np.ndarray, margin: float = 0.12) -> tuple[tuple[float, float], ...]:
    """Axis limits holding the central 98 % of the points ``(P, 2)`` and every camera ``(K, 2)``
    on each axis, plus a margin."""
    both = np.concatenate([np.percentile(xy, [1, 99], axis=0) if len(xy) else np.zeros((0, 2)), cams,
                           np.zeros((1, 2))])
    lo, hi = both.min(axis=0), both.max(axis=0)
    pad = np.maximum((hi - lo) * margin, 1e-3)
    return (lo[0] - pad[0], hi[0] + pad[0]), (lo[1] - pad[1], hi[1] + pad[1])


def _get(flat: Mapping[str, object], key: str) -> float | None:
    """A number of the flattened summary; None when absent, null or NaN."""
    v = flat.get(key)
    return float(v) if isinstance(v, (int, float, np.number)) and np.isfinite(v) else None


def _fit(x: tuple[float, float], y: tuple[float, float], ratio: float) -> tuple[tuple[float, float], ...]:
    """Widen one of the limits so that height / width = ``ratio`` (the panel's shape)."""
    w, h = x[1] - x[0], y[1] - y[0]
    if h < ratio * w:
        c, h = (y[0] + y[1]) / 2, ratio * w
        return x, (c - h / 2, c + h / 2)
    c, w = (x[0] + x[1]) / 2, h / ratio
    return (c - w / 2, c + w / 2), y


def _title(stage: str, label: str, flat: Mapping[str, object], n_read: int) -> str:
    n, e = _get(flat, f"map.points.{stage}"), _get(flat, f"map.esi.{stage}")
    esi = f"e_si {e:.3f}" if e is not None else "e_si —"
    return f"{label}\n{int(n) if n is not None else n_read} points, {esi}"


def _removed(vo: Map | None, kept: Map | None) -> np.ndarray:
    """``(M, 3)`` points of the VO map that the culled map no longer has (same coordinates: the
    culled map is a subset of the front end's); empty without a culled map."""
    if vo is None or kept is None:
        return np.zeros((0, 3))
    have = {tuple(r) for r in kept[0]}
    return vo[0][np.array([tuple(r) not in have for r in vo[0]], dtype=bool).reshape(-1)]


def _panel(ax: Axes, data: Map, stage: str, label: str, flat: Mapping[str, object], basis: np.ndarray,
           hv: tuple[int, int], cams: np.ndarray | None, removed: np.ndarray | None) -> str:
    """Draw one map (``read_ply``'s result) in one view; return its title."""
    h, v = hv
    pts, colours, _ = data
    p = pts @ basis.T
    title = _title(stage, label, flat, len(pts))
    if colours is None:  # the xyz-only maps of older runs
        colours = np.tile(np.asarray(map_ply.NO_GT), (len(p), 1))
        title += " (map without error colours)"
    # no-GT points first, then the larger errors on top of the small ones
    strength = np.linalg.norm(colours - np.asarray(map_ply.ERROR_ZERO), axis=1)
    strength[np.all(np.isclose(colours, map_ply.NO_GT, atol=2 / 255), axis=1)] = -1
    order = np.argsort(strength, kind="stable")
    size = float(np.clip(5000.0 / max(len(p), 1), 0.8, 9.0))
    if removed is not None and len(removed):  # under the kept points, fainter the more there are
        r = removed @ basis.T
        ax.scatter(r[:, h], r[:, v], marker="x", c="k", s=max(size * 2.0, 4), linewidths=0.6,
                   alpha=float(np.clip(40.0 / len(r), 0.12, 0.8)), rasterized=True)
        title = title.replace(" points,", f" points ({len(r)} culled ×),")
    ax.scatter(p[order, h], p[order, v], c=colours[order], s=size, linewidths=0, rasterized=True)
    if cams is not None and len(cams):
        cp = cams @ basis.T
        ax.plot(cp[:, h], cp[:, v], "-", color="k", lw=0.8, alpha=0.6)
        ax.plot(cp[:1, h], cp[:1, v], "o", color="k", ms=3)
    ax.grid(alpha=0.2)
    return title


def plot_maps(folder: Path, path: Path, flat: Mapping[str, object], heading: str) -> bool:
    """Front and top view of a run's maps (one column per file of :data:`PANELS`) as a PNG.

    Args:
        folder: the run folder (``map_*.ply``, ``traj_kf*.txt``).
        path: the PNG to write.
        flat: the run's flattened ``summary.json`` (point counts, e_si, notes of absent maps).
        heading: the figure's title.
    Returns:
        False (nothing written) when the run has no ``map_vo.ply``.
    """
    if not (folder / "map_vo.ply").is_file():
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, Normalize
    from matplotlib.patches import Patch

    basis = _view_basis(folder)
    maps = {f: map_ply.read_ply(folder / f) for f, _, _ in PANELS if (folder / f).is_file()}
    panels = [(f, st, lab) for f, st, lab in PANELS if f in maps]
    raw_notes = flat.get("notes")
    notes = raw_notes if isinstance(raw_notes, dict) else {}
    absent = [f"no {f}: {notes.get(f'map.points.{st}') or 'not written by this run'}"
              for f, st, _ in PANELS if f not in maps]
    culled = "map_culled.ply" in maps or _get(flat, "map.points.culled") is not None
    cams = {"map_vo.ply": _cameras(folder, ""), "map_ba.ply": _cameras(folder, "_ba")}
    cams["map_culled.ply"] = cams["map_vo.ply"]
    pts_v, cams_v = maps["map_vo.ply"][0] @ basis.T, np.concatenate(list(cams.values())) @ basis.T
    views = (("front view (as seen by the cameras)", 0, 1, "right", "up"),
             ("top view (from above the cameras)", 0, 2, "right", "forward"))
    lims = [_limits(pts_v[:, [h, v]], cams_v[:, [h, v]]) for _, h, v, _, _ in views]
    # each row as tall as its view's extent (equal axes), within 0.35-1.4 of the panel width
    ratios = [float(np.clip((y[1] - y[0]) / (x[1] - x[0]), 0.35, 1.4)) for x, y in lims]
    lims = [_fit(x, y, r) for (x, y), r in zip(lims, ratios)]
    width, bottom = 4.8, 1.0 + 0.16 * len(absent)  # inches: panel width, band under the panels
    fig_w, fig_h = max(width * len(panels), 10.0), width * sum(ratios) + 1.6 + bottom
    fig, axes = plt.subplots(2, len(panels), figsize=(fig_w, fig_h), squeeze=False,
                             gridspec_kw={"height_ratios": ratios})
    removed = _removed(maps["map_vo.ply"], maps.get("map_culled.ply"))
    for col, (fname, stage, label) in enumerate(panels):
        if fname == "map_ba.ply" and not culled:
            label = "after global BA (no culling)"
        for row, (vname, h, v, hl, vl) in enumerate(views):
            ax = axes[row, col]
            ax.set_xlim(*lims[row][0])
            ax.set_ylim(*lims[row][1])
            ax.set_aspect("equal", adjustable="box")
            ax.tick_params(labelsize=7)
            ax.set_xlabel(f"{hl} (map units)", fontsize=8)
            if col == 0:
                ax.set_ylabel(f"{vname}\n{vl} (map units)", fontsize=8)
            title = _panel(ax, maps[fname], stage, label, flat, basis, (h, v), cams.get(fname),
                           removed if fname == "map_culled.ply" else None)
            if row == 0:
                ax.set_title(title, fontsize=10)
    heading = fit_width(fig, heading, 12)  # on as many lines as it needs, with room above the panels for each
    fig.tight_layout(rect=(0, bottom / fig_h, 1, 1 - (0.5 + 0.2 * heading.count("\n")) / fig_h))
    # the colour scale of the PLYs, the no-GT colour, and what is not drawn
    ramp = map_ply.error_colours(np.linspace(-1, 1, 256) * map_ply.ERROR_SATURATION)
    sm = plt.cm.ScalarMappable(cmap=ListedColormap(ramp),
                               norm=Normalize(-map_ply.ERROR_SATURATION, map_ply.ERROR_SATURATION))
    cax = fig.add_axes((0.25, (bottom - 0.35) / fig_h, 0.40, 0.13 / fig_h))
    cb = fig.colorbar(sm, cax=cax, orientation="horizontal")
    cb.set_label("log z − log z* of each point in its host keyframe, minus the map's mean "
                 "(blue: too near, red: too far)", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    handles = [Patch(color=map_ply.NO_GT, label="no GT depth"),
               plt.Line2D([], [], color="k", lw=0.8, marker="o", ms=3, label="keyframe path (start ●)")]
    if len(removed):
        handles.insert(1, plt.Line2D([], [], color="k", lw=0, marker="x", ms=4, label="culled point"))
    fig.legend(handles=handles, loc="upper left", fontsize=8, frameon=False,
               bbox_to_anchor=(0.70, (bottom - 0.15) / fig_h))
    for i, line in enumerate(reversed(absent)):
        fig.text(0.02, (0.1 + 0.16 * i) / fig_h, textwrap.shorten(line, 160), fontsize=8, color="0.35")
    fig.suptitle(heading, fontsize=12)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return True


def map_figures(runs: pd.DataFrame, out_dir: Path) -> list[Path]:
    """:func:`plot_maps` of the lowest seed of every (sequence, scheme, config) into
    ``out_dir/maps/maps_<sequence>_<scheme>[_<config>]_seed<k>.png``; returns the files written."""
    runs = runs.assign(config=runs.get("config", ""),
                       _seed=pd.to_numeric(runs["seed"], errors="coerce") if "seed" in runs else np.nan)
    written = []
    for (seq, scheme, config), g in runs.groupby(["sequence.name", "scheme", "config"], sort=True):
        r = g.sort_values("_seed", na_position="last").iloc[0]
        seed = "" if r["_seed"] != r["_seed"] else f"seed{int(r['_seed'])}"
        name = "_".join(x for x in ("maps", slug(seq), slug(scheme), slug(config)[:60], seed) if x)
        heading = f"{seq} · {scheme} · {seed or Path(r['folder']).name}" + (f" · {config}" if config else "")
        path = Path(out_dir) / "maps" / f"{name}.png"
        if plot_maps(Path(r["folder"]), path, r.to_dict(), heading):
            written.append(path)
    return written

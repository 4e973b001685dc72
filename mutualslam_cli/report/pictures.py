"""Pictures a run draws itself (``dense.png``, ``depth.png``), gathered into a report.

:func:`run_pictures` copies ``<kind>.png`` of the lowest seed of every (sequence, scheme, config) into
``<report>/<kind>/<kind>_<sequence>_<scheme>[_<config>]_seed<k>.png``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.report.columns import numeric, slug


def run_pictures(runs: pd.DataFrame, out_dir: Path, kind: str) -> list[Path]:
    """Copy ``<kind>.png`` of the lowest seed of each (sequence, scheme, config) of ``runs`` that has one;
    returns the files written."""
    runs = runs.assign(config=runs.get("config", ""), _seed=numeric(runs, "seed"))
    written = []
    for (seq, scheme, config), g in runs.groupby(["sequence.name", "scheme", "config"], sort=True):
        for _, r in g.sort_values("_seed", na_position="last").iterrows():
            src = Path(r["folder"]) / f"{kind}.png"
            if not src.is_file():
                continue
            seed = "" if r["_seed"] != r["_seed"] else f"seed{int(r['_seed'])}"
            name = "_".join(x for x in (kind, slug(seq), slug(scheme), slug(config)[:60], seed) if x)
            dst = Path(out_dir) / kind / f"{name}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(dst) as tmp:
                shutil.copyfile(src, tmp)
            written.append(dst)
            break
    return written

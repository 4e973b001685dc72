"""The table of runs a report is built from (:func:`collect`): every complete run under the result folders,
one row each — its flattened ``summary.json``, its folder, its ``config.yaml`` as ``config.<key>`` columns
and a ``config`` label naming the settings that differ between runs (:func:`config_labels`).

A report reports what it can: a run whose ``summary.json`` is not valid JSON or not a JSON object, or whose
``config.yaml`` cannot be read, is skipped with a note naming the file and why; a value that is not a
finite number (``Infinity``, ``NaN`` written by hand or another tool) becomes an empty cell with a note.
Only when no run is left is it an error. Staging folders and the ``_cache`` are never searched.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from mutualslam_cli.config.yaml_file import read_yaml_mapping
from mutualslam_cli.errors import DatasetError, SchemaError
from mutualslam_cli.results.summary import flatten, read_summary
from mutualslam_cli.types import JSON

#: Config keys that do not make runs different experiments (``adapt.scheme`` has its own column).
#: ``threads`` is not among them: the numbers follow the thread count (torch's reductions sum in
#: another order), so runs with different counts are told apart like any other setting.
#: ``device`` is the setting (``auto`` resolves per machine): the device a run used is ``run_device``.
IGNORED_CONFIG = ("seed", "out", "adapt.scheme", "data.data_root", "eval.save_weights", "device")


def _read_config(folder: Path) -> dict[str, JSON]:
    """``config.*`` columns of a run's ``config.yaml`` (empty when the run has none); read strictly.

    Raises:
        DatasetError: the file is not a YAML mapping (one line naming it).
    """
    path = folder / "config.yaml"
    if not path.is_file():
        return {}
    cfg = read_yaml_mapping(path, DatasetError, "run config (config.yaml)")
    return {f"config.{k}": v for k, v in flatten(cfg).items()}


def config_labels(runs: pd.DataFrame, exclude: tuple[str, ...] = ()) -> pd.Series:
    """Per run, ``"key=value, ..."`` of the config keys whose values differ between the runs
    (except :data:`IGNORED_CONFIG` and ``exclude``); ``""`` when all runs agree. ``?``: the run
    has no such key (older ``config.yaml`` or none)."""
    keys = [c for c in runs.columns if c.startswith("config.") and c[7:] not in IGNORED_CONFIG + exclude
            and not c.startswith(("config.experiment.", "config.dense."))]  # what a run was for / after it
    shown = runs[keys].map(lambda v: "?" if v is None or (isinstance(v, float) and v != v) else str(v))
    differing = [c for c in keys if shown[c].nunique() > 1]
    if not differing:
        return pd.Series("", index=runs.index)
    return shown[differing].apply(lambda r: ", ".join(f"{c[7:]}={r[c]}" for c in differing), axis=1)


def _searched(path: Path, root: Path) -> bool:
    """Whether a ``summary.json`` found under ``root`` belongs to a run: not inside a hidden folder (a run's
    staging folder, :mod:`~mutualslam_cli.results.staging`) or the ``_cache``."""
    return not any(part.startswith(".") or part == "_cache" for part in path.relative_to(root).parts[:-1])


def _finite(row: dict[str, JSON], summary: Path, notes: list[str]) -> None:
    """Numbers of ``row`` that are not finite become ``None`` (an empty cell), each with a note."""
    for key, v in row.items():
        if isinstance(v, float) and not math.isfinite(v):
            row[key] = None
            notes.append(f"{summary}: {key} is {v}, not a finite number; its cells are left empty")


def _row(folder: Path, notes: list[str]) -> dict[str, JSON]:
    """One run's row (module docstring).

    Raises:
        DatasetError: the run is damaged: ``summary.json`` not valid JSON, ``config.yaml``
            not a YAML mapping.
        SchemaError: ``summary.json`` is not an object, or not of a schema version this mslam reads.
    """
    d = read_summary(folder).flat()
    _finite(d, folder / "summary.json", notes)
    d["folder"] = str(folder)
    parts = folder.parts
    for key, fallback in (("sequence.name", parts[-3] if len(parts) >= 3 else "?"),
                          ("scheme", parts[-2] if len(parts) >= 2 else "?")):
        d[key] = fallback if d.get(key) is None else str(d[key])  # a name of another type still names the row
    d.update(_read_config(folder))
    d["config.run_device"] = d.get("run.device_label")  # a grouping key like any setting (module docstring)
    return d


def collect(paths: list[str | Path], notes: list[str] | None = None) -> pd.DataFrame:
    """One row per complete run found under ``paths``: flattened summary keys, ``folder``,
    ``config.<key>`` of its ``config.yaml`` and ``config`` (:func:`config_labels`).

    Args:
        notes: receives one line per damaged run skipped and per value left empty (module docstring).

    Raises:
        DatasetError: a path does not exist, or no run could be read (the message says why each was skipped).
    """
    notes = notes if notes is not None else []
    rows: list[dict[str, JSON]] = []
    skipped: list[str] = []
    for p in map(Path, paths):
        if not p.exists():
            raise DatasetError(f"{p}: no such results folder")
        for s in sorted(f for f in p.rglob("summary.json") if _searched(f, p)):
            try:
                rows.append(_row(s.parent, notes))
            except (DatasetError, SchemaError) as e:
                skipped.append(str(e))
                notes.append(f"skipped, damaged: {e}")
    if not rows:
        why = f"{len(skipped)} damaged, none readable ({skipped[0]})" if skipped else "no summary.json found"
        raise DatasetError(f"{', '.join(map(str, paths))}: no complete run to report ({why})")
    runs = pd.DataFrame(rows)
    runs["config"] = config_labels(runs)
    return runs

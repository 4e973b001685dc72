"""Reading the table of runs (:func:`~mutualslam_cli.report.tables.collect`): a summary key as numbers,
a label as a file name, a value as table text."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd


def numeric(runs: pd.DataFrame, key: str) -> pd.Series:
    """``runs[key]`` as floats: NaN where the column is absent or a value is null."""
    return pd.to_numeric(runs[key], errors="coerce") if key in runs else pd.Series(np.nan, index=runs.index)


def slug(text: str) -> str:
    """``text`` as a safe file-name part: runs of anything but letters, digits and ``.+=-`` become ``_``."""
    return re.sub(r"[^A-Za-z0-9.+=-]+", "_", text).strip("_")


def cell_text(v: object) -> str:
    """A table cell: ``—`` for a missing value, 4 significant digits for a float (whole numbers from
    10,000 up), anything else as ``str``."""
    if v is None or (isinstance(v, (float, np.floating)) and not np.isfinite(v)):
        return "—"
    if isinstance(v, (float, np.floating)):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)

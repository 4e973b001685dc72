"""``keyframes.csv``: one :class:`KeyframeRow` per keyframe of a run — what Algorithm 1 did with it (the adapter's
:class:`~mutualslam_cli.adapt.step_info.StepInfo`: state, validation or batch, L_val, steps, loss parts), the work
the back end did on it (seconds of bridge, merge, BA, loop closure), and on the realtime clock when its work started
and ended. :func:`keyframes_table` writes the rows in :data:`COLUMNS` order.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields

import pandas as pd

from mutualslam_cli.adapt.step_info import StepInfo
from mutualslam_cli.types import Scalar

#: The back end's work on a keyframe, ``keyframes.csv`` columns in seconds (wall time on this machine).
WORK_SECONDS = ("bridge_s", "merge_s", "ba_s", "loop_s")

#: ``keyframes.csv``'s columns in order; the loss parts (``loss_<part>``, :func:`step_columns`) follow ``ms``.
COLUMNS = ("kf_id", "not_ticked", *(f.name for f in fields(StepInfo) if f.name not in ("kf_id", "loss", "health")),
           "n_sparse", *WORK_SECONDS, "rt_start_ms", "rt_end_ms")


def step_columns(info: StepInfo) -> dict[str, Scalar]:
    """The adapter's step info as flat CSV columns: lists space-joined, enums by value, the loss parts as
    ``loss_<part>`` columns."""
    row: dict[str, Scalar] = {}
    for k, v in dict(vars(info)).items():
        if isinstance(v, dict):
            row.update({f"{k}_{p}": x for p, x in v.items()})
        elif isinstance(v, (list, tuple)):
            row[k] = " ".join(map(str, v))
        else:
            row[k] = v.value if hasattr(v, "value") else v
    return row


@dataclass
class KeyframeRow:
    """One keyframe's row (module docstring).

    Attributes:
        kf_id: the keyframe.
        info: the adapter's record of it as its work stands (a copy: its tick, then its steps and consolidation);
            ``None``: not ticked.
        not_ticked: why Algorithm 1 did not tick it (scheme ``none``, a segment no bridge joined), else ``None``.
        n_sparse: the map points it observes with a depth (its sparse-depth labels), ``None`` when not ticked.
        seconds: ``{column: s}`` of the back end's work on it (:data:`WORK_SECONDS`).
        steps: realtime: the steps it took before the next keyframe came (else ``info.steps``).
        rt_start_ms, rt_end_ms: realtime: when its work started and ended on the sequence's clock (ms).
    """

    kf_id: int
    info: StepInfo | None = None
    not_ticked: str | None = None
    n_sparse: int | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    steps: int | None = None
    rt_start_ms: float | None = None
    rt_end_ms: float | None = None

    def took(self, info: StepInfo) -> None:
        """The adapter's record after more work on this keyframe (a copy: the adapter may go on changing its own)."""
        self.info = copy.deepcopy(info)

    def add_seconds(self, column: str, seconds: float) -> None:
        """``seconds`` more of the back end's work (a :data:`WORK_SECONDS` column)."""
        if column not in WORK_SECONDS:
            raise KeyError(f"{column!r} is not a keyframes.csv work column ({', '.join(WORK_SECONDS)})")
        self.seconds[column] = self.seconds.get(column, 0.0) + seconds

    @property
    def is_validation(self) -> bool:
        return self.info is not None and bool(self.info.is_validation)

    @property
    def trained(self) -> bool:
        return self.info is not None and bool(self.info.trained)

    @property
    def run_global_ba(self) -> bool:
        """Algorithm 1 asked for culling + the global BA at this keyframe."""
        return self.info is not None and bool(self.info.run_global_ba)

    @property
    def n_steps(self) -> int:
        """Optimiser steps taken on it."""
        if self.steps is not None:
            return int(self.steps)
        return int(self.info.steps) if self.info is not None else 0

    def to_row(self) -> dict[str, Scalar]:
        """The ``keyframes.csv`` row: the columns it has, in :data:`COLUMNS` order (loss parts after ``ms``)."""
        row: dict[str, Scalar] = {"kf_id": self.kf_id}
        if self.not_ticked is not None:
            row["not_ticked"] = self.not_ticked
        if self.info is not None:
            row.update({k: v for k, v in step_columns(self.info).items() if k != "kf_id"})
        if self.steps is not None:
            row["steps"] = self.steps
        if self.n_sparse is not None:
            row["n_sparse"] = self.n_sparse
        row.update({k: self.seconds[k] for k in WORK_SECONDS if k in self.seconds})
        for k in ("rt_start_ms", "rt_end_ms"):
            if getattr(self, k) is not None:
                row[k] = getattr(self, k)
        return row


def _column_order(columns: list[str]) -> list[str]:
    at_ms = COLUMNS.index("ms")
    losses = [c for c in columns if c.startswith("loss_")]  # in the order the adapter first gave them
    rank = {c: (i if i <= at_ms else i + len(losses)) for i, c in enumerate(COLUMNS)}
    rank.update({c: at_ms + 1 + j for j, c in enumerate(losses)})
    return sorted(columns, key=lambda c: rank.get(c, len(rank) + columns.index(c)))


def keyframes_table(rows: list[KeyframeRow]) -> pd.DataFrame:
    """``keyframes.csv`` from ``rows`` (in keyframe order): one line each, the columns any row has in
    :data:`COLUMNS` order; a cell a row lacks is empty."""
    table = pd.DataFrame([r.to_row() for r in rows])
    return table[_column_order(list(table.columns))]

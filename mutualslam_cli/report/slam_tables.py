"""The report's tables of a map's consistency (issue 39, "one map that holds its scale"): scale drift
(``trajectory.local_scale.*``, ``trajectory.local_ate_m.*``: :mod:`~mutualslam_cli.stages.scale_drift`) and loop
recall against GT revisits (``loop.recall.*``: :mod:`~mutualslam_cli.stages.loop_recall`).

Entries of the same shape as :data:`~mutualslam_cli.report.tables.TABLES` (mean over seeds per sequence, scheme
and config); :func:`shown` leaves a table out when no run has its values (loop recall: only runs with
``loop.enabled`` and GT have it).
"""

from __future__ import annotations

import pandas as pd

from mutualslam_cli.report.columns import numeric

#: table name → (title, [(column label, summary key)])
SLAM_TABLES: dict[str, tuple[str, list[tuple[str, str]]]] = {
    "scale_drift": ("Scale drift: the local Sim(3) scale over windows of 15 keyframes relative to the whole "
                    "run's one Sim(3) (max/min: 1 = the map held its scale; a restarted segment against its own), "
                    "and the local ATE (median over windows of the RMSE after each window's own Sim(3), m) "
                    "beside the global one (VO: the front end alone; BA: the final map)", [
        ("scale max/min VO", "trajectory.local_scale.vo.max_over_min"),
        ("scale min VO", "trajectory.local_scale.vo.min"), ("scale max VO", "trajectory.local_scale.vo.max"),
        ("local ATE VO", "trajectory.local_ate_m.vo"), ("global ATE VO", "trajectory.ate_rmse_m.vo"),
        ("scale max/min BA", "trajectory.local_scale.ba.max_over_min"),
        ("scale min BA", "trajectory.local_scale.ba.min"), ("scale max BA", "trajectory.local_scale.ba.max"),
        ("local ATE BA", "trajectory.local_ate_m.ba"), ("global ATE BA", "trajectory.ate_rmse_m.ba"),
    ]),
    "loop_recall": ("Loop recall against GT: keyframes that revisit an older one (≥ loop.min_gap keyframes "
                    "before, GT within 30 cm and 30°), and of them how many the detector found (a true partner "
                    "among its candidates), verified (geometry passed) and closed (loop.enabled runs with GT)", [
        ("revisits", "loop.recall.revisits"), ("found", "loop.recall.found"),
        ("verified", "loop.recall.verified"), ("closed", "loop.recall.closed"),
        ("loops closed", "loop.accepted"), ("candidates", "loop.candidates"),
    ]),
}

#: A table of :data:`SLAM_TABLES` is shown only when some run has a value of this key.
REQUIRES = {"loop_recall": "loop.recall.revisits"}


def shown(name: str, runs: pd.DataFrame) -> bool:
    """Whether table ``name`` has anything to show for ``runs`` (tables not in :data:`REQUIRES`: always)."""
    key = REQUIRES.get(name)
    return key is None or bool(numeric(runs, key).notna().any())

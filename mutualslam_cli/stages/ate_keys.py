"""The trajectory's summary keys (``trajectory.ate_rmse_m.*``, ``trajectory.ate_rmse_m_per_segment.*``) from
:func:`~mutualslam_cli.metrics.slam.evaluate_trajectory`'s RMSEs: what the front-end, BA and adaptation stages write."""

from __future__ import annotations

from typing import Any

from mutualslam_cli.results.summary import Summary


def set_ate(summary: Summary, traj: dict[str, Any], names: dict[str, str]) -> None:
    """:func:`~mutualslam_cli.metrics.slam.evaluate_trajectory`'s RMSEs under ``names``
    (``{"kf": leaf, "all": leaf}``): as
    ``trajectory.ate_rmse_m.<leaf>`` (one Sim(3), the headline) and, secondary,
    ``trajectory.ate_rmse_m_per_segment.<leaf>`` (each segment aligned on its own; equal to the
    headline for one segment)."""
    for key, name in names.items():
        for src, group in ((key, "ate_rmse_m"), (f"{key}_per_segment", "ate_rmse_m_per_segment")):
            dotted = f"trajectory.{group}.{name}"
            r = traj.get(src)
            if r is None and src.endswith("_per_segment") and traj.get(key) is not None:
                summary.set(dotted, float(traj[key].rmse))  # one segment
            elif r is None:
                summary.absent(dotted, traj["notes"].get(src, traj["notes"].get("trajectory", "not computed")))
            else:
                summary.set(dotted, float(r.rmse))
                if getattr(r, "note", None):  # each segment aligned on its own
                    summary.notes[dotted] = r.note

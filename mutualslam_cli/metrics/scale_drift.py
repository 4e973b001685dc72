"""Scale drift of a monocular trajectory: the local Sim(3) scale over short runs of keyframes against the
scale of the one Sim(3) over the whole trajectory, and the local ATE beside the global one.

A monocular map holds its scale only as far as its odometry does; a single whole-trajectory Sim(3) (the
ATE's headline, :func:`~mutualslam_cli.metrics.trajectory.ate`) hides *where* the unit changed. Strasdat,
Montiel and Davison, "Scale Drift-Aware Large Scale Monocular SLAM", RSS 2010, treat the scale of a
monocular map as a quantity of each keyframe that drifts; here it is measured against GT by aligning short
sub-trajectories on their own, as the relative error does over fixed intervals (Sturm et al., IROS 2012, the
RPE; Zhang and Scaramuzza, "A Tutorial on Quantitative Trajectory Evaluation for Visual(-Inertial)
Odometry", IROS 2018, the relative error over sub-trajectories, where a Sim(3) per sub-trajectory exposes
the scale drift):

1. associate the estimated keyframes with GT by timestamp (the ATE's association) and fit one Sim(3)
   (Umeyama 1991) over all pairs: scale ``s_glob`` (GT metres per map unit), RMSE = the global ATE;
2. for each window of ``N`` consecutive associated keyframes (stride 1: every window, so that the extremes
   do not depend on where the first window starts) fit a Sim(3) on that window alone: scale ``s_loc`` and
   the window's RMSE after its own fit (the *local ATE*);
3. report ``s_loc / s_ref`` per window, ``s_ref = s_glob`` (one segment) or its segment's scale (several): 1
   where the map's unit there equals its average unit.

A window must lie within one tracking segment (a front end that re-initialised starts each segment at an
origin and in a unit of its own: a window across the restart mixes two scales and is skipped). With several
segments the one Sim(3) over all of them has no meaningful scale (segments at unrelated origins: on a
two-segment test the whole fit's scale came out 1/40 of either segment's), so each window is then relative to
its own segment's Sim(3) (the per-segment ATE's alignment, :func:`~mutualslam_cli.metrics.trajectory.ate_segments`);
the global ATE stays the one Sim(3) over the whole (the headline). Windows whose positions are degenerate
(collinear: a pure straight line fixes no rotation) are skipped and counted.

Summary figures: ``max``, ``min`` of ``s_loc / s_ref``, ``max_over_min`` (how much the unit changed along
the run; 1 for a map that holds its scale), and the median local ATE over windows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT
from mutualslam_cli.errors import DatasetError, GeometryError
from mutualslam_cli.metrics.alignment import align_positions
from mutualslam_cli.metrics.trajectory import associate_indices
from mutualslam_cli.types import JSONObject, Trajectory, check_shape

#: Keyframes per window (the issue's default: long enough to fix a Sim(3), short enough to see the drift).
WINDOW = 15
#: Windows start at every associated keyframe (module docstring, 2).
STRIDE = 1


@dataclass
class ScaleDrift:
    """Local against global Sim(3) scale of one trajectory (module docstring).

    Attributes:
        window, stride: keyframes per window and between window starts.
        global_scale: ``s_glob`` of the one Sim(3) over all pairs (GT metres per map unit).
        global_rmse: the ATE RMSE (m) of that alignment (the headline ATE).
        n_pairs: associated keyframes.
        start, end: ``(W,)`` int, index (into the estimate) of each window's first and last keyframe.
        start_time: ``(W,)`` float, timestamp (s) of each window's first keyframe.
        segment: ``(W,)`` int, the segment of each window.
        rel_scale: ``(W,)`` ``s_loc / s_ref`` per window.
        ref_scale: ``(W,)`` ``s_ref``: ``s_glob``, or with several segments the window's segment's own Sim(3) scale.
        local_rmse: ``(W,)`` RMSE (m) of each window after its own Sim(3).
        n_crossing, n_degenerate: windows skipped for crossing a segment boundary / degenerate positions.
        per_segment: several segments: each window relative to its own segment's scale.
    """

    window: int
    stride: int
    global_scale: float
    global_rmse: float
    n_pairs: int
    start: np.ndarray
    end: np.ndarray
    start_time: np.ndarray
    segment: np.ndarray
    rel_scale: np.ndarray
    local_rmse: np.ndarray
    ref_scale: np.ndarray
    n_crossing: int = 0
    n_degenerate: int = 0
    per_segment: bool = False

    @property
    def max(self) -> float:
        return float(np.max(self.rel_scale))

    @property
    def min(self) -> float:
        return float(np.min(self.rel_scale))

    @property
    def max_over_min(self) -> float:
        """``max(s_loc) / min(s_loc)``: how far the map's unit moved along the run (1: it held)."""
        return self.max / self.min

    @property
    def local_ate(self) -> float:
        """Median over windows of the window RMSE after its own Sim(3), metres."""
        return float(np.median(self.local_rmse))

    def summary(self) -> JSONObject:
        """Plain values for ``summary.json`` (no arrays)."""
        return {"max": self.max, "min": self.min, "max_over_min": self.max_over_min, "local_ate_m": self.local_ate,
                "global_scale": self.global_scale, "global_ate_m": self.global_rmse, "windows": len(self.rel_scale),
                "window": self.window, "stride": self.stride, "n_crossing": self.n_crossing,
                "n_degenerate": self.n_degenerate,
                "per_segment": self.per_segment}


def _rmse(p_ref: np.ndarray, aligned: np.ndarray) -> float:
    """Translational RMSE (Sturm et al. 2012, eq. 3) of aligned positions ``(K, 3)``, metres."""
    return float(np.sqrt(np.mean(np.sum((p_ref - aligned) ** 2, axis=1))))


def scale_drift(
    ref: Trajectory,
    est: Trajectory,
    segments: np.ndarray | None = None,
    window: int = WINDOW,
    stride: int = STRIDE,
    max_dt: float = MAX_DT,
    association: Literal["nearest", "unique"] = "nearest",
) -> ScaleDrift:
    """Local Sim(3) scales of ``est`` over windows of ``window`` keyframes, relative to the whole-trajectory
    Sim(3) against ``ref`` (module docstring).

    Args:
        ref: GT trajectory (metres); est: the estimated keyframes (map units).
        segments: ``(M,)`` segment (map unit) of each pose of ``est`` (``None``: one segment).
        window: keyframes per window (≥ 3: a Sim(3) needs three non-collinear positions).
        stride: associated keyframes between the starts of two windows.

    Raises:
        ValueError: ``window < 3`` or ``stride < 1``.
        ShapeError: ``segments`` is not one id per estimated pose.
        DatasetError: no pair within ``max_dt``.
        GeometryError: fewer than ``window`` associated keyframes, a degenerate whole trajectory, or no
            window within one segment.
    """
    if window < 3 or stride < 1:
        raise ValueError(f"window {window} (≥ 3) and stride {stride} (≥ 1)")
    seg = np.zeros(len(est), np.int64) if segments is None else np.asarray(segments).reshape(-1)
    check_shape(seg, [len(est)], "segments (one id per est pose)")
    i_ref, i_est = associate_indices(ref.timestamps, est.timestamps, max_dt, association)
    if len(est) == 0:
        raise GeometryError("no keyframe")
    if len(i_ref) == 0:
        raise DatasetError(f"no keyframe within {max_dt:g} s of a GT pose")
    if len(i_ref) < window:
        raise GeometryError(f"{len(i_ref)} keyframes with GT < {window} (one window)")
    p_ref, p_est = ref.positions[i_ref], est.positions[i_est]
    aligned, _, _, s_glob = align_positions(p_ref, p_est, "sim3")
    seg_pair = seg[i_est]
    ref_scale = {int(sid): s_glob for sid in np.unique(seg_pair)}
    if len(ref_scale) > 1:  # each segment's own unit (module docstring)
        for sid in ref_scale:
            m = seg_pair == sid
            try:
                ref_scale[sid] = align_positions(p_ref[m], p_est[m], "sim3")[3] if m.sum() >= window else np.nan
            except GeometryError:
                ref_scale[sid] = np.nan
    rows: list[tuple[int, int, float, int, float, float, float]] = []
    n_cross = n_degen = 0
    for k in range(0, len(i_est) - window + 1, stride):
        sl = slice(k, k + window)
        if np.any(seg_pair[sl] != seg_pair[k]):
            n_cross += 1
            continue
        s_ref = ref_scale[int(seg_pair[k])]
        try:
            if not np.isfinite(s_ref):
                raise GeometryError("segment not aligned")
            al, _, _, s_loc = align_positions(p_ref[sl], p_est[sl], "sim3")  # Umeyama 1991 on the window alone
        except GeometryError:
            n_degen += 1
            continue
        rows.append((int(i_est[k]), int(i_est[k + window - 1]), float(est.timestamps[i_est[k]]), int(seg_pair[k]),
                     s_loc / s_ref, _rmse(p_ref[sl], al), s_ref))
    if not rows:
        raise GeometryError(f"no window of {window} keyframes within one segment could be aligned "
                            f"({n_cross} cross a segment boundary, {n_degen} degenerate)")
    start, end, t0, seg_ids, rel, loc, refs = (np.array(c) for c in zip(*rows))
    return ScaleDrift(window, stride, float(s_glob), _rmse(p_ref, aligned), len(i_ref), start.astype(np.int64),
                      end.astype(np.int64), t0.astype(np.float64), seg_ids.astype(np.int64), rel.astype(np.float64),
                      loc.astype(np.float64), refs.astype(np.float64), n_cross, n_degen,
                      len(ref_scale) > 1)

"""Evaluation metrics (DESIGN §7): depth accuracy (PCD, e_si, abs_rel) and trajectory ATE
(association and statistics in :mod:`.trajectory`, Umeyama alignment in :mod:`.alignment`); a run's
trajectory and map against GT (:mod:`.slam`: keyframe and all-frame ATE, the map's per-point log-depth
errors and e_si), whose summary keys the stages write.

Library code only (numpy, OpenCV for resizing); each formula cites its source next to the line.
"""

from mutualslam_cli.errors import GeometryError
from mutualslam_cli.metrics.alignment import umeyama
from mutualslam_cli.metrics.depth import (
    DepthStats,
    depth_frame_metrics,
    depth_stats,
    esi,
    percent_correct,
    resize_to,
    running_mean,
    scale_factor,
    valid_mask,
)
from mutualslam_cli.metrics.trajectory import (
    AteResult,
    SegmentedAteResult,
    associate_indices,
    associate_trajectories,
    ate,
    ate_segments,
    path_length,
)

__all__ = [
    "AteResult",
    "DepthStats",
    "GeometryError",
    "SegmentedAteResult",
    "associate_indices",
    "associate_trajectories",
    "ate",
    "ate_segments",
    "depth_frame_metrics",
    "depth_stats",
    "esi",
    "path_length",
    "percent_correct",
    "resize_to",
    "running_mean",
    "scale_factor",
    "umeyama",
    "valid_mask",
]

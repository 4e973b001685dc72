"""The front end's section of the run configuration (``vo:``): the monocular visual odometry
(:mod:`mutualslam_cli.vo`) and its oracles, map reuse, relocalisation and the joins of segments."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

from mutualslam_cli.config.checks import Relation, above, at_least, between, setting


@dataclass(frozen=True)
class VOConfig:
    """The front end's settings; each field's range is beside it, ``RELATIONS`` holds those between fields."""

    RELATIONS: ClassVar[tuple[Relation[VOConfig], ...]] = (
        Relation("max_fts", lambda c: c.max_fts >= c.min_tracked, lambda c: f"≥ min_tracked ({c.min_tracked})"),
    )

    mode: Literal["svo", "gt", "gt-depth"] = "svo"
    """``svo``: our monocular front end. ``gt``: pose oracle — our front end's keyframes and
    tracks with GT keyframe poses, map points re-triangulated from the tracks (metric, at our
    map's density; :mod:`~mutualslam_cli.vo.pose_oracle`). ``gt-depth``: GT poses and map
    points sampled from GT depth at ~5× our map's density, an upper bound that also leaks
    GT depth (:mod:`~mutualslam_cli.vo.depth_oracle`)."""
    grid_size: int = setting(20, at_least(4, "pixels"))
    """Feature detection grid cell in pixels (paper: grid_size 20)."""
    max_fts: int = setting(500, at_least(8))
    """Features per keyframe (paper: max_fts 500)."""
    core_kfs: int = setting(5, at_least(2, "keyframes"))
    """Keyframes in the windowed geometric BA (paper: core_kfs 5)."""
    klt_window: int = setting(17, at_least(5, "pixels"))
    """KLT patch size in pixels (the backward check uses ~¾ of it). 17 tracks as well as the
    common 21 on the shared sequences at ~30 % less KLT time (make bench)."""
    klt_levels: int = setting(3, at_least(0))
    """KLT pyramid levels above the base image."""
    fb_threshold_px: float = setting(1.0, above(0, "pixels"))
    """Forward–backward KLT error above which a track is dropped."""
    ransac_threshold_px: float = setting(2.0, above(0, "pixels"))
    """PnP-RANSAC inlier threshold."""
    kf_min_parallax_px: float = setting(30.0, above(0, "pixels"))
    """Median feature displacement since the last keyframe that triggers a new keyframe."""
    kf_min_tracked_ratio: float = setting(0.5, between(0, 1, lo_open=True))
    """Fraction of last keyframe's features still tracked below which a keyframe is made."""
    min_tracked: int = setting(30, at_least(6, "PnP needs at least 6 matches"))
    """Fewer map-point tracks than this within 2 × ``ransac_threshold_px`` of the pose is a tracking loss."""
    reuse_map: bool = True
    """Map reuse: at a keyframe (and when tracking is weak) the points of the whole map unit that project into
    the frame are matched again from the keyframe that saw them from the closest viewpoint, however old
    (SVO 2.0's overlapping keyframes, :mod:`~mutualslam_cli.vo.local_map`); ``false``: only the points of the
    newest ``core_kfs`` keyframes (the front end before issue 39)."""
    depth_seeds: bool = False
    """New depth-filter seeds start at the adapted network's depth in the map's unit, with the network's measured
    relative error as their deviation (CNN-SVO; :mod:`~mutualslam_cli.vo.depth_prior`). Needs the network: used in
    causal runs (``mslam run``), not by the front end on its own. ``false``: SVO's start (the paper)."""
    scale_prior: bool = False
    """A weak log-depth prior from the adapted network, at the map unit's reference scale, on the points the
    windowed BA's free keyframes host (:mod:`~mutualslam_cli.vo.depth_prior`). Causal runs only, as
    ``depth_seeds``. ``false``: the paper."""
    relocalise: bool = True
    """After a tracking loss, look for the frame among the existing keyframes (ORB descriptors of
    their map points, PnP-RANSAC, verified on the local map: :mod:`~mutualslam_cli.vo.relocalise`)
    and continue in the same map; ``false`` re-initialises a new segment at once (the paper's SVO)."""
    reloc_frames: int = setting(15, at_least(0, "frames"))
    """Frames after a loss during which only relocalisation may continue the map; a new segment is
    initialised after them (a camera that moved on to unseen parts cannot relocalise)."""
    bridge_segments: bool = True
    """Scale-consistent re-initialisation: a new segment (relocalisation failed) is joined to the map
    before it by the adaptation stage, scaled by the network's depth ratio on both sides of the gap
    and placed at the last tracked pose (:mod:`~mutualslam_cli.backend.bridges`); ``false`` keeps every
    segment in its own frame and unit (the paper's fresh start). Not part of the front end's cache key."""
    merge_segments: bool = True
    """A segment started after a tracking loss keeps looking for the map before it (the loop closure's place
    recognition and verification, its scale from nearby old and new points); when found, it is moved onto that
    map by the measured Sim(3), replacing its bridge or joining a segment whose bridge was refused (ORB-SLAM3's
    map merging, :mod:`~mutualslam_cli.backend.merge`). Needs the network (the scale), as bridges do; not part of
    the front end's cache key. ``false``: bridges only."""
    gt_kf_every: int = setting(5, at_least(1, "frames"))
    """``gt-depth`` oracle: a keyframe every k frames."""
    gt_max_points: int = setting(500, at_least(1))
    """``gt-depth`` oracle: map points per keyframe (from GT depth at detected corners)."""
    inject_outliers: float = setting(0.0, between(0, 1, hi_open=True))
    """Test knob: after the front end, this fraction of map points (seeded) gets a gross
    depth error, ×2 or ×0.4, so culling can be measured against known outliers. 0 = off. Not
    part of the front-end cache key (applied to the cached map)."""

"""The back end's sections of the run configuration: map-point culling + global photometric BA (``ba:``)
and loop closure (``loop:``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

from mutualslam_cli.config.checks import Relation, above, at_least, between, setting


@dataclass(frozen=True)
class BAConfig:
    """Culling + global BA; each field's range is beside it, ``RELATIONS`` holds those between fields."""

    RELATIONS: ClassVar[tuple[Relation[BAConfig], ...]] = (
        Relation("nearby_slots", lambda c: c.nearby_slots < c.max_targets,
                 lambda c: f"in [0, max_targets) (max_targets = {c.max_targets})"),
        Relation("huber_grey", lambda c: c.huber_grey <= c.outlier_grey,
                 lambda c: f"≤ outlier_grey ({c.outlier_grey})"),
    )

    enabled: bool = True
    """Run map-point culling and global photometric BA when Algorithm 1 triggers it and once at
    the end of the run (``false``: neither, the VO map and trajectory as they are)."""
    culling: bool = True
    """Cull map points with the adapted depth (Eq. 10) before each BA; ``false`` = BA without
    culling (the paper's Table 5 middle rows)."""
    gamma: float = setting(0.5, above(0))
    """γ of the culling rule (Eq. 10)."""
    d_max: float = setting(1.5, above(0, "map units"))
    """d_max of the culling rule, map units (Eq. 10)."""
    final: Literal["on_request", "always"] = "on_request"
    """When culling + global BA runs: ``on_request`` — only when Algorithm 1 requests it (the paper;
    the map after the run is the loop's map then, and without any request the run has no after-BA
    figures); ``always`` — also once more over the whole map at the end of the run."""
    pattern: Literal["dso", "square3"] = "square3"
    """Residual pattern: DSO's eight pixels spread over 5×5 (``dso``), or the dense 3×3 patch the paper
    names (``square3``, Alismail et al.)."""
    max_targets: int = setting(5, at_least(1))
    """Target keyframes per map point: its observations first, then keyframes nearby in space."""
    nearby_targets: bool = True
    """Add keyframes nearby in space as targets (paper §III-C: "re-projections to the nearby keyframes,
    including the existing 3D-2D constraints")."""
    nearby_slots: int = setting(2, at_least(0))
    """Targets per point kept for nearby keyframes: the existing observations take at most
    ``max_targets − nearby_slots`` (with ``nearby_targets``)."""
    iterations: int = setting(10, at_least(0))
    """Levenberg–Marquardt iterations at full resolution (shared by its ``rounds``)."""
    rounds: int = setting(2, at_least(1))
    """Rounds of outlier classification at full resolution (each keeps its active blocks)."""
    levels: int = setting(1, at_least(1))
    """Image pyramid levels (coarse-to-fine; fewer when the images are small). 1, as DSO's BA: on the
    ICL lr kt2 window from our VO 2.2 mm became 0.60 mm after BA with 1 level and 0.88 mm with 3, from
    GT poses the BA moved them 0.73 and 1.03 mm (the coarse levels' minima differ along weakly
    determined directions)."""
    image_scale: float = setting(1.0, between(0, 1, lo_open=True))
    """BA image resolution relative to the VO camera (1: full resolution on the finest level)."""
    huber_grey: float = setting(5.0, above(0, "grey levels"))
    """Huber threshold of a photometric residual, grey levels of 255. DSO uses 9 on photometrically
    calibrated images; on ours (measured with DSO's pattern and 3 levels) 5 moved GT poses least (ICL
    lr kt2 window: 0.8 mm instead of 1.2) and lowered the VO's ATE as much or more on four of the
    five sequences measured."""
    window: int = setting(0, at_least(0, "keyframes, 0 = the whole map"))
    """Keyframes a trigger's culling + BA works on: the newest W (the first of them fixed), older keyframes
    and their points untouched (0 = the whole map, the paper's global BA; > 0 bounds a trigger's cost)."""
    outlier_grey: float = setting(12.0, above(0, "grey levels"))
    """A block whose weighted energy exceeds this residual at every pixel is an outlier (DSO: 12)."""


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure (:mod:`~mutualslam_cli.backend.loop_detector`, :mod:`~mutualslam_cli.backend.pose_graph`): the
    paper's future work, off by default (the paper). The loop detector takes this record as its thresholds."""

    enabled: bool = False
    """Look for each new keyframe among the old ones; a verified loop is closed by a Sim(3) pose graph and a BA."""
    min_gap: int = setting(30, at_least(1, "keyframes"))
    """Keyframes between a loop's two ends at least (nearer ones are the odometry's own business)."""
    cooldown: int = setting(0, at_least(0, "keyframes"))
    """Keyframes after a loop or merge is closed in which no other is looked for. 0: every keyframe is queried —
    the revisits that follow a loop while drift is still there close it further; one that agrees with the map as
    it stands is not closed again (``already closed``). The old rule, ``min_gap`` here too, kept 57 of fr1_xyz's
    true revisits from being queried."""
    inlier_px: float = setting(4.0, above(0, "pixels"))
    """PnP inlier threshold of a loop's pose against the old map, pixels (the front end tracks at
    ``vo.ransac_threshold_px`` = 2): the old map has drifted since it was made, and RedKitchen's true revisits
    missed their own images by a median 2.1–2.9 px, so 2 px refused 20 of 22 of them on the inlier ratio."""
    witness_ratio: float = setting(0.3, between(0, 1))
    """Share of the old witness keyframes' points in view under the loop pose that their own images must find
    (KLT, unwarped, from up to 30° away); 0.5 refused 10 of RedKitchen's 22 true revisit pairs."""
    n_candidates: int = setting(3, at_least(1))
    """Old keyframes verified per new keyframe, best appearance first."""
    max_scale_error: float = setting(0.1, above(0))
    """Largest relative standard error of a loop's scale (the network's depth ratios on both ends)."""
    max_depth_spread: float = setting(0.25, above(0))
    """Largest relative spread (1.4826 × MAD / median) of the old points' depths under the loop pose against the
    network's depth."""

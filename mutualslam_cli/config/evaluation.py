"""The evaluation's sections of the run configuration: depth and trajectory metrics (``eval:``) and the
dense reconstruction scored after them (``dense:``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

from mutualslam_cli.config.checks import Relation, above, at_least, setting


@dataclass(frozen=True)
class EvalConfig:
    """Depth and trajectory metrics; each field's range is beside it."""

    pcd_threshold: float = setting(0.1, above(0, "relative error"))
    """Relative error below which a depth pixel counts as correct (paper §IV-B)."""
    max_depth: float = setting(10.0, above(0, "metres"))
    """GT depth above this (metres) is not evaluated."""
    stride: int = setting(1, at_least(1, "frames"))
    """Evaluate depth on every k-th frame with GT depth."""
    save_weights: bool = False
    """Write the adapted weights into the result folder."""
    ate_max_dt: float = setting(0.02, above(0, "seconds"))
    """Trajectory association threshold in seconds (TUM benchmark)."""
    batch: int = setting(0, at_least(0, "0 = auto"))
    """Frames per forward pass in the depth evaluation (results do not depend on it beyond rounding); 0 = 8 on
    a GPU, 1 on the CPU. Per frame, 640×192 bf16, 2 threads, AVX512-BF16: batch 1 60 ms, 2 58, 4 59, 8 72 — on
    the CPU it does not pay (OpenVINO runs one frame per call anyway)."""
    export_frames: int = setting(4, at_least(0))
    """Frames, evenly spread over the sequence, whose depth both models save (``depth/``: 16-bit PNG at
    5000 per unit, TUM's convention, and ``.npy``) and show in ``depth.png``, GT or not. 0 = none."""
    online: bool = True
    """Also score every evaluated frame with the model of its time, as the adaptation loop goes
    (:mod:`~mutualslam_cli.online.scores`; ``depth.pcd_online.*``): one more prediction per frame."""


@dataclass(frozen=True)
class DenseConfig:
    """Dense reconstruction from the adapted depth (:mod:`~mutualslam_cli.stages.dense`):
    TSDF fusion of both models' depth along the run's poses, in metres, scored against the same
    fusion of GT depth with GT poses. Defaults suit rooms. Each field's range is beside it, ``RELATIONS`` holds
    those between fields."""

    RELATIONS: ClassVar[tuple[Relation[DenseConfig], ...]] = (
        Relation("depth_min", lambda c: c.depth_min < c.depth_max, lambda c: f"< depth_max ({c.depth_max})"),
        Relation("scalings", lambda c: "sequence" in c.scalings and len(set(c.scalings)) == len(c.scalings),
                 lambda c: "a list that holds 'sequence' (the headline scores) and no name twice"),
    )

    enabled: bool = False
    """Run the dense stage after the evaluation (``mslam fuse RUN_DIR`` runs it on a finished run)."""
    every: int = setting(0, at_least(0, "0 = the keyframes"))
    """Frames fused: 0 = the keyframes; k > 0 = every k-th frame that has a pose."""
    scalings: list[Literal["sequence", "frame", "gt"]] = field(default_factory=lambda: ["sequence", "frame", "gt"])
    """Depth scalings fused and scored (:mod:`~mutualslam_cli.dense.scaling`), each one TSDF per model:
    ``sequence`` (one VO scale per sequence, the ``dense.<metric>.<model>`` keys; always included),
    ``frame`` (each frame's own VO scale, ``dense.frame_scale.*``), ``gt`` (each frame scaled to GT
    depth, an oracle, ``dense.gt_scale.*``). Leaving one out saves its fusion; its keys are null."""
    voxel_size: float = setting(0.02, above(0, "metres"))
    """TSDF voxel edge, metres (the F-score's 5 cm is 2.5 voxels). > 0."""
    trunc_voxels: float = setting(4.0, at_least(1, "voxels"))
    """Truncation distance in voxels (4 × 0.02 = 0.08 m). ≥ 1."""
    depth_min: float = setting(0.1, above(0, "metres"))
    """Depth below this (metres) is not fused. > 0."""
    depth_max: float = setting(4.0, above(0, "metres"))
    """Depth above this (metres) is not fused. > depth_min."""
    block_resolution: int = setting(8, at_least(2, "voxels"))
    """Voxels per block edge (8: 16 cm blocks; less empty space around a surface than 16)."""
    block_count: int = setting(40000, at_least(1))
    """Cap on the voxel blocks of one TSDF (allocated once, never grown): memory ≤ block_count ×
    block_resolution³ × 20 bytes (40000 × 8³ × 20 B = 410 MB). A frame that needs more blocks
    updates only the blocks that exist. ≥ 1."""
    weight_threshold: float = setting(1.0, at_least(0))
    """Surface extraction keeps voxels fused at least this many times. ≥ 0."""
    render_width: int = setting(480, at_least(32, "pixels"))
    """Width of each panel of ``dense.png``, pixels (height ¾ of it). ≥ 32."""

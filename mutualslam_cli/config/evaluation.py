"""The evaluation's sections of the run configuration: depth and trajectory metrics (``eval:``) and the
dense reconstruction scored after them (``dense:``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class EvalConfig:
    pcd_threshold: float = 0.1
    """Relative error below which a depth pixel counts as correct (paper §IV-B)."""
    max_depth: float = 10.0
    """GT depth above this (metres) is not evaluated."""
    stride: int = 1
    """Evaluate depth on every k-th frame with GT depth."""
    save_weights: bool = False
    """Write the adapted weights into the result folder."""
    ate_max_dt: float = 0.02
    """Trajectory association threshold in seconds (TUM benchmark)."""
    batch: int = 0
    """Frames per forward pass in the depth evaluation (results do not depend on it beyond rounding); 0 = 8 on
    a GPU, 1 on the CPU. Per frame, 640×192 bf16, 2 threads, AVX512-BF16: batch 1 60 ms, 2 58, 4 59, 8 72 — on
    the CPU it does not pay (OpenVINO runs one frame per call anyway)."""
    export_frames: int = 4
    """Frames, evenly spread over the sequence, whose depth both models save (``depth/``: 16-bit PNG at
    5000 per unit, TUM's convention, and ``.npy``) and show in ``depth.png``, GT or not. 0 = none."""
    online: bool = True
    """Also score every evaluated frame with the model of its time, as the adaptation loop goes
    (:mod:`~mutualslam_cli.online.scores`; ``depth.pcd_online.*``): one more prediction per frame."""


@dataclass(frozen=True)
class DenseConfig:
    """Dense reconstruction from the adapted depth (:mod:`~mutualslam_cli.stages.dense`):
    TSDF fusion of both models' depth along the run's poses, in metres, scored against the same
    fusion of GT depth with GT poses. Defaults suit rooms."""

    enabled: bool = False
    """Run the dense stage after the evaluation (``mslam fuse RUN_DIR`` runs it on a finished run)."""
    every: int = 0
    """Frames fused: 0 = the keyframes; k > 0 = every k-th frame that has a pose."""
    scalings: list[Literal["sequence", "frame", "gt"]] = field(default_factory=lambda: ["sequence", "frame", "gt"])
    """Depth scalings fused and scored (:mod:`~mutualslam_cli.dense.scaling`), each one TSDF per model:
    ``sequence`` (one VO scale per sequence, the ``dense.<metric>.<model>`` keys; always included),
    ``frame`` (each frame's own VO scale, ``dense.frame_scale.*``), ``gt`` (each frame scaled to GT
    depth, an oracle, ``dense.gt_scale.*``). Leaving one out saves its fusion; its keys are null."""
    voxel_size: float = 0.02
    """TSDF voxel edge, metres (the F-score's 5 cm is 2.5 voxels). > 0."""
    trunc_voxels: float = 4.0
    """Truncation distance in voxels (4 × 0.02 = 0.08 m). ≥ 1."""
    depth_min: float = 0.1
    """Depth below this (metres) is not fused. > 0."""
    depth_max: float = 4.0
    """Depth above this (metres) is not fused. > depth_min."""
    block_resolution: int = 8
    """Voxels per block edge (8: 16 cm blocks; less empty space around a surface than 16)."""
    block_count: int = 40000
    """Cap on the voxel blocks of one TSDF (allocated once, never grown): memory ≤ block_count ×
    block_resolution³ × 20 bytes (40000 × 8³ × 20 B = 410 MB). A frame that needs more blocks
    updates only the blocks that exist. ≥ 1."""
    weight_threshold: float = 1.0
    """Surface extraction keeps voxels fused at least this many times. ≥ 0."""
    render_width: int = 480
    """Width of each panel of ``dense.png``, pixels (height ¾ of it). ≥ 32."""

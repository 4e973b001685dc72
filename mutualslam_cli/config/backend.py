"""The run configuration's sections for what comes after the adaptation loop's inputs: culling + global BA,
evaluation, loop closure, dense reconstruction, and the experiment grids (re-exported by
:mod:`mutualslam_cli.config`, whose :class:`~mutualslam_cli.config.RunConfig` holds them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class BAConfig:
    enabled: bool = True
    """Run map-point culling and global photometric BA when Algorithm 1 triggers it and once at
    the end of the run (``false``: neither, the VO map and trajectory as they are)."""
    culling: bool = True
    """Cull map points with the adapted depth (Eq. 10) before each BA; ``false`` = BA without
    culling (the paper's Table 5 middle rows)."""
    gamma: float = 0.5
    """γ of the culling rule (Eq. 10)."""
    d_max: float = 1.5
    """d_max of the culling rule, map units (Eq. 10)."""
    final: Literal["on_request", "always"] = "on_request"
    """When culling + global BA runs: ``on_request`` — only when Algorithm 1 requests it (the paper;
    the map after the run is the loop's map then, and without any request the run has no after-BA
    figures); ``always`` — also once more over the whole map at the end of the run."""
    pattern: Literal["dso", "square3"] = "square3"
    """Residual pattern: DSO's eight pixels spread over 5×5 (``dso``), or the dense 3×3 patch the paper
    names (``square3``, Alismail et al.)."""
    max_targets: int = 5
    """Target keyframes per map point: its observations first, then keyframes nearby in space."""
    nearby_targets: bool = True
    """Add keyframes nearby in space as targets (paper §III-C: "re-projections to the nearby keyframes,
    including the existing 3D-2D constraints")."""
    nearby_slots: int = 2
    """Targets per point kept for nearby keyframes: the existing observations take at most
    ``max_targets − nearby_slots`` (with ``nearby_targets``)."""
    iterations: int = 10
    """Levenberg–Marquardt iterations at full resolution (shared by its ``rounds``)."""
    rounds: int = 2
    """Rounds of outlier classification at full resolution (each keeps its active blocks)."""
    levels: int = 1
    """Image pyramid levels (coarse-to-fine; fewer when the images are small). 1, as DSO's BA: on the
    ICL lr kt2 window from our VO 2.2 mm became 0.60 mm after BA with 1 level and 0.88 mm with 3, from
    GT poses the BA moved them 0.73 and 1.03 mm (the coarse levels' minima differ along weakly
    determined directions)."""
    image_scale: float = 1.0
    """BA image resolution relative to the VO camera (1: full resolution on the finest level)."""
    huber_grey: float = 5.0
    """Huber threshold of a photometric residual, grey levels of 255. DSO uses 9 on photometrically
    calibrated images; on ours (measured with DSO's pattern and 3 levels) 5 moved GT poses least (ICL
    lr kt2 window: 0.8 mm instead of 1.2) and lowered the VO's ATE as much or more on four of the
    five sequences measured."""
    window: int = 0
    """Keyframes a trigger's culling + BA works on: the newest W (the first of them fixed), older keyframes
    and their points untouched (0 = the whole map, the paper's global BA; > 0 bounds a trigger's cost)."""
    outlier_grey: float = 12.0
    """A block whose weighted energy exceeds this residual at every pixel is an outlier (DSO: 12)."""


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
    (:mod:`~mutualslam_cli.stages.online_eval`; ``depth.pcd_online.*``): one more prediction per frame."""


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure (:mod:`~mutualslam_cli.vo.loop_closure`, :mod:`~mutualslam_cli.ba.pose_graph`): the paper's
    future work, off by default (the paper)."""

    enabled: bool = False
    """Look for each new keyframe among the old ones; a verified loop is closed by a Sim(3) pose graph and a BA."""
    min_gap: int = 30
    """Keyframes between a loop's two ends at least; also between two loops closed."""
    n_candidates: int = 3
    """Old keyframes verified per new keyframe, best appearance first."""
    max_scale_error: float = 0.1
    """Largest relative standard error of a loop's scale (the network's depth ratios on both ends)."""
    max_depth_spread: float = 0.25
    """Largest relative spread of the old points' depths under the loop pose against the network's depth."""


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


@dataclass(frozen=True)
class ExperimentConfig:
    """What a paper experiment runs (``mslam ablate --config configs/<experiment>.yaml``) and reports."""

    name: str = ""
    """The experiment (e.g. ``table3_schemes``); empty for an ordinary run."""
    schemes: list[str] = field(default_factory=list)
    """Schemes ``mslam ablate`` runs when ``--schemes`` is not given (empty: its default list)."""
    seeds: list[int] = field(default_factory=list)
    """Seeds ``mslam ablate`` runs when ``--seeds`` is not given (empty: seed 0)."""
    ours: str = "replay+ewc"
    """The scheme the paper tables report as "Ours"."""
    variants: dict[str, list[str]] = field(default_factory=dict)
    """Named config variants, label → ``key=value`` overrides: ``mslam ablate`` runs the whole grid once
    per variant into ``<out>/<label>/`` (e.g. Table 5's culling off and ``vo.max_fts`` 120)."""

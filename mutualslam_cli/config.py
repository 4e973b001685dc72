"""Run configuration: frozen dataclasses, loaded with ``yaml.safe_load`` and validated. ``configs/paper.yaml``
holds the paper's values (DESIGN §4–7), which are the defaults: a missing key means "the paper's value".
``--set section.key=value`` overrides one field; the value is parsed as YAML (``--set adapt.lr=1e-4``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from mutualslam_cli.config_parse import apply_overrides, build, check_run
from mutualslam_cli.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


@dataclass(frozen=True)
class DataConfig:
    data_root: str | None = None
    """Root for relative ``datasets.yaml`` paths; ``None`` → ``$MSLAM_DATA`` or the yaml's folder."""
    max_frames: int = 0
    """Use only the first N associated frames (0 = all)."""
    stride: int = 1
    """Use every k-th frame."""


@dataclass(frozen=True)
class VOConfig:
    mode: Literal["svo", "gt", "gt-depth"] = "svo"
    """``svo``: our monocular front end. ``gt``: pose oracle — our front end's keyframes and
    tracks with GT keyframe poses, map points re-triangulated from the tracks (metric, at our
    map's density; :mod:`~mutualslam_cli.vo.pose_oracle`). ``gt-depth``: GT poses and map
    points sampled from GT depth at ~5× our map's density, an upper bound that also leaks
    GT depth (:mod:`~mutualslam_cli.vo.depth_oracle`)."""
    grid_size: int = 20
    """Feature detection grid cell in pixels (paper: grid_size 20)."""
    max_fts: int = 500
    """Features per keyframe (paper: max_fts 500)."""
    core_kfs: int = 5
    """Keyframes in the windowed geometric BA (paper: core_kfs 5)."""
    klt_window: int = 17
    """KLT patch size in pixels (the backward check uses ~¾ of it). 17 tracks as well as the
    common 21 on the shared sequences at ~30 % less KLT time (make bench)."""
    klt_levels: int = 3
    """KLT pyramid levels above the base image."""
    fb_threshold_px: float = 1.0
    """Forward–backward KLT error above which a track is dropped."""
    ransac_threshold_px: float = 2.0
    """PnP-RANSAC inlier threshold."""
    kf_min_parallax_px: float = 30.0
    """Median feature displacement since the last keyframe that triggers a new keyframe."""
    kf_min_tracked_ratio: float = 0.5
    """Fraction of last keyframe's features still tracked below which a keyframe is made."""
    min_tracked: int = 30
    """Fewer map-point tracks than this within 2 × ``ransac_threshold_px`` of the pose is a tracking loss."""
    relocalise: bool = True
    """After a tracking loss, look for the frame among the existing keyframes (ORB descriptors of
    their map points, PnP-RANSAC, verified on the local map: :mod:`~mutualslam_cli.vo.relocalise`)
    and continue in the same map; ``false`` re-initialises a new segment at once (the paper's SVO)."""
    reloc_frames: int = 15
    """Frames after a loss during which only relocalisation may continue the map; a new segment is
    initialised after them (a camera that moved on to unseen parts cannot relocalise)."""
    bridge_segments: bool = True
    """Scale-consistent re-initialisation: a new segment (relocalisation failed) is joined to the map
    before it by the adaptation stage, scaled by the network's depth ratio on both sides of the gap
    and placed at the last tracked pose (:mod:`~mutualslam_cli.vo.segments`); ``false`` keeps every
    segment in its own frame and unit (the paper's fresh start). Not part of the front end's cache key."""
    gt_kf_every: int = 5
    """``gt-depth`` oracle: a keyframe every k frames."""
    gt_max_points: int = 500
    """``gt-depth`` oracle: map points per keyframe (from GT depth at detected corners)."""
    inject_outliers: float = 0.0
    """Test knob: after the front end, this fraction of map points (seeded) gets a gross
    depth error, ×2 or ×0.4, so culling can be measured against known outliers. 0 = off. Not
    part of the front-end cache key (applied to the cached map)."""


@dataclass(frozen=True)
class NetConfig:
    width: int = 640
    """Network input width (Monodepth2 mono+stereo_640x192)."""
    height: int = 192
    """Network input height."""
    min_depth: float = 0.1
    """disp_to_depth minimum depth (Monodepth2)."""
    max_depth: float = 100.0
    """disp_to_depth maximum depth (Monodepth2)."""
    weights: str | None = None
    """Folder with encoder.pth/depth.pth; ``None`` → the ``mslam pretrain`` default model."""
    fast: Literal["auto", "on", "off"] = "auto"
    """bf16 autocast + channels-last: ``auto`` enables it where the CPU supports bf16."""
    runtime: Literal["auto", "torch", "openvino", "openvino-int8"] = "auto"
    """Depth evaluation runtime (:mod:`~mutualslam_cli.adapt.inference`): ``auto`` = OpenVINO when
    installed and ``fast`` is not ``off``, in bf16 where the CPU has it (40 vs 64 ms per frame here),
    else in int8 calibrated on 8 frames of the sequence (:mod:`~mutualslam_cli.adapt.quantize`)."""


@dataclass(frozen=True)
class AdaptConfig:
    scheme: str = "replay+ewc"
    """Adaptation scheme (registry name); ``none`` keeps the pre-trained model."""
    lr: float = 1e-4
    """Adam learning rate (paper §IV: 1e-3; 1e-4 here, see configs/paper.yaml)."""
    lambda_sparse: float = 0.1
    """λ1, weight of L_sparse (Eq. 7)."""
    lambda_smooth: float = 0.1
    """λ2, weight of L_smooth (Eq. 7)."""
    alpha: float = 0.85
    """SSIM/L1 balance α in pe (Eq. 4)."""
    ewc_beta: float = 5e7
    """β of Eq. 1."""
    ewc_max_f: float = 1e-3
    """max_F cap of Eq. 2 (applied as min, DESIGN §5)."""
    mas_lambda: float = 43.0
    """λ of Eq. 19 for MAS. Paper (Appendix B): 0.5, which acts ~75× more weakly than the paper's EWC
    (mean shrink 0.0006 vs 0.046); 43 gives MAS EWC's measured strength
    (:mod:`~mutualslam_cli.bench.strength`, README "Regulariser strength")."""
    si_lambda: float = 240.0
    """λ of Eq. 19 for SI. Paper (Appendix B): 1.0, ~200× weaker than the paper's EWC (shrink 0.0002
    vs 0.046); 240 gives SI EWC's measured strength (:mod:`~mutualslam_cli.bench.strength`)."""
    si_xi: float = 1e-3
    """ξ damping of SI's importance (Zenke et al.)."""
    steps_per_keyframe: int = 8
    """Optimiser steps per training keyframe (the paper's loop is asynchronous and does not fix it)."""
    labels: Literal["causal", "hindsight"] = "causal"
    """``causal``: the front end and Algorithm 1 share one clock — a step or validation at time t uses the map
    as it stood at t, bridges and global BAs reach the front end then (DESIGN §5). ``hindsight`` (a diagnostic):
    the front end runs to the end first, every keyframe is trained on the final map, segments bridged after it."""
    schedule: Literal["fixed", "realtime"] = "fixed"
    """``fixed``: ``steps_per_keyframe`` steps each; ``realtime``: the loop on the sequence's clock, every piece
    of its work charged, trained until the next keyframe arrives (:mod:`~mutualslam_cli.stages.realtime`)."""
    step_cost_ms: float | Literal["measured"] = 250.0
    """``realtime``: the cost of one optimiser step, ms of sequence time (250: the paper's GPU, DESIGN §10);
    ``measured``: this machine's step, all other work at its wall time (:mod:`~mutualslam_cli.stages.realtime`)."""
    max_steps: int = 32
    """``realtime``: cap on one keyframe's steps (a camera at rest makes long keyframe intervals)."""
    train_width: int = 0
    """Fine-tuning resolution (multiple of 32, ≤ net.width; 0 = net.width): batches are resampled (area)
    to it, intrinsics and sparse pixels scaled. Depth is still predicted and evaluated at net size."""
    train_height: int = 0
    """Fine-tuning height (multiple of 32, ≤ net.height; 0 = net.height)."""
    freeze_stages: int = 0
    """Leading encoder stages kept fixed (0–5: conv1+bn1, layer1, …, layer4): no gradient, no backward."""
    anchor: Literal["previous_batch", "batch_start", "lagged"] = "previous_batch"
    """θ*: parameters after the previous batch (paper; = start of this batch) or one batch earlier (lagged)."""
    reg_mode: Literal["prox", "penalty"] = "prox"
    """How EWC/MAS/SI enter the update: a proximal step after each Adam step, or added to the loss."""
    val_scope: Literal["all", "current"] = "all"
    """L_val over all validation keyframes so far, or only the arriving one."""
    val_max: int = 0
    """``all``: at most this many validation keyframes, evenly spread from the first to the newest (0 = every one)."""
    validate_every: int = 5
    """m of Algorithm 1."""
    patience: int = 3
    """n of Algorithm 1."""
    tau_val: float = 0.2
    """τ_val of Algorithm 1 (threshold on L_val = L_sparse)."""
    replay_capacity: int = 0
    """Keyframes kept for replay (0 = all, stored at network resolution)."""
    luo_window: int = 3
    """Scheme ``luo``: the most recent training keyframes (target included) searched for its stereo partners
    (≤ ``luo_window − 1`` sources; 3: Eq. 3's two, a step costs what ``recent``'s does; 4 and 5 found no more
    partners on tum_fr1_xyz, redkitchen_7scenes, icl_lr_kt2). ≥ 2."""
    luo_min_horizontal_ratio: float = 0.8
    """Scheme ``luo``: a keyframe pair is a simulated stereo pair only if |t_x| / ‖t‖ ≥ this, t the
    partner's camera centre in the target camera's frame (x: along the image rows). 0.8 = at most
    36.9° off the x axis, |t_x| ≥ 4/3·‖(t_y, t_z)‖: dominant with a margin over 1/√2 (x holds half of
    ‖t‖²). A zero baseline never qualifies. In [0, 1]."""
    luo_max_rotation_deg: float = 5.0
    """Scheme ``luo``: … and their relative rotation angle is ≤ this, degrees (a rectified stereo
    pair has none). Rotation alone then moves the image by ≤ f·tan 5° ≈ 0.09·f. With the default
    ratio and window, 27 %, 44 % and 42 % of the keyframes of the three sequences above find a
    partner (10°: 27 %, 47 %, 83 % — ICL's keyframes pan by 4.8° median). In [0, 180]."""
    comoda_lr: float = 1e-4
    """Scheme ``comoda`` (CoMoDa-style end-to-end baseline, ``adapt/comoda.py``): Adam learning rate of
    the joint depth + pose update (CoMoDa's / Monodepth2's 1e-4, Adam β = (0.9, 0.999)). > 0."""
    comoda_steps_per_frame: int = 1
    """Scheme ``comoda``: Adam steps per arriving frame (CoMoDa: one update per frame). ≥ 1."""
    comoda_replay_from: Literal["source", "sequence"] = "source"
    """Scheme ``comoda``: what is replayed. ``source``: a fixed bank of triplets of the pre-training
    domain, rendered at the start (CoMoDa replays samples of its KITTI training set; ``comoda_source``);
    ``sequence``: a reservoir of this sequence's own past triplets."""
    comoda_replay_per_step: int = 3
    """Scheme ``comoda``: past triplets drawn uniformly from the replay buffer into each update batch,
    beside the current triplet (batch = 1 + this, as CoMoDa mixes the current sample with replayed
    ones). ≥ 0; 0 = no replay."""
    comoda_replay_capacity: int = 200
    """Scheme ``comoda``: triplets kept for replay: the size of the source-domain bank (200: rendered
    in ~90 s by a results folder's first comoda run, then read from ``<out>/_cache/comoda/``), or of
    the reservoir over the sequence's whole past (a uniform sample of it). Stored at network
    resolution as uint8: 200 triplets at 640×192 are 221 MB (DESIGN §10: ≤ 3 GB, flat in sequence
    length). ≥ 1."""
    comoda_smoothness: float = 1e-3
    """Scheme ``comoda``: weight of the edge-aware smoothness (Monodepth2's 1e-3, which CoMoDa keeps). ≥ 0."""
    comoda_min_motion: float = 0.0
    """Scheme ``comoda``: motion gate. A triplet whose mean absolute intensity change
    ``mean|I_t − I_s|`` (images in [0, 1], s = t ± 1) is below this for either source is static: no
    update, not stored for replay. CoMoDa skips frames where the car stands still by its GPS speed,
    which indoor sequences do not have; the per-pixel auto-mask still removes static pixels.
    0 = off (default). ≥ 0."""
    comoda_pose_weights: str = ""
    """Scheme ``comoda``: folder with Monodepth2's ``pose_encoder.pth`` + ``pose.pth``. Empty: the
    depth weights folder's (``net.weights``) pose files when present (Monodepth2's released models
    ship them beside ``encoder.pth``), else the default weights folder's (``mslam pretrain`` writes
    them), else the pose encoder is initialised from the depth encoder (``conv1`` repeated over the
    two frames and halved, as Monodepth2 initialises it from ImageNet) with a random decoder, and a
    warning is logged. ``summary.json`` names the choice (``adaptation.pose_network``)."""


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


@dataclass(frozen=True)
class RunConfig:
    seed: int = 0
    """Seed of every random choice (replay sampling, RANSAC, init)."""
    threads: int = 0
    """torch/OpenCV threads (0 = all cores)."""
    device: str = "auto"
    """Where the depth network runs: ``auto`` (CUDA when ``torch.cuda.is_available()``, else the CPU), ``cpu``,
    ``cuda`` or ``cuda:N``; VO, BA and metrics always run on the CPU (:mod:`~mutualslam_cli.device`)."""
    deterministic: bool = True
    """CUDA: deterministic cuDNN algorithms, no autotuning (one seed, one result; slower convolution backward
    kernels); ``false``: ``cudnn.benchmark`` autotuning (:mod:`~mutualslam_cli.device`). No effect on the CPU."""
    out: str = "results"
    """Folder that receives ``<sequence>/<scheme>/seed<k>/``."""
    data: DataConfig = field(default_factory=DataConfig)
    vo: VOConfig = field(default_factory=VOConfig)
    net: NetConfig = field(default_factory=NetConfig)
    adapt: AdaptConfig = field(default_factory=AdaptConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config (safe for ``yaml.safe_dump`` and JSON)."""
    return dataclasses.asdict(cfg)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> RunConfig:
    """Load a YAML config (default ``configs/paper.yaml``), apply ``--set`` overrides, validate.

    Raises:
        ConfigError: missing file, invalid YAML, unknown key, wrong type, invalid value.
    """
    path = Path(path) if path is not None else CONFIG_DIR / "paper.yaml"
    data: dict[str, Any] = {}
    if path.exists():
        try:
            loaded = yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{path}: expected a mapping of sections (seed, vo, net, adapt, ...)")
        data = loaded or {}
    elif path != CONFIG_DIR / "paper.yaml":
        raise ConfigError(f"{path}: config file not found")
    cfg = build(RunConfig, apply_overrides(data, overrides or [], create=True), "")
    check_run(cfg)
    return cfg


def with_settings(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """Return ``cfg`` with ``--set``-style ``key=value`` overrides applied (validated like a file)."""
    out = build(RunConfig, apply_overrides(to_dict(cfg), overrides, create=False), "")
    check_run(out)
    return out


def with_overrides(cfg: RunConfig, **sections: dict[str, Any]) -> RunConfig:
    """Return ``cfg`` with some fields replaced: ``with_overrides(cfg, adapt={"scheme": "none"})``."""
    data = to_dict(cfg)
    for sec, vals in sections.items():
        if isinstance(vals, dict):
            data[sec].update(vals)
        else:
            data[sec] = vals
    out = build(RunConfig, data, "")
    check_run(out)
    return out

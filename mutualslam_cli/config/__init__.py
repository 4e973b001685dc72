"""Run configuration: frozen dataclasses, loaded with ``yaml.safe_load`` and validated. ``configs/paper.yaml``
holds the paper's values (DESIGN §4–7), which are the defaults: a missing key means "the paper's value".
``--set section.key=value`` overrides one field; the value is parsed as YAML (``--set adapt.lr=1e-4``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from mutualslam_cli.config.parse import apply_overrides, build, check_run
from mutualslam_cli.config.backend import BAConfig, DenseConfig, EvalConfig, ExperimentConfig, LoopConfig
from mutualslam_cli.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parent.parent.parent / "configs"


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
    reloc_frames: int = 15
    """Frames after a loss during which only relocalisation may continue the map; a new segment is
    initialised after them (a camera that moved on to unseen parts cannot relocalise)."""
    bridge_segments: bool = True
    """Scale-consistent re-initialisation: a new segment (relocalisation failed) is joined to the map
    before it by the adaptation stage, scaled by the network's depth ratio on both sides of the gap
    and placed at the last tracked pose (:mod:`~mutualslam_cli.vo.segments`); ``false`` keeps every
    segment in its own frame and unit (the paper's fresh start). Not part of the front end's cache key."""
    merge_segments: bool = True
    """A segment started after a tracking loss keeps looking for the map before it (the loop closure's place
    recognition and verification, its scale from nearby old and new points); when found, it is moved onto that
    map by the measured Sim(3), replacing its bridge or joining a segment whose bridge was refused (ORB-SLAM3's
    map merging, :mod:`~mutualslam_cli.stages.merge`). Needs the network (the scale), as bridges do; not part of
    the front end's cache key. ``false``: bridges only."""
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
    """Scheme ``luo``: … and their relative rotation is ≤ this, degrees (a rectified pair has none; 5°: 27 %, 44 %,
    42 % of the three sequences' keyframes find a partner, 10°: 27 %, 47 %, 83 %). In [0, 180]."""
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
    """Scheme ``comoda``: triplets kept for replay: the source-domain bank (rendered once into
    ``<out>/_cache/comoda/``) or a reservoir over the sequence's past; uint8 at network resolution (200 at
    640×192: 221 MB). ≥ 1."""
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
    loop: LoopConfig = field(default_factory=LoopConfig)
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

"""The depth network's sections of the run configuration: the network itself (``net:``: input size,
depth range, weights, runtime) and its online adaptation (``adapt:``: the scheme, Algorithm 1's constants,
the losses, the regularisers, and the ``luo`` and ``comoda`` baselines' settings)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

from mutualslam_cli.config.checks import FRACTION, NOT_EMPTY, Range, Relation, above, at_least, between, setting


@dataclass(frozen=True)
class NetConfig:
    """The depth network's settings; each field's range is beside it, ``RELATIONS`` holds those between fields."""

    RELATIONS: ClassVar[tuple[Relation[NetConfig], ...]] = (
        Relation("min_depth", lambda c: c.min_depth < c.max_depth, lambda c: f"< max_depth ({c.max_depth})"),
    )

    width: int = setting(640, Range(lo=32, hi=8192, multiple_of=32))
    """Network input width (Monodepth2 mono+stereo_640x192)."""
    height: int = setting(192, Range(lo=32, hi=8192, multiple_of=32))
    """Network input height."""
    min_depth: float = setting(0.1, above(0))
    """disp_to_depth minimum depth (Monodepth2)."""
    max_depth: float = setting(100.0, above(0))
    """disp_to_depth maximum depth (Monodepth2)."""
    weights: str | None = None
    """Folder with encoder.pth/depth.pth; ``None`` → the ``mslam pretrain`` default model."""
    fast: Literal["auto", "on", "off"] = "auto"
    """bf16 autocast + channels-last: ``auto`` enables it where the CPU supports bf16."""
    fast_train: Literal["decoder", "all"] = "decoder"
    """What trains in mixed precision on the fast path: ``decoder`` (the encoder's gradients in fp32, the
    adapted model within 1.1 PCD points of fp32's, README "Precision") or ``all`` (the encoder too: a
    faster step, and a model 3–6 points away from fp32's on the shared windows,
    :mod:`~mutualslam_cli.adapt.depthnet`)."""
    runtime: Literal["auto", "torch", "openvino", "openvino-int8"] = "auto"
    """Depth evaluation runtime (:mod:`~mutualslam_cli.adapt.inference`): ``auto`` = OpenVINO when
    installed and ``fast`` is not ``off``, in bf16 where the CPU has it (40 vs 64 ms per frame here),
    else in fp32; ``openvino-int8``: int8 calibrated on 8 frames of the sequence
    (:mod:`~mutualslam_cli.adapt.quantize`), faster on AVX2 but it moves an adapted model's PCD by 1–18 points."""


@dataclass(frozen=True)
class AdaptConfig:
    """The online adaptation's settings; each field's range is beside it."""

    scheme: str = setting("replay+ewc", NOT_EMPTY)
    """Adaptation scheme (registry name); ``none`` keeps the pre-trained model."""
    lr: float = setting(1e-3, above(0))
    """Adam learning rate: the paper's 1e-3 (§IV). ``configs/tuned.yaml`` sets 1e-4, chosen on tum_fr1_xyz, which
    the book therefore reports only on other data."""
    lambda_sparse: float = setting(0.1, at_least(0))
    """λ1, weight of L_sparse (Eq. 7)."""
    lambda_smooth: float = setting(0.1, at_least(0))
    """λ2, weight of L_smooth (Eq. 7)."""
    alpha: float = setting(0.85, FRACTION)
    """SSIM/L1 balance α in pe (Eq. 4)."""
    ewc_beta: float = setting(5e7, at_least(0))
    """β of Eq. 1."""
    ewc_max_f: float = setting(1e-3, at_least(0))
    """max_F cap of Eq. 2 (applied as min, DESIGN §5)."""
    mas_lambda: float = setting(43.0, at_least(0))
    """λ of Eq. 19 for MAS. Paper (Appendix B): 0.5, which acts ~75× more weakly than the paper's EWC
    (mean shrink 0.0006 vs 0.046); 43 gives MAS EWC's measured strength
    (:mod:`~mutualslam_cli.bench.strength`, README "Regulariser strength")."""
    si_lambda: float = setting(240.0, at_least(0))
    """λ of Eq. 19 for SI. Paper (Appendix B): 1.0, ~200× weaker than the paper's EWC (shrink 0.0002
    vs 0.046); 240 gives SI EWC's measured strength (:mod:`~mutualslam_cli.bench.strength`)."""
    si_xi: float = setting(1e-3, above(0))
    """ξ damping of SI's importance (Zenke et al.)."""
    steps_per_keyframe: int = setting(8, at_least(1))
    """Optimiser steps per training keyframe (the paper's loop is asynchronous and does not fix it)."""
    labels: Literal["causal", "hindsight"] = "causal"
    """``causal``: the front end and Algorithm 1 share one clock — a step or validation at time t uses the map
    as it stood at t, bridges and global BAs reach the front end then (DESIGN §5). ``hindsight`` (a diagnostic):
    the front end runs to the end first, every keyframe is trained on the final map, segments bridged after it."""
    schedule: Literal["fixed", "realtime"] = "fixed"
    """``fixed``: ``steps_per_keyframe`` steps each; ``realtime``: the loop on the sequence's clock, every piece
    of its work charged, trained until the next keyframe arrives (:mod:`~mutualslam_cli.online.realtime`)."""
    step_cost_ms: float | Literal["measured"] = setting(250.0, above(0, "or 'measured'"))
    """``realtime``: the cost of one optimiser step, ms of sequence time (250: the paper's GPU, DESIGN §10);
    ``measured``: this machine's step, all other work at its wall time (:mod:`~mutualslam_cli.online.realtime`)."""
    max_steps: int = setting(32, at_least(1))
    """``realtime``: cap on one keyframe's steps (a camera at rest makes long keyframe intervals)."""
    train_width: int = setting(0, Range(lo=0, multiple_of=32, unit="0 = net.width"))
    """Fine-tuning resolution (multiple of 32, ≤ net.width; 0 = net.width): batches are resampled (area)
    to it, intrinsics and sparse pixels scaled. Depth is still predicted and evaluated at net size."""
    train_height: int = setting(0, Range(lo=0, multiple_of=32, unit="0 = net.height"))
    """Fine-tuning height (multiple of 32, ≤ net.height; 0 = net.height)."""
    freeze_stages: int = setting(0, between(0, 5, "encoder stages"))
    """Leading encoder stages kept fixed (0–5: conv1+bn1, layer1, …, layer4): no gradient, no backward."""
    scale: Literal["learn", "align", "align_batch", "calibrate"] = "learn"
    """How the network meets the map's arbitrary units. ``learn`` (the paper): it learns them from L_sparse and
    L_photo. ``align_batch`` (configs/default.yaml): the batch's predicted depth is scaled by one factor, the median
    ratio of its map points' depths to the prediction, before the losses, so training asks for the depth's shape
    and the keyframes' relative scale, never for the map's unit; ``align``: one factor per image (the frames' scales
    then drift apart); ``calibrate``: the factor of the first keyframe trained on, once, then ``learn``. The
    network carries the factor as :attr:`DepthNet.unit`, so what reads its depth gets map units
    (:func:`~mutualslam_cli.adapt.losses.label_scale`; README "Adapting without picking a rate")."""
    encoder_lr: float = setting(1.0, above(0))
    """The encoder's learning rate as a fraction of ``lr`` (1 = the paper: one rate for the whole network). The
    encoder holds the pre-trained features every later layer reads; a smaller share keeps them while the decoder
    adapts (README "Adapting without picking a rate")."""
    trust: float = setting(0.0, at_least(0, "0 = off"))
    """Trust region of one optimiser step: each parameter tensor moves by at most ``trust·‖θ‖`` (0 = off, the
    paper). Adam moves every weight by about ``lr`` whatever its size; this bounds the relative change instead."""
    average: float = setting(0.0, Range(lo=0.0, hi=0.999, unit="0 = off"))
    """Weight average: after each batch the network that predicts (L_val, culling, evaluation) is
    ``a·previous + (1 − a)·trained`` while training goes on from the trained weights (0 = off, the paper)."""
    anchor: Literal["previous_batch", "batch_start", "lagged"] = "previous_batch"
    """θ*: parameters after the previous batch (paper; = start of this batch) or one batch earlier (lagged)."""
    reg_mode: Literal["prox", "penalty"] = "prox"
    """How EWC/MAS/SI enter the update: a proximal step after each Adam step, or added to the loss."""
    fisher_at: Literal["end", "last_step"] = "end"
    """Where EWC's per-keyframe gradients are taken: at the parameters the batch reached (``end``, the paper's
    Alg. 2; one more forward/backward pass, ~1.1 steps) or from the batch's last step's own passes, one Adam step
    earlier (``last_step``: ~0.4 steps; a different Fisher, README "EWC's Fisher from the last step")."""
    val_scope: Literal["all", "current"] = "all"
    """L_val over all validation keyframes so far, or only the arriving one."""
    val_max: int = setting(0, at_least(0, "0 = every one"))
    """``all``: at most this many validation keyframes, evenly spread from the first to the newest (0 = every one)."""
    validate_every: int = setting(5, at_least(1))
    """m of Algorithm 1."""
    patience: int = setting(3, at_least(1))
    """n of Algorithm 1."""
    tau_val: float = setting(0.2, at_least(0))
    """τ_val of Algorithm 1 (threshold on L_val = L_sparse)."""
    replay_capacity: int = setting(0, Range(lo=3, or_zero=True, unit="0 = all"))
    """Keyframes kept for replay (0 = all, stored at network resolution)."""
    luo_window: int = setting(3, at_least(2, "the target and one candidate"))
    """Scheme ``luo``: the most recent training keyframes (target included) searched for its stereo partners
    (≤ ``luo_window − 1`` sources; 3: Eq. 3's two, a step costs what ``recent``'s does; 4 and 5 found no more
    partners on tum_fr1_xyz, redkitchen_7scenes, icl_lr_kt2). ≥ 2."""
    luo_min_horizontal_ratio: float = setting(0.8, FRACTION)
    """Scheme ``luo``: a keyframe pair is a simulated stereo pair only if |t_x| / ‖t‖ ≥ this, t the
    partner's camera centre in the target camera's frame (x: along the image rows). 0.8 = at most
    36.9° off the x axis, |t_x| ≥ 4/3·‖(t_y, t_z)‖: dominant with a margin over 1/√2 (x holds half of
    ‖t‖²). A zero baseline never qualifies. In [0, 1]."""
    luo_max_rotation_deg: float = setting(5.0, between(0, 180, "degrees"))
    """Scheme ``luo``: … and their relative rotation is ≤ this, degrees (a rectified pair has none; 5°: 27 %, 44 %,
    42 % of the three sequences' keyframes find a partner, 10°: 27 %, 47 %, 83 %). In [0, 180]."""
    comoda_lr: float = setting(1e-4, above(0))
    """Scheme ``comoda`` (CoMoDa-style end-to-end baseline, ``adapt/comoda.py``): Adam learning rate of
    the joint depth + pose update (CoMoDa's / Monodepth2's 1e-4, Adam β = (0.9, 0.999)). > 0."""
    comoda_steps_per_frame: int = setting(1, at_least(1))
    """Scheme ``comoda``: Adam steps per arriving frame (CoMoDa: one update per frame). ≥ 1."""
    comoda_replay_from: Literal["source", "sequence"] = "source"
    """Scheme ``comoda``: what is replayed. ``source``: a fixed bank of triplets of the pre-training
    domain, rendered at the start (CoMoDa replays samples of its KITTI training set; ``comoda_source``);
    ``sequence``: a reservoir of this sequence's own past triplets."""
    comoda_replay_per_step: int = setting(3, at_least(0))
    """Scheme ``comoda``: past triplets drawn uniformly from the replay buffer into each update batch,
    beside the current triplet (batch = 1 + this, as CoMoDa mixes the current sample with replayed
    ones). ≥ 0; 0 = no replay."""
    comoda_replay_capacity: int = setting(200, at_least(1))
    """Scheme ``comoda``: triplets kept for replay: the source-domain bank (rendered once into
    ``<out>/_cache/comoda/``) or a reservoir over the sequence's past; uint8 at network resolution (200 at
    640×192: 221 MB). ≥ 1."""
    comoda_smoothness: float = setting(1e-3, at_least(0))
    """Scheme ``comoda``: weight of the edge-aware smoothness (Monodepth2's 1e-3, which CoMoDa keeps). ≥ 0."""
    comoda_min_motion: float = setting(0.0, at_least(0))
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

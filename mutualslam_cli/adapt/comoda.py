"""``comoda``: a CoMoDa-style end-to-end online adapter that needs no SLAM (a baseline, paper §IV-B).

CoMoDa (Kuznietsov, Proesmans and Van Gool, "CoMoDA: Continuous Monocular Depth Adaptation Using
Past Experiences", WACV 2021) adapts a Monodepth2 depth network *and* its pose network on the test
video itself, one update per arriving frame, on the frame triplet (t−1, t, t+1) mixed with triplets
replayed from the past. The paper compares against it in Table 4 ("learning-based online adaptation")
and attributes part of the gap to the pose network, which was never trained indoors. Here:

- **Loss** (Monodepth2, Godard et al. ICCV 2019, §3.2–3.3, which CoMoDa keeps):
  ``L = mean_p min( min_s pe(I_t, I_{s→t}), min_s pe(I_t, I_s) + ε ) + λ_s · L_smooth``, s ∈ {t−1, t+1}:
  per-pixel **minimum reprojection** (Eq. 4 of Monodepth2) with **auto-masking** — the identity
  reprojection (source not warped) joins the minimum, so a pixel where not moving explains the
  image better (static camera, objects moving with it) contributes its identity error, which has
  no gradient, i.e. is masked out (Eq. 5 of Monodepth2; ``ε`` ~ 1e-5 noise breaks ties, as there).
  ``pe`` is ours (Eq. 4 of the paper, α = 0.85, same as Monodepth2); warps use the *predicted*
  depth and the *pose network's* relative pose (Eq. 5 of the paper). Reprojections falling outside
  the source image do not compete (Monodepth2 lets border-padded values compete). Scale 0 only
  (Monodepth2 and CoMoDa average four scales; one scale keeps the CPU step comparable with ours).
- **Pose network** (:class:`~mutualslam_cli.adapt.networks.pose.PoseNet`): frames in temporal
  order, ``T_{t−1→t}`` inverted for the earlier source as in Monodepth2.
- **Update**: ``comoda_steps_per_frame`` Adam steps (lr ``comoda_lr``) on a batch = the current
  triplet + ``comoda_replay_per_step`` triplets drawn uniformly without replacement from the replay
  set (CoMoDa's batch of 4 = 1 + 3). The replay set (``comoda_replay_from``) is, as in CoMoDa, a
  fixed bank of ``comoda_replay_capacity`` triplets of the *pre-training* domain
  (:mod:`~mutualslam_cli.adapt.comoda_source`: CoMoDa replays KITTI training samples, its "distant
  past"), each with its own intrinsics; or (``sequence``) a reservoir of this sequence's past
  triplets, each stored after its update. Triplets are uint8 at network resolution.
- **BatchNorm** as CoMoDa's code has it (``CoMoDA.set_adapt``): both networks in eval mode, so the
  running statistics stay those of pre-training (batches of ≤ 4), *and* BatchNorm's affine weight
  and bias frozen (``requires_grad = False``, so Adam never sees them; CoMoDa's code freezes them),
  in the depth and the pose network (:func:`freeze_batchnorm`). Gradients still flow through the
  layers; convolutions and decoder biases are trained. CoMoDa selects the frozen parameters by name
  (``"bn"`` in it), which misses the BatchNorm of the ResNet shortcuts (``layerN.0.downsample.1``);
  here every BatchNorm layer is frozen, found by type. Eval mode is re-asserted at each call.
- **Pose network source** (:func:`~mutualslam_cli.adapt.comoda_pose.make_pose_net`):
  ``adapt.comoda_pose_weights``, else the depth weights folder ``net.weights`` when it holds pose files,
  else the default weights folder's, else an encoder copied from the depth encoder with a random
  decoder; ``summary.json`` names it (``adaptation.pose_network``).
- **Not transferred indoors**: CoMoDa's velocity loss (GPS speed gives metric scale; TUM / ICL-NUIM
  have no speed) and its static-frame rule (a translation below 0.2 m by GPS speed; here an
  optional photometric gate, ``comoda_min_motion``, off by default).
- **Lag**: the target t is trained when t+1 arrives, so the update lags one frame.
- **Trajectory**: ``T_wc`` chained from the pose network's ``T_{t→t+1}`` predicted (no grad) when
  frame t+1 arrives, after that frame's update: ``T_wc(t+1) = T_wc(t) · T_{t→t+1}⁻¹``, frame 0 = I.
  Its scale is the depth network's (monocular), so its ATE is Sim(3)-aligned.
- Determinism: ``torch.manual_seed(seed)`` at construction; replay draws and reservoir choices
  come from numpy Generators seeded with ``seed`` and ``seed + 1``; the tie-breaking noise from a
  torch Generator seeded with ``seed + 2`` (drawn on the CPU whatever the device, so it is the same
  noise everywhere).
- Device: both networks and the optimiser live on ``device``; frames, triplets and the replay set stay
  on the CPU as uint8 and each update's batch is sent over; poses come back to the CPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt.depthnet import fast_context, predictor
from mutualslam_cli.adapt.losses import photometric_error, smoothness_loss
from mutualslam_cli.adapt.networks.pose import PoseNet
from mutualslam_cli.adapt.warp import warp
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.config.checks import check_config
from mutualslam_cli.device import grad_scaler, module_device, synchronize
from mutualslam_cli.errors import ShapeError
from mutualslam_cli.types import check_shape

#: Std of the noise added to the identity reprojection error to break ties (Monodepth2: 1e-5).
IDENTITY_NOISE = 1e-5
#: A reprojection outside the source image gets this error, so it never wins the minimum.
INVALID_PE = 1e4
#: The BatchNorm layers :func:`freeze_batchnorm` freezes.
BATCHNORM_TYPES = (nn.BatchNorm1d, nn.BatchNorm2d, nn.BatchNorm3d, nn.SyncBatchNorm)


def freeze_batchnorm(*modules: nn.Module) -> int:
    """CoMoDa's adaptation mode (its ``set_adapt``): each module in eval mode (BatchNorm running
    statistics frozen) and the affine ``weight``/``bias`` of every BatchNorm layer set to
    ``requires_grad = False`` (in place). Returns the number of parameter tensors frozen."""
    n = 0
    for module in modules:
        module.eval()
        for m in module.modules():
            if isinstance(m, BATCHNORM_TYPES):
                for p in m.parameters(recurse=False):
                    p.requires_grad_(False)
                    n += 1
    return n


def se3_inv_torch(T: torch.Tensor) -> torch.Tensor:
    """Differentiable inverse of rigid transforms ``(B, 4, 4)``: ``[Rᵀ | −Rᵀ t]``."""
    R, t = T[:, :3, :3], T[:, :3, 3:4]
    Rt = R.transpose(1, 2)
    top = torch.cat([Rt, -Rt @ t], 2)
    return torch.cat([top, T[:, 3:4]], 1)


def to_uint8(image: torch.Tensor) -> torch.Tensor:
    """``(3, H, W)`` float in [0, 1] (or uint8) → uint8, rounded."""
    if image.dtype == torch.uint8:
        return image.clone()
    return (image.detach().float().clamp(0, 1) * 255.0).round().to(torch.uint8)


def automasked_min_reprojection(target: torch.Tensor, sources: list[torch.Tensor], depth: torch.Tensor,
                                K: torch.Tensor, T_t2s: list[torch.Tensor], alpha: float = 0.85,
                                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Monodepth2's per-pixel minimum reprojection with auto-masking (Godard et al. 2019, Eq. 4–5).

    Args:
        target: ``(B, 3, H, W)`` in [0, 1]. sources: each ``(B, 3, H, W)``. depth: ``(B, 1, H, W)``.
        K: ``(B, 3, 3)`` intrinsics at this resolution. T_t2s: per source ``(B, 4, 4)`` target → source.
        alpha: SSIM/L1 balance of ``pe``.
        generator: for the tie-breaking noise (:data:`IDENTITY_NOISE`).

    Returns:
        ``(loss, mask)``: 0-d mean over all pixels of the per-pixel minimum, and ``(B, 1, H, W)`` bool,
        True where a warped source wins (pixels that train the networks).
    """
    b, n = target.shape[0], len(sources)
    if n == 0 or n != len(T_t2s):
        raise ShapeError(f"automasked_min_reprojection: {n} sources and {len(T_t2s)} poses")
    src = torch.cat(sources, 0)
    warped, valid = warp(src, depth.float().repeat(n, 1, 1, 1), K.float().repeat(n, 1, 1), torch.cat(T_t2s, 0))
    reproj = photometric_error(target, warped, alpha)                               # (n·B, 1, H, W)
    reproj = torch.where(valid, reproj, torch.full_like(reproj, INVALID_PE))
    reproj = torch.cat(reproj.split(b, 0), 1)                                       # (B, n, H, W)
    with torch.no_grad():
        ident = torch.cat(photometric_error(target, src, alpha).split(b, 0), 1)     # (B, n, H, W), no gradient
        noise = torch.randn(ident.shape, generator=generator, dtype=ident.dtype, device="cpu") * IDENTITY_NOISE
        ident = ident + noise.to(ident.device)
    combined = torch.cat([ident, reproj], 1)                                        # Monodepth2 Eq. 5
    best, idx = combined.min(1, keepdim=True)
    return best.mean(), idx >= n


@dataclass
class FrameStep:
    """What one :meth:`ComodaAdapter.add_frame` did.

    Attributes:
        frame: index of the arriving frame. target: index of the trained triplet's middle frame
            (``frame − 1``) or ``None`` before the first full triplet.
        trained: an update ran. static: the motion gate skipped the triplet.
        batch: triplet targets in the batch (current first, then the replayed ones; a replayed
            source-domain triplet ``k`` of the bank is ``-1 - k``).
        loss: ``photo``, ``smooth``, ``total``, ``automask`` (fraction of pixels trained) of the first
            step; empty when not trained.
        step_ms: milliseconds of the update (all steps).
    """

    frame: int
    target: int | None = None
    trained: bool = False
    static: bool = False
    batch: list[int] = field(default_factory=list)
    loss: dict[str, float] = field(default_factory=dict)
    step_ms: float = 0.0


class ComodaAdapter:
    """CoMoDa-style online adaptation of a depth network and a pose network from raw frames.

    Args:
        depth_net: module with ``predict(x (B, 3, H, W) in [0, 1]) -> depth (B, 1, H, W)``.
        pose_net: :class:`PoseNet` (trained jointly).
        cfg: supplies ``alpha`` and the ``comoda_*`` settings (:class:`AdaptConfig`).
        K_net: ``(3, 3)`` intrinsics at network resolution.
        seed: seed of every random choice.
        fast: bf16 autocast around the forward passes (losses stay fp32).
        replay_bank: ``(triplets (N, 3, 3, H, W) uint8, K (3, 3))``: replay only these (CoMoDa's
            replay of the training domain) and store nothing of the sequence; ``None``: replay a
            reservoir of the sequence's own past triplets.
        device: where both networks run (they are moved there); default: the depth network's device.

    Raises:
        ConfigError: a ``comoda_*`` setting out of range.
    """

    def __init__(self, depth_net: nn.Module, pose_net: PoseNet, cfg: AdaptConfig,
                 K_net: torch.Tensor | np.ndarray, seed: int = 0, fast: bool = False,
                 replay_bank: tuple[torch.Tensor, torch.Tensor] | None = None,
                 device: torch.device | str | None = None) -> None:
        check_config(cfg, "adapt")  # every setting in its range (records built in code skip load_config)
        self.device = torch.device(device) if device is not None else module_device(depth_net)
        depth_net.to(self.device)
        pose_net.to(self.device)
        self.K_net = torch.as_tensor(np.asarray(K_net), dtype=torch.float32, device="cpu")
        check_shape(self.K_net, [3, 3], "ComodaAdapter: K_net")
        torch.manual_seed(seed)
        self.n_bn_frozen = freeze_batchnorm(depth_net, pose_net)  # eval mode + BN affine frozen (CoMoDa)
        self.net, self.pose_net = depth_net, pose_net
        self.cfg, self.fast = cfg, bool(fast)
        params = [p for m in (depth_net, pose_net) for p in m.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(params, lr=cfg.comoda_lr, betas=(0.9, 0.999))
        self.scaler = grad_scaler(self.device, self.fast)
        self.rng = np.random.default_rng(seed)
        self.reservoir_rng = np.random.default_rng(seed + 1)
        self.noise = torch.Generator(device="cpu").manual_seed(seed + 2)
        self.window: list[tuple[int, torch.Tensor]] = []   # the last three frames, uint8 (3, H, W)
        self.replay: list[tuple[int, torch.Tensor, torch.Tensor]] = []  # (target, (3, 3, H, W) uint8, K (3, 3))
        self.fixed_bank = replay_bank is not None
        if replay_bank is not None:
            triplets, K_src = replay_bank
            check_shape(triplets, ["N", 3, 3, "H", "W"], "ComodaAdapter: replay_bank triplets")
            K_src = torch.as_tensor(K_src, dtype=torch.float32, device="cpu")
            self.replay = [(-1 - k, triplets[k], K_src) for k in range(triplets.shape[0])]
        self.n_seen_triplets = 0
        self.poses: list[np.ndarray] = []                   # T_wc of every frame so far
        self.history: list[FrameStep] = []
        self.step_ms: list[float] = []

    # ------------------------------------------------------------------ public
    def add_frame(self, image: torch.Tensor) -> FrameStep:
        """Consume the next frame ``(3, H, W)`` (float in [0, 1] or uint8) at network resolution.

        When a triplet (t−1, t, t+1) is complete, one update trains target t; then the pose from t
        to t+1 extends the trajectory.
        """
        check_shape(image, [3, "H", "W"], "ComodaAdapter.add_frame")
        self._eval_mode()
        idx = len(self.poses)
        self.window = (self.window + [(idx, to_uint8(image).cpu())])[-3:]
        info = FrameStep(frame=idx)
        if len(self.window) == 3:
            triplet = torch.stack([img for _, img in self.window])
            info.target = self.window[1][0]
            self.train_triplet(info.target, triplet, info)
        self._extend_trajectory()
        self.history.append(info)
        return info

    def train_triplet(self, target: int, triplet: torch.Tensor, info: FrameStep | None = None) -> FrameStep:
        """One CoMoDa update on ``triplet`` ``(3, 3, H, W)`` uint8 (t−1, t, t+1) + replayed ones, then store it.

        A static triplet (motion gate) is neither trained on nor stored. Returns ``info`` filled in.
        """
        check_shape(triplet, [3, 3, "H", "W"], "ComodaAdapter.train_triplet")
        info = info if info is not None else FrameStep(frame=target + 1, target=target)
        self._eval_mode()
        if self._is_static(triplet):
            info.static = True
            return info
        self._update(target, triplet, info)
        self._store(target, triplet)
        return info

    def trajectory(self) -> np.ndarray:
        """``(N, 4, 4)`` float64 ``T_wc`` of the frames so far, chained from the pose network (frame 0 = I)."""
        return np.stack(self.poses) if self.poses else np.zeros((0, 4, 4))

    def loss_on(self, triplets: torch.Tensor) -> dict[str, float]:
        """The loss parts of the current networks on ``(B, 3, 3, H, W)`` uint8 triplets of this
        sequence's camera, without training."""
        self._eval_mode()
        with torch.no_grad():
            _, parts = self._loss(triplets.to(self.device), self.K_net.expand(triplets.shape[0], 3, 3).to(self.device))
        return parts

    # ------------------------------------------------------------------ internals
    def _eval_mode(self) -> None:
        """Both networks back in eval mode (BatchNorm statistics frozen) even if a caller set ``train()``."""
        self.net.eval()
        self.pose_net.eval()

    def _is_static(self, triplet: torch.Tensor) -> bool:
        if self.cfg.comoda_min_motion <= 0:
            return False
        f = triplet.float() / 255.0
        change = min(float((f[1] - f[0]).abs().mean()), float((f[1] - f[2]).abs().mean()))
        return change < self.cfg.comoda_min_motion

    def _loss(self, triplets: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """Eq. 4–5 of Monodepth2 + λ_s·L_smooth on ``(B, 3, 3, H, W)`` uint8 triplets (t−1, t, t+1)
        with their ``(B, 3, 3)`` intrinsics, both on the adapter's device."""
        f = triplets.float() / 255.0
        prev, tgt, nxt = f[:, 0], f[:, 1], f[:, 2]
        with fast_context(self.fast, self.device):
            depth = predictor(self.net)(tgt)
            T_prev2t = self.pose_net(prev, tgt)        # T_{t−1→t}
            T_t2next = self.pose_net(tgt, nxt)         # T_{t→t+1}
        photo, mask = automasked_min_reprojection(tgt, [prev, nxt], depth, K,
                                                  [se3_inv_torch(T_prev2t.float()), T_t2next.float()],
                                                  self.cfg.alpha, self.noise)
        smooth = smoothness_loss(depth, tgt)
        total = photo + self.cfg.comoda_smoothness * smooth
        values = torch.stack([photo, smooth, total, mask.float().mean()]).detach().tolist()  # one copy to the host
        parts = dict(zip(("photo", "smooth", "total", "automask"), values))
        return total, parts

    def _update(self, target: int, triplet: torch.Tensor, info: FrameStep) -> None:
        k = min(self.cfg.comoda_replay_per_step, len(self.replay))
        picks = sorted(self.rng.choice(len(self.replay), size=k, replace=False).tolist()) if k else []
        batch = torch.stack([triplet] + [self.replay[i][1] for i in picks]).to(self.device)  # uint8 over
        K = torch.stack([self.K_net] + [self.replay[i][2] for i in picks]).to(self.device)
        info.batch = [target] + [self.replay[i][0] for i in picks]
        t0 = time.perf_counter()
        for s in range(self.cfg.comoda_steps_per_frame):
            self.optimizer.zero_grad(set_to_none=True)
            loss, parts = self._loss(batch, K)
            if self.scaler is None:
                loss.backward()
                self.optimizer.step()
            else:  # fp16: scaled loss, a step with an inf/NaN gradient skipped
                self.scaler.scale(loss).backward()
                self.scaler.step(self.optimizer)
                self.scaler.update()
            if s == 0:
                info.loss = parts
        synchronize(self.device)
        info.step_ms = 1000.0 * (time.perf_counter() - t0)
        self.step_ms.append(info.step_ms)
        info.trained = True

    def _store(self, target: int, triplet: torch.Tensor) -> None:
        """Reservoir sampling (Vitter's algorithm R): every past triplet stays with equal probability.
        Nothing is stored when the replay set is a fixed bank."""
        if self.fixed_bank:
            return
        self.n_seen_triplets += 1
        if len(self.replay) < self.cfg.comoda_replay_capacity:
            self.replay.append((target, triplet.cpu(), self.K_net))
            return
        j = int(self.reservoir_rng.integers(self.n_seen_triplets))
        if j < self.cfg.comoda_replay_capacity:
            self.replay[j] = (target, triplet.cpu(), self.K_net)

    def _extend_trajectory(self) -> None:
        if not self.poses:
            self.poses.append(np.eye(4))
            return
        a, b = (img.to(self.device).float()[None] / 255.0 for _, img in self.window[-2:])
        with torch.no_grad(), fast_context(self.fast, self.device):
            T = self.pose_net(a, b)[0].double().cpu().numpy()  # T_{t→t+1}
        self.poses.append(self.poses[-1] @ np.linalg.inv(T))

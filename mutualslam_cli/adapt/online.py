"""The online adaptation loop: Algorithm 1 (state machine) driving Algorithm 2 (fine-tuning).

One call of :meth:`OnlineAdapter.add_keyframe` = one tick of Algorithm 1 (see
:mod:`mutualslam_cli.adapt.state`): a validation keyframe (every m-th) is stored and L_val is
computed; any other keyframe is stored and the network is fine-tuned right away on the batch
the scheme selects (newest keyframe first, e.g. + one replayed older keyframe).

Choices the paper leaves open (documented here, DESIGN §5):

- **Newest keyframe's photometric sources.** s ∈ {i−1, i+1} (Eq. 3), but K_{i+1} does not exist yet when
  K_i arrives: K_i trains at once with s = i−1 only, and with both when replayed; the first training keyframe
  is not trained on (``luo``: simulated stereo partners, :meth:`Scheme.sources`). A batch item with fewer
  sources repeats one of them, so the batch stays one forward pass.
- **L_val** (Eq. 9) = L_sparse over all validation keyframes so far (``val_scope="all"``; ``"current"``: the
  arriving one), with the current model, each weighing equally: the growing held-out set early stopping
  monitors, so forgetting of earlier places raises it (docs/adaptation.md).
- **BatchNorm** stays in eval mode (running statistics frozen): batches have 1–2 images; gradients flow through it.
- **Loss parts** in :class:`StepInfo` are the batch's first step's; ``penalty`` the regulariser's value at its end.
- **Regulariser** (``ewc``, ``replay+ewc|mas|si``): a proximal step after each Adam step (``reg_mode="prox"``) or a
  loss term (``"penalty"``, the paper's form): :mod:`mutualslam_cli.adapt.regularizers`.
- Determinism: ``torch.manual_seed(seed)`` at construction, replay draws from a numpy Generator
  seeded with ``seed`` and buffer eviction from one seeded with ``seed + 1``.
- Device (:mod:`~mutualslam_cli.device`): network, optimiser and regulariser tensors on ``device``; images stay on the
  CPU until a batch is assembled. fp16 (GPUs without bf16) scales the loss; EWC's Fisher gradients are unscaled.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Mapping
from typing import Literal, cast

import numpy as np
import torch
from torch import nn

from mutualslam_cli.adapt import losses
from mutualslam_cli.adapt.batch import TrainingBatch, make_batch, resample_batch
from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample, LabelSource
from mutualslam_cli.adapt.depthnet import DepthNet, fast_context, freeze_encoder_stages, make_adam, predictor
from mutualslam_cli.adapt.health import HealthMonitor
from mutualslam_cli.adapt.keyframe_grads import KeyframeGrads
from mutualslam_cli.adapt.regularizers import Regularizer, trainable
from mutualslam_cli.adapt.schemes import get_scheme
from mutualslam_cli.adapt.stabilise import ScaleAlignment, TrustRegion, WeightAverage, param_groups
from mutualslam_cli.adapt.state import (
    Action,
    FineTuneDone,
    FsmParams,
    FsmState,
    TrainingKeyframe,
    ValidationKeyframe,
    is_validation_index,
    step,
)
from mutualslam_cli.adapt.step_info import StepInfo, StepLog  # StepInfo: what add_keyframe returns
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.device import grad_scaler, module_device, synchronize
from mutualslam_cli.errors import ConfigError, TransitionError
from mutualslam_cli.types import check_shape

log = logging.getLogger(__name__)

LossFn = Callable[..., tuple[torch.Tensor, dict[str, float]]]
ValFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


class OnlineAdapter:
    """Online fine-tuning of a depth network from VO keyframes (paper Alg. 1 + Alg. 2).

    Args:
        net: module with ``predict(x (B, 3, H, W) in [0, 1]) -> depth (B, 1, H, W)``, differentiable.
        cfg: adaptation settings (scheme, lr, λ1, λ2, α, regulariser constants, m, n, τ_val, …).
        K_net: ``(3, 3)`` intrinsics at network resolution (default K of the samples).
        seed: seed of every random choice of the loop.
        fast: bf16 autocast around the forward pass (losses stay fp32).
        on_global_ba: called with the :class:`StepInfo` when Alg. 1 sets ``run_global_ba``;
            it may call :meth:`per_keyframe_val_loss`, :meth:`update_poses`, :meth:`update_sparse`.
        loss_fn: L_train with the signature of :func:`mutualslam_cli.adapt.losses.train_loss`
            (default: that function).
        val_fn: L_sparse with the signature of :func:`mutualslam_cli.adapt.losses.sparse_depth_loss`.
        val_scope: ``"all"`` validation keyframes so far (default) or ``"current"`` only.
        reg_mode: ``"prox"`` (default) or ``"penalty"``, how the regulariser enters the update.
        labels: where stored keyframes' poses and sparse depths are read when used (the map as it stands
            then, DESIGN §5); ``None``: the values each sample arrived with.
        device: where the network is trained (it is moved there); default: where its parameters are.

    Raises:
        ConfigError: unknown scheme, bad capacity, anchor, ``val_scope`` or FSM constants.
    """

    def __init__(self, net: nn.Module, cfg: AdaptConfig, K_net: torch.Tensor | np.ndarray, seed: int = 0,
                 fast: bool = False, on_global_ba: Callable[[StepInfo], None] | None = None, *,
                 loss_fn: LossFn | None = None, val_fn: ValFn | None = None,
                 val_scope: Literal["all", "current"] = "all", reg_mode: Literal["prox", "penalty"] = "prox",
                 labels: LabelSource | None = None, device: torch.device | str | None = None) -> None:
        if loss_fn is None or val_fn is None:
            loss_fn = loss_fn or losses.train_loss
            val_fn = val_fn or losses.sparse_depth_loss
        if val_scope not in ("all", "current"):
            raise ConfigError(f"adapt.val_scope = {val_scope!r}: expected 'all' or 'current'")
        self.device = torch.device(device) if device is not None else module_device(net)
        self.K_net = torch.as_tensor(np.asarray(K_net), dtype=torch.float32, device="cpu")
        check_shape(self.K_net, [3, 3], "OnlineAdapter: K_net")
        torch.manual_seed(seed)
        self.net = net.to(self.device).eval()
        self.cfg = cfg
        self.fast = bool(fast)
        self.on_global_ba = on_global_ba
        self.loss_fn, self.val_fn, self.val_scope = loss_fn, val_fn, val_scope
        self.scheme = get_scheme(cfg.scheme, cfg)
        self.buffer = KeyframeBuffer(cfg.replay_capacity, seed=seed + 1, labels=labels)
        self._pending: tuple[StepInfo, TrainingBatch, float] | None = None  # a batch waiting for its steps
        self._opened: tuple[float, int] | None = None  # step_pending: the pending batch's start and steps so far
        self.rng = np.random.default_rng(seed)
        if cfg.freeze_stages:
            freeze_encoder_stages(cast(DepthNet, net), cfg.freeze_stages)  # stages to freeze: a DepthNet's
        self.params = trainable(net)
        self.optimizer = make_adam(param_groups(net, self.params, cfg.lr, cfg.encoder_lr), lr=cfg.lr) \
            if self.scheme.trains else None
        # adapt/stabilise.py: the step's trust region and the predicting weight average (off in the paper)
        self.trust = TrustRegion(self.params, cfg.trust) if cfg.trust > 0 and self.scheme.trains else None
        self.average = WeightAverage(self.params, cfg.average) if cfg.average > 0 and self.scheme.trains else None
        self.health = HealthMonitor(net) if self.scheme.trains else None
        self.scale = ScaleAlignment(cfg.scale)  # the map's units for the losses (adapt.scale)
        self.scaler = grad_scaler(self.device, self.fast)  # fp16 autocast only (a GPU without bf16)
        self.kf_grads = KeyframeGrads(net, self.params, self._predict, self._one_loss,  # for EWC's Fisher
                                      from_last_step=cfg.fisher_at == "last_step")
        self.regularizer: Regularizer | None = self.scheme.make_regularizer(net, cfg, self._predict, reg_mode)
        self.fsm_params = FsmParams(cfg.validate_every, cfg.patience, cfg.tau_val)
        self.fsm = FsmState()
        self.finetune_ms: list[float] = []
        self.step_ms: list[float] = []
        self.step_log = StepLog()  # every step's time beside the work around it (steps.csv)
        self.batch_ms: list[float] = []  # per trained keyframe: assembling the batch (replay decode, resampling)
        self.consolidate_ms: list[float] = []  # … and the regulariser's end of batch (Fisher, importance)
        self.history: list[StepInfo] = []

    # ------------------------------------------------------------------ public
    def add_keyframe(self, sample: KeyframeSample, steps: int | None = None) -> StepInfo:
        """Consume one keyframe: one tick of Algorithm 1, its fine-tuning included (:meth:`begin_keyframe`
        then :meth:`train_pending`).

        Args:
            sample: the keyframe at network resolution (see :class:`KeyframeSample`).
            steps: optimiser steps for it when trained on (default ``cfg.steps_per_keyframe``; 0: none).

        Returns:
            What happened (:class:`StepInfo`).

        Raises:
            ShapeError: malformed sample.
        """
        info = self.begin_keyframe(sample)
        self.train_pending(self.cfg.steps_per_keyframe if steps is None else steps)
        return info

    def begin_keyframe(self, sample: KeyframeSample) -> StepInfo:
        """One tick of Algorithm 1 up to the optimiser steps: a validation keyframe (every m-th) is stored
        and L_val computed (the FSM may request global BA: ``info.run_global_ba``); another is stored and,
        when the scheme trains, its batch assembled now — its labels are the map's now — and kept for
        :meth:`train_pending`, which must come before the next keyframe."""
        if self._pending is not None:
            raise TransitionError("train_pending() the previous keyframe's batch before the next keyframe")
        t0 = time.perf_counter()
        t = self.fsm.t
        info = StepInfo(kf_id=sample.kf_id, t=t, state=self.fsm.mode.value, is_validation=False, trained=False)
        if is_validation_index(t, self.fsm_params.m):  # Alg. 1: t > 0 and t % m == 0
            self.buffer.add(sample, training=False)
            info.is_validation = True
            info.l_val = self._l_val(sample.kf_id)
            self.fsm, actions = step(self.fsm, ValidationKeyframe(info.l_val), self.fsm_params)
            info.run_global_ba = Action.RUN_GLOBAL_BA in actions
        else:
            self.buffer.add(sample, training=True)
            self.fsm, actions = step(self.fsm, TrainingKeyframe(), self.fsm_params)
            t_batch = time.perf_counter()
            batch = self._begin_fine_tune(sample.kf_id, info) if Action.FINE_TUNE in actions else None
            if batch is not None:
                self._pending = (info, batch, 1000.0 * (time.perf_counter() - t_batch))
            self.fsm, _ = step(self.fsm, FineTuneDone(), self.fsm_params)
        self.step_log.mark("l_val" if info.is_validation else "tick")
        info.state = self.fsm.mode.value
        info.n_converged = self.fsm.n_converged
        info.ms = 1000.0 * (time.perf_counter() - t0)
        self.history.append(info)
        log.debug("kf %d t=%d val=%s l_val=%s n_conv=%d ba=%s", info.kf_id, t, info.is_validation, info.l_val,
                  info.n_converged, info.run_global_ba)
        if info.run_global_ba and self.on_global_ba is not None:
            self.on_global_ba(info)
        return info

    @property
    def pending(self) -> StepInfo | None:
        """The keyframe whose batch waits for :meth:`train_pending` (``None``: none)."""
        return None if self._pending is None else self._pending[0]

    def train_pending(self, steps: int) -> StepInfo | None:
        """Alg. 2 on the batch :meth:`begin_keyframe` assembled: ``steps`` Adam steps (+ regulariser), then
        the regulariser's consolidation; returns the keyframe's (updated) :class:`StepInfo`, ``None`` when
        no batch waits."""
        for _ in range(steps):
            self.step_pending()
        return self.end_pending()

    def step_pending(self) -> bool:
        """One optimiser step on the pending batch (the realtime clock takes them one at a time, as its time
        allows; :meth:`end_pending` consolidates); ``False`` when no batch waits."""
        if self._pending is None:
            return False
        info, batch, batch_ms = self._pending
        t = time.perf_counter()
        if self._opened is None:
            self._opened = (self._open_batch(batch_ms), 0)
        self._step(batch, info, first=self._opened[1] == 0)
        self._opened = (self._opened[0], self._opened[1] + 1)
        info.ms += 1000.0 * (time.perf_counter() - t)
        return True

    def end_pending(self) -> StepInfo | None:
        """The pending batch's end after :meth:`step_pending`: consolidation when it took a step; ``None`` when
        no batch waits."""
        if self._pending is None:
            return None
        info, batch, batch_ms = self._pending
        self._pending = None
        if self._opened is not None:
            t = time.perf_counter()
            self._close_batch(batch, info, self._opened[1], self._opened[0], batch_ms)
            info.ms += 1000.0 * (time.perf_counter() - t)
            self.step_log.mark("consolidate")
        self._opened = None
        return info

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """Feed BA-refined ``T_wc`` back into training (paper §III-A); returns how many were known."""
        return self.buffer.update_poses(poses)

    def update_sparse(self, points: Mapping[int, tuple[torch.Tensor, torch.Tensor]]) -> int:
        """Feed BA-refined sparse points ``{kf_id: (uv (M, 2), depth (M,))}`` back; returns how many were known."""
        return self.buffer.update_sparse(points)

    @torch.no_grad()
    def per_keyframe_val_loss(self, ids: list[int] | None = None, chunk: int = 4) -> dict[int, float]:
        """L_val (Eq. 9, = L_sparse) of stored keyframes with the current model.

        Args:
            ids: keyframe ids (default: every stored keyframe, training and validation).
            chunk: images per forward pass.

        Returns:
            ``{kf_id: L_val}``; NaN for a keyframe without sparse points. Keyframes whose image
            was evicted (``replay_capacity > 0``) are absent.
        """
        ids = [k for k in (self.buffer.all_ids if ids is None else ids) if k in self.buffer]
        out: dict[int, float] = {}
        dev = self.device
        for i in range(0, len(ids), chunk):
            samples = [self.buffer.get(k, dev) for k in ids[i:i + chunk]]
            depth = self._predict(torch.stack([s.image for s in samples]))
            vals = []
            for b, s in enumerate(samples):
                if s.uv.shape[0] == 0:
                    vals.append(torch.full((), float("nan"), dtype=torch.float64, device=dev))
                    continue
                mask = torch.ones(1, s.uv.shape[0], dtype=torch.bool, device=dev)
                one = self.scale.apply(depth[b:b + 1], s.uv[None].to(dev), s.depth[None].to(dev), mask)
                vals.append(self.val_fn(one, s.uv[None].to(dev), s.depth[None].to(dev), mask).double())
            out.update(zip((s.kf_id for s in samples), torch.stack(vals).tolist()))  # one copy back per chunk
        return out

    # ------------------------------------------------------------------ internals
    def _predict(self, x: torch.Tensor) -> torch.Tensor:
        """Forward pass of ``x`` (on :attr:`device`), mixed precision when ``fast``; float32 depth ``(B, 1, H, W)``."""
        with fast_context(self.fast, self.device):
            return predictor(self.net)(x).float()

    def _l_val(self, kf_id: int) -> float:
        """Alg. 1's L_val: mean per-keyframe L_sparse over the validation set (see module docstring)."""
        ids = self.buffer.validation_ids if self.val_scope == "all" else [kf_id]
        if self.cfg.val_max and len(ids) > self.cfg.val_max:  # evenly spread, first and newest included
            ids = [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, self.cfg.val_max).round().astype(int))]
        vals = [v for v in self.per_keyframe_val_loss(ids).values() if not math.isnan(v)]
        return float(np.mean(vals)) if vals else float("nan")

    def _make_batch(self, ids: list[int]) -> TrainingBatch | None:
        """The batch of ``ids`` on :attr:`device` (:func:`~mutualslam_cli.adapt.batch.make_batch`), at training size."""
        batch = make_batch(self.buffer, self.scheme, ids, self.device)
        cfg = self.cfg
        return None if batch is None else resample_batch(batch, cfg.train_width, cfg.train_height)

    def _one_loss(self, batch: TrainingBatch, depth: torch.Tensor, b: int) -> torch.Tensor:
        """Keyframe ``b``'s own L_train from its depth ``(1, 1, H, W)`` and its slice of ``batch``."""
        cfg, one = self.cfg, slice(b, b + 1)
        depth = self.scale.apply(depth, batch.uv[one], batch.d[one], batch.mask[one])
        loss, _ = self.loss_fn(depth, batch.target[one], [s[one] for s in batch.sources], batch.K[one],
                               [t[one] for t in batch.T_t2s], batch.uv[one], batch.d[one],
                               batch.mask[one], cfg.lambda_sparse, cfg.lambda_smooth, cfg.alpha)
        return loss

    def _begin_fine_tune(self, kf_id: int, info: StepInfo) -> TrainingBatch | None:
        """Keyframe ``kf_id``'s batch (the scheme's selection, labels as they stand now); ``None``: nothing to train."""
        if not self.scheme.trains or self.optimizer is None:
            return None
        info.sources = self.scheme.sources(self.buffer, kf_id)
        return self._make_batch(self.scheme.select(self.buffer, kf_id, self.rng))

    def _open_batch(self, batch_ms: float) -> float:
        """Before a batch's first step: θ* for the regulariser (Alg. 2 line 4: θ_cpy = θ); returns its start."""
        self.batch_ms.append(batch_ms)
        t0 = time.perf_counter()
        if self.average is not None:
            self.average.to_trained()  # train on from the optimiser's own weights, not the average
        if self.regularizer is not None:
            self.regularizer.before_batch(self.net)
        return t0

    def _step(self, batch: TrainingBatch, info: StepInfo, first: bool) -> None:
        """One Adam step on the batch's L_train, the regulariser's proximal step or penalty with it."""
        reg, cfg, scaler, opt = self.regularizer, self.cfg, self.scaler, self.optimizer
        assert opt is not None  # _begin_fine_tune gives no batch to a scheme without one
        ts = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        capture = self.kf_grads.step_capture() if self.regularizer is not None and \
            self.regularizer.needs_sample_grads else None
        with capture.recording() if capture is not None else contextlib.nullcontext():
            depth = self._predict(batch.target)
        if first and self.health is not None:  # the first step sees the weights the keyframe arrived with
            info.health = self.health.of_prediction(depth[:1], batch.uv[:1], batch.d[:1], batch.mask[:1])
        depth = self.scale.apply(depth, batch.uv, batch.d, batch.mask, first)
        loss, parts = self.loss_fn(depth, batch.target, batch.sources, batch.K, batch.T_t2s,
                                   batch.uv, batch.d, batch.mask, cfg.lambda_sparse,
                                   cfg.lambda_smooth, cfg.alpha)
        if scaler is None:
            loss.backward()
        else:  # fp16: scaled backward, then the true gradients in .grad for the regulariser and Adam
            scaler.scale(loss).backward()
        if capture is not None:
            capture.after_backward(self.params, None if scaler is None else float(scaler.get_scale()))
        if scaler is not None:
            scaler.unscale_(opt)
        penalty = reg is not None and reg.mode == "penalty"
        # ∇L_train for the regulariser's importance; a copy only when the penalty's backward adds to .grad
        grads = [] if reg is None else [(p.grad.detach().clone() if penalty else p.grad.detach())
                                        if p.grad is not None else torch.zeros_like(p) for p in self.params]
        if first and self.health is not None:
            info.health.update(self.health.of_gradients())
        if penalty and reg is not None:
            pen = reg.penalty(self.net)  # Eq. 1 / Eq. 19 regulariser at the current θ
            if pen.requires_grad:
                pen.backward()  # coupled: ∇(L_train + penalty) through Adam
        stepped = True
        if self.trust is not None:
            self.trust.before()
        if scaler is None:
            opt.step()
        else:  # a step with an inf/NaN gradient is skipped (and the scale lowered): so is its prox
            scale = scaler.get_scale()
            scaler.step(opt)
            scaler.update()
            stepped = scaler.get_scale() >= scale
        if self.trust is not None:
            self.trust.after()
        if capture is not None and not stepped:
            capture.clear()  # an inf/NaN gradient: no Fisher from it
        if reg is not None and stepped:
            if reg.mode == "prox":
                reg.prox(self.net, opt)  # decoupled: proximal step of the penalty in Adam's metric
            reg.after_step(self.net, grads)
        if first:
            info.loss = {k: float(v) for k, v in parts.items()}
        synchronize(self.device)  # CUDA runs ahead of the host: the step is over when the device is done
        self.step_ms.append(1000.0 * (time.perf_counter() - ts))
        self.step_log.step(info.kf_id, self.step_ms[-1], len(batch.ids))

    def _close_batch(self, batch: TrainingBatch, info: StepInfo, steps: int, t0: float, batch_ms: float) -> None:
        """After a batch's last step: the regulariser's consolidation (Alg. 2 line 7) and the keyframe's record."""
        reg, pen_val = self.regularizer, 0.0
        tc = time.perf_counter()
        if reg is not None:
            with torch.no_grad():
                pen_val = float(reg.penalty(self.net))  # distance from θ* left at the end of the batch
            scale = None if self.scaler is None else float(self.scaler.get_scale())
            per_kf = self.kf_grads.of_batch(batch, steps, scale) if reg.needs_sample_grads else None
            reg.after_batch(self.net, batch.target[:1], per_kf)  # consolidate (Alg. 2 line 7)
        if self.health is not None:
            info.health.update(self.health.of_weights())
        self.scale.end_batch(self.net)  # the network's depth in the map's units of its newest keyframe
        if self.average is not None:
            self.average.to_average()  # the averaged weights predict until the next batch
        synchronize(self.device)
        self.consolidate_ms.append(1000.0 * (time.perf_counter() - tc))
        info.loss["penalty"] = pen_val
        info.trained = True
        info.steps = steps
        info.batch = list(batch.ids)
        self.finetune_ms.append(1000.0 * (time.perf_counter() - t0) + batch_ms)

"""Parameter-importance regularisers for online adaptation: EWC, MAS, SI (paper Eq. 1–2, 19–21).

All three add ``c · Σ_i w_i (θ_i − θ*_i)²`` to L_train and differ in the importance ``w``:

- **EWC** (Kirkpatrick et al. 2017; paper Eq. 1–2, Alg. 2): ``c = β/2``, ``w = F̂``; ``F`` sums the
  empirical Fisher of each batch, ``j`` counts batches, ``F̂ = min(F / j, max_F)``. The batch's
  empirical Fisher is taken where the paper takes it, "at the end of every training batch": the
  mean over the batch's keyframes of the *per-keyframe* squared gradient of L_train at the
  parameters the batch reached, ``F^(j) = 1/N Σ_k (∂L_k/∂θ)²`` (Kirkpatrick et al.'s empirical
  Fisher: per-sample gradients at the consolidated parameters). Squared gradients of the
  batch-*mean* loss, or of the steps on the way, measure the misfit of the keyframe being learnt,
  not curvature: at a minimum of the mean loss they vanish while the per-sample ones do not
  (``tests/adapt/test_regularizers.py``). Cost: one forward/backward pass per batch keyframe per
  batch. The paper prints ``max`` but calls max_F "the maximum value of F̂"; a literal max with
  β = 5e7 freezes the net (DESIGN §5).
- **MAS** (Aljundi et al. 2018; Appendix B Eq. 19–20): ``c = λ``, ``w = Ω`` = mean over samples of
  ``|∂ mean(G(x)²) / ∂θ|``. G is the *inverse* depth map: the CNN's own output is a disparity
  (depth is an affine-in-inverse post-processing, Monodepth2 ``disp_to_depth``); with G = depth
  the importance scales with depth³ and far pixels dominate it (measured: Ω up to 1e4 on a 2 m
  plane, and replay+mas diverged). The squared L2 norm is divided by the number of pixels so λ
  does not depend on the image size. One sample per batch: the batch's *newest*
  keyframe, evaluated at the end of the batch (MAS computes Ω at the consolidated parameters);
  replayed keyframes are not counted twice.
- **SI** (Zenke et al. 2017; Appendix B Eq. 19, 21): ``c = λ``; per step ``ω −= g · Δθ`` (g = gradient
  of L_train, the path integral), at the end of a batch ``Ω += max(ω, 0) / ((Δθ_batch)² + ξ)`` and
  ``ω = 0``. Negative contributions (steps that raised the loss) are clipped to 0 so the penalty
  stays a convex quadratic.

**Anchor θ\\* and why the penalty acts.** The paper defines θ* as the parameters after the previous
batch. With one optimiser step per keyframe that step is taken *at* θ = θ*, where the penalty and
its gradient are exactly zero: added to the loss, the regulariser would never change anything.
Two independent choices make it act; both are options, the defaults are marked:

*How the penalty enters the update* (``mode``):

- ``"prox"`` (**default**): Adam steps on L_train only, then the proximal step of the penalty
  **in Adam's own metric**. Adam moves each parameter by ``P·m̂`` with the per-parameter step
  ``P = lr / (√v̂ + ε)`` (``v̂`` = bias-corrected second moment), i.e. it is gradient descent
  preconditioned by ``diag(P)``. The matching proximal step is
  ``θ ← argmin_θ c w (θ − θ*)² + (θ − x)² / (2P) = θ* + (x − θ*) / (1 + 2·P·c·w)``.
  Fixed points: with ``x = θ − P·g`` (at a fixed point Adam's momentum ``m̂`` equals the
  gradient ``g`` of L_train), ``(θ − θ*)(1 + 2Pcw) = θ − θ* − P g`` ⇔ ``g + 2cw(θ − θ*) = 0``:
  exactly the stationarity condition of L_train + the penalty (Eq. 1 / Eq. 19), whatever ``P``
  is. Using the scalar ``lr`` instead of ``P`` (plain forward–backward splitting, correct only
  for SGD) makes the equilibrium ``lr·sign(g) = 2·lr·c·w·(θ − θ*)``, an offset of
  ``1/(2cw)`` independent of the data term: on a 1-D quadratic with ``cw = 10`` it settled at
  0.050 for curvatures 1e-3, 1 and 100 where the minimisers are 5e-5, 0.048 and 0.83
  (``tests/adapt/test_regularizers.py::test_prox_minimises_the_penalised_quadratic``). The step acts on
  *every* step (also the first, also with ``steps_per_keyframe = 1``) and only shrinks
  ``θ − θ*``, never pushes past θ*. Coupled into Adam instead, a quadratic this stiff (β·F̂ up
  to 5e4) is normalised by √v̂ and stored in Adam's momentum, which keeps moving θ on the next
  batch's first step; AdamW decouples weight decay for the same reason (Loshchilov & Hutter 2019).
- ``"penalty"``: the paper's literal form, ``L_train + c Σ w (θ − θ*)²`` back-propagated through
  Adam; it acts only from the second step of a batch (``steps_per_keyframe ≥ 2``).

*Where θ* sits* (``anchor``):

- ``"previous_batch"`` (**default**, paper): θ* = parameters after the previous batch, the latest
  posterior mode, which is what the Laplace argument of Appendix A requires (θ*_T1 = parameters
  that have absorbed all past data). ``"batch_start"`` (AdaptConfig) is the same point: nothing
  changes θ between the end of one batch and the start of the next.
- ``"lagged"``: θ* = parameters at the start of the *previous* batch, so even a single coupled
  step sees θ − θ* = last batch's update. It centres the quadratic on a point that has not seen
  the previous batch and, with Adam's sign-like steps, acts as negative momentum. For comparison.

Hook order per batch, as called by :class:`~mutualslam_cli.adapt.online.OnlineAdapter`::

    reg.before_batch(model)
    for each step: loss = L_train (+ reg.penalty(model) if mode == "penalty"); backward; Adam step;
                   reg.prox(model, optimizer) if mode == "prox"; reg.after_step(model, grads_of_L_train)
    reg.after_batch(model, newest_images, sample_grads)   # sample_grads only if reg.needs_sample_grads

**Strength.** The three importances differ by orders of magnitude for the same coefficient, so
each run measures what its regulariser does: after every proximal step the *shrink*
``1 − ‖θ − θ*‖₂ / ‖x − θ*‖₂`` — the share of the batch's Adam displacement the regulariser took
back (0: inert, 1: frozen) — kept in :attr:`Regularizer.shrinks` and summarised as
``adaptation.reg.shrink.{mean,median}`` in ``summary.json``. The default coefficients are set so
the three regularisers shrink alike (README, "Regulariser strength"; ``mslam bench strength``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from torch import nn

from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.errors import ConfigError

Anchor = Literal["previous_batch", "batch_start", "lagged"]
ANCHORS = ("previous_batch", "batch_start", "lagged")
MODES = ("prox", "penalty")


def trainable(model: nn.Module) -> list[torch.Tensor]:
    """Parameters with ``requires_grad``, in ``model.parameters()`` order."""
    return [p for p in model.parameters() if p.requires_grad]


class Regularizer:
    """Common base: importance ``weights`` and anchor ``θ*``; penalty ``c Σ w (θ − θ*)²``.

    Args:
        model: the network (its trainable parameters are regularised).
        coef: ``c`` (β/2 for EWC, λ for MAS and SI).
        anchor: ``previous_batch`` | ``batch_start`` | ``lagged`` (module docstring).
        mode: ``prox`` | ``penalty`` (module docstring).
    """

    name = "base"
    #: ``after_batch`` wants the per-keyframe gradients of L_train at the parameters reached (EWC).
    needs_sample_grads = False

    def __init__(self, model: nn.Module, coef: float, anchor: str = "previous_batch", mode: str = "prox") -> None:
        if anchor not in ANCHORS:
            raise ConfigError(f"adapt.anchor: {anchor!r} is not one of {list(ANCHORS)}")
        if mode not in MODES:
            raise ConfigError(f"regulariser mode: {mode!r} is not one of {list(MODES)}")
        self.coef = float(coef)
        self.anchor = anchor
        self.mode = mode
        params = trainable(model)
        self.star = [p.detach().clone() for p in params]  # θ*
        self.weights = [torch.zeros_like(p) for p in params]  # importance w (F̂ or Ω)
        # θ at the start of the previous batch (kept only for the lagged anchor)
        self._prev_start = [t.clone() for t in self.star] if anchor == "lagged" else None
        self.batches = 0
        self.shrinks: list[float] = []  # per proximal step: 1 − ‖θ − θ*‖ / ‖x − θ*‖ (module docstring)

    def before_batch(self, model: nn.Module) -> None:
        """Set θ* for the coming batch (module docstring: anchor policy)."""
        now = [p.detach().clone() for p in trainable(model)]
        if self._prev_start is not None:
            self.star, self._prev_start = self._prev_start, now  # θ at the start of the previous batch
        else:
            self.star = now  # θ after the previous batch = at the start of this one (paper)

    def penalty(self, model: nn.Module) -> torch.Tensor:
        """``c Σ_i w_i (θ_i − θ*_i)²`` (Eq. 1 for EWC with c = β/2, Eq. 19 for MAS/SI); scalar, differentiable."""
        params = trainable(model)
        total = params[0].new_zeros(()) if params else torch.zeros((), device="cpu")
        for p, w, s in zip(params, self.weights, self.star):
            total = total + (w * (p - s) ** 2).sum()
        return self.coef * total

    @torch.no_grad()
    def prox(self, model: nn.Module, optimizer: torch.optim.Optimizer) -> None:
        """Proximal step of the penalty in Adam's metric, after ``optimizer.step()`` (module docstring).

        ``θ ← θ* + (x − θ*) / (1 + 2·P·c·w)`` with ``P = lr / (√v̂ + ε)`` per parameter, read from the
        optimiser's state (``v̂ = exp_avg_sq / (1 − β2^t)``, as ``torch.optim.Adam`` computes it).
        A parameter Adam has not stepped yet (no state) is left as it is.

        Raises:
            ConfigError: the optimiser is not Adam/AdamW (or uses amsgrad), so ``P`` is unknown.
        """
        groups = {id(q): g for g in optimizer.param_groups for q in g["params"]}
        before = after = 0.0
        for p, w, s in zip(trainable(model), self.weights, self.star):
            g = groups.get(id(p))
            if g is None or g.get("amsgrad", False) or "betas" not in g:
                raise ConfigError("the proximal regulariser needs Adam (without amsgrad) over the model's parameters")
            st = optimizer.state.get(p)
            if not st or "exp_avg_sq" not in st:
                continue
            bias2 = 1.0 - g["betas"][1] ** float(st["step"])
            step = (st["exp_avg_sq"] / bias2).sqrt_().add_(g["eps"]).reciprocal_().mul_(g["lr"])  # P = lr/(√v̂+ε)
            p.sub_(s)
            before += float(p.square().sum())
            p.div_(step.mul_(w).mul_(2.0 * self.coef).add_(1.0))  # (x − θ*)/(1 + 2Pcw)
            after += float(p.square().sum())
            p.add_(s)  # θ* + (x − θ*)/(1 + 2Pcw)
        if before > 0.0:
            self.shrinks.append(1.0 - (after / before) ** 0.5)

    def after_step(self, model: nn.Module, grads: list[torch.Tensor]) -> None:
        """Called after each optimiser step with the gradients of L_train (no penalty) of that step."""

    def after_batch(self, model: nn.Module, newest: torch.Tensor | None = None,
                    sample_grads: list[list[torch.Tensor]] | None = None) -> None:
        """Consolidate the importance at the end of a batch.

        Args:
            newest: ``(B, 3, H, W)`` images of the batch's newest keyframe(s) (MAS).
            sample_grads: per batch keyframe, the gradients of its own L_train at the parameters
                reached (one tensor per trainable parameter); given when ``needs_sample_grads``.
        """
        self.batches += 1


class EWC(Regularizer):
    """EWC adapted to single-task online fine-tuning (paper Eq. 1–2, Alg. 2).

    Args:
        model: network.
        beta: β of Eq. 1 (paper 5e7).
        max_f: cap of F̂ (paper max_F = 1e-3, applied as min; DESIGN §5).
        anchor: see module docstring.
    """

    name = "ewc"
    needs_sample_grads = True

    def __init__(self, model: nn.Module, beta: float, max_f: float, anchor: str = "previous_batch",
                 mode: str = "prox") -> None:
        super().__init__(model, beta / 2.0, anchor, mode)  # Eq. 1: Σ β/2 F̂ (θ − θ*)²
        self.max_f = float(max_f)
        self.fisher_sum = [torch.zeros_like(w) for w in self.weights]  # F of Eq. 2

    def after_batch(self, model: nn.Module, newest: torch.Tensor | None = None,
                    sample_grads: list[list[torch.Tensor]] | None = None) -> None:
        if not sample_grads:
            return
        super().after_batch(model, newest, sample_grads)
        n = len(sample_grads)
        for i, (F, w) in enumerate(zip(self.fisher_sum, self.weights)):
            for grads in sample_grads:  # F^(j) = 1/N Σ_k (∂L_k/∂θ)², at the parameters reached
                F.add_(grads[i].detach().square(), alpha=1.0 / n)  # Eq. 2: F = F + F^(j)
            torch.clamp(F / self.batches, max=self.max_f, out=w)  # Eq. 2: F̂ = min(F / j, max_F)


class MAS(Regularizer):
    """Memory Aware Synapses (Aljundi et al. 2018; paper Appendix B Eq. 20).

    Args:
        model: network.
        lam: λ of Eq. 19 (paper 0.5).
        predict: ``x (B, 3, H, W) -> depth (B, 1, H, W)`` (float32 output, differentiable); the
            function G whose squared norm defines the importance.
        anchor: see module docstring.
    """

    name = "mas"

    def __init__(self, model: nn.Module, lam: float, predict: Callable[[torch.Tensor], torch.Tensor],
                 anchor: str = "previous_batch", mode: str = "prox") -> None:
        super().__init__(model, lam, anchor, mode)
        self.predict = predict
        self.omega_sum = [torch.zeros_like(w) for w in self.weights]
        self.samples = 0

    def after_batch(self, model: nn.Module, newest: torch.Tensor | None = None,
                    sample_grads: list[list[torch.Tensor]] | None = None) -> None:
        if newest is None or newest.shape[0] == 0:
            return
        super().after_batch(model, newest)
        params = trainable(model)
        for x in newest:
            out = 1.0 / self.predict(x[None]).float()  # G = inverse depth (the CNN's disparity output)
            sq = (out ** 2).mean()  # ‖G(x)‖² / #pixels (Aljundi et al. 2018, Eq. 4)
            grads = torch.autograd.grad(sq, params, allow_unused=True)
            for o, g in zip(self.omega_sum, grads):
                if g is not None:
                    o.add_(g.abs())  # |∂‖G‖²/∂θ|
            self.samples += 1
        for w, o in zip(self.weights, self.omega_sum):
            torch.div(o, self.samples, out=w)  # Eq. 20: Ω = 1/N Σ_j |…|


class SI(Regularizer):
    """Synaptic Intelligence (Zenke et al. 2017; paper Appendix B Eq. 21).

    Args:
        model: network.
        lam: λ of Eq. 19 (paper 1.0).
        xi: damping ξ of Eq. 21.
        anchor: see module docstring.
    """

    name = "si"

    def __init__(self, model: nn.Module, lam: float, xi: float, anchor: str = "previous_batch",
                 mode: str = "prox") -> None:
        super().__init__(model, lam, anchor, mode)
        self.xi = float(xi)
        self.omega = [torch.zeros_like(w) for w in self.weights]  # ω, path integral of this batch
        self._last = [p.detach().clone() for p in trainable(model)]
        self._batch_start = [t.clone() for t in self._last]

    def before_batch(self, model: nn.Module) -> None:
        super().before_batch(model)
        self._last = [p.detach().clone() for p in trainable(model)]
        self._batch_start = [t.clone() for t in self._last]
        for o in self.omega:
            o.zero_()

    def after_step(self, model: nn.Module, grads: list[torch.Tensor]) -> None:
        for o, g, last, p in zip(self.omega, grads, self._last, trainable(model)):
            o.sub_(g.detach() * (p.detach() - last))  # Zenke Eq. 3: ω -= g · Δθ
            last.copy_(p.detach())

    def after_batch(self, model: nn.Module, newest: torch.Tensor | None = None,
                    sample_grads: list[list[torch.Tensor]] | None = None) -> None:
        super().after_batch(model, newest)
        for w, o, start, p in zip(self.weights, self.omega, self._batch_start, trainable(model)):
            total = p.detach() - start  # Δθ over the batch (the task)
            w.add_(torch.clamp(o, min=0) / (total ** 2 + self.xi))  # Eq. 21: Ω += ω / (Δθ² + ξ)
            o.zero_()


def make_regularizer(kind: str, model: nn.Module, cfg: AdaptConfig,
                     predict: Callable[[torch.Tensor], torch.Tensor] | None = None,
                     mode: str = "prox") -> Regularizer:
    """Build ``"ewc" | "mas" | "si"`` from an :class:`AdaptConfig`.

    Raises:
        ConfigError: unknown kind, bad anchor, or MAS without ``predict``.
    """
    if kind == "ewc":
        return EWC(model, cfg.ewc_beta, cfg.ewc_max_f, cfg.anchor, mode)
    if kind == "mas":
        if predict is None:
            raise ConfigError("MAS needs the network's predict function")
        return MAS(model, cfg.mas_lambda, predict, cfg.anchor, mode)
    if kind == "si":
        return SI(model, cfg.si_lambda, cfg.si_xi, cfg.anchor, mode)
    raise ConfigError(f"unknown regulariser {kind!r}; valid: ['ewc', 'mas', 'si']")

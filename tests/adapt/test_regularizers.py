"""EWC / MAS / SI: formulas on hand-computed cases, anchors, and that they act in the default config."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from mutualslam_cli.adapt.batch import TrainingBatch
from mutualslam_cli.adapt.buffer import KeyframeSample
from mutualslam_cli.adapt.depthnet import make_adam
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.adapt.regularizers import EWC, MAS, SI, make_regularizer, trainable
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.errors import ConfigError

torch.set_num_threads(1)


class Linear(nn.Module):
    def __init__(self, w):
        super().__init__()
        self.w = nn.Parameter(torch.tensor(w, dtype=torch.float64))

    def forward(self, x):
        return (self.w * x).sum()


class TinyNet(nn.Module):
    """Stand-in depth net: two convs → sigmoid disparity → depth in (0.1, 100)."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.c1 = nn.Conv2d(3, 4, 3, padding=1)
        self.c2 = nn.Conv2d(4, 1, 3, padding=1)
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(0.3 * torch.randn(p.shape, generator=g))

    def predict(self, x):
        disp = torch.sigmoid(self.c2(torch.relu(self.c1(x))))
        return 1.0 / (0.01 + (10.0 - 0.01) * disp)


def sparse_only_loss(depth, target, sources, K, T_t2s, uv, d, mask, lam_sparse, lam_smooth, alpha):
    """Stand-in L_train (train_loss signature): mean |1/D − 1/D_sparse| at integer pixels."""
    b = torch.arange(depth.shape[0])[:, None].expand_as(mask)
    pred = depth[b, 0, uv[..., 1].long(), uv[..., 0].long()]
    err = (1 / pred - 1 / d.clamp(min=1e-3)).abs()
    loss = (err * mask).sum() / mask.sum()
    return loss, {"photo": 0.0, "sparse": float(loss.detach()), "smooth": 0.0, "total": float(loss.detach())}


def val_fn(depth, uv, d, mask):
    return sparse_only_loss(depth, None, [], None, [], uv, d, mask, 0, 0, 0)[0]


def samples(n: int, seed: int = 0, h: int = 8, w: int = 12) -> list[KeyframeSample]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for k in range(n):
        uv = torch.stack([torch.randint(0, w, (10,), generator=g), torch.randint(0, h, (10,), generator=g)], 1).float()
        out.append(KeyframeSample(k, torch.rand(3, h, w, generator=g), torch.eye(3), np.eye(4), uv,
                                  1.0 + 2.0 * torch.rand(10, generator=g)))
    return out


def run(scheme: str, n: int = 8, mode: str = "prox", **over) -> OnlineAdapter:
    cfg = AdaptConfig(scheme=scheme, **over)
    ad = OnlineAdapter(TinyNet(), cfg, torch.eye(3), seed=3, loss_fn=sparse_only_loss, val_fn=val_fn, reg_mode=mode)
    for s in samples(n):
        ad.add_keyframe(s)
    return ad


def flat(model) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in trainable(model)])


# ---------------------------------------------------------------- formulas
def test_ewc_fisher_is_squared_gradient_by_hand():
    x, y = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64), 3.0
    m = Linear([0.2, 0.1, -0.4])
    ewc = EWC(m, beta=2.0, max_f=1e9)
    # batch 1: two keyframes; hand gradient of 0.5 (w·x − y)² is (w·x − y) x
    r = float((m.w.detach() * x).sum()) - y
    g_hand = r * x
    ewc.before_batch(m)
    loss = 0.5 * (m(x) - y) ** 2
    (g_auto,) = torch.autograd.grad(loss, [m.w])
    torch.testing.assert_close(g_auto, g_hand)
    ewc.after_step(m, [g_auto])  # the optimiser's steps do not enter the Fisher
    ewc.after_batch(m, None, [[g_auto], [2 * g_auto]])
    F1 = (g_hand ** 2 + (2 * g_hand) ** 2) / 2  # per-batch Fisher = mean over keyframes of g_k²
    torch.testing.assert_close(ewc.weights[0], F1)
    # batch 2: one keyframe with gradient g3; F̂ = (F1 + g3²) / j, j = 2
    g3 = torch.tensor([0.3, 0.0, -1.0], dtype=torch.float64)
    ewc.before_batch(m)
    ewc.after_batch(m, None, [[g3]])
    torch.testing.assert_close(ewc.weights[0], (F1 + g3 ** 2) / 2)


def test_ewc_fisher_of_per_keyframe_gradients_where_the_mean_gradient_is_zero():
    """Two keyframes pulling opposite ways: the batch-mean loss is at its minimum (gradient 0), its
    squared gradient says "no curvature"; the per-keyframe squared gradients (Eq. 2) do not."""
    y = torch.tensor([1.0, -1.0, 2.0, 0.0], dtype=torch.float64)
    tgt = torch.stack([y, -y])  # keyframe targets: the mean loss is minimal at w = 0
    cfg = AdaptConfig(scheme="replay+ewc", ewc_max_f=1e9, steps_per_keyframe=1)

    def loss_fn(depth, target, *rest):
        return 0.5 * ((depth.reshape(depth.shape[0], -1) - target.reshape(target.shape[0], -1)) ** 2).sum(1).mean(), {}

    class Direct(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(4, dtype=torch.float64))

        def predict(self, x):
            return self.w.expand(x.shape[0], 4).reshape(x.shape[0], 1, 1, 4)

    net = Direct()
    ad = OnlineAdapter(net, cfg, torch.eye(3), loss_fn=loss_fn, val_fn=val_fn)
    batch = TrainingBatch(ids=[0, 1], target=tgt.reshape(2, 1, 1, 4), sources=[tgt.reshape(2, 1, 1, 4)],
                          K=torch.eye(3).expand(2, 3, 3), T_t2s=[torch.eye(4).expand(2, 4, 4)],
                          uv=torch.zeros(2, 1, 2), d=torch.zeros(2, 1), mask=torch.zeros(2, 1, dtype=torch.bool))
    mean_grad = torch.autograd.grad(loss_fn(net.predict(batch.target), batch.target)[0], [net.w])[0]
    assert float(mean_grad.abs().max()) == 0.0
    grads = ad.kf_grads.at_current(batch)
    ewc = ad.regularizer
    ewc.before_batch(net)
    ewc.after_batch(net, None, grads)
    torch.testing.assert_close(ewc.weights[0], y ** 2)  # mean of (w − y_k)² over k = y²
    assert float(ewc.weights[0].sum()) > 0


def test_ewc_fisher_capped_at_max_f():
    m = Linear([0.0, 0.0, 0.0])
    ewc = EWC(m, beta=5e7, max_f=1e-3)
    for g in ([10.0, 0.01, 1e-5], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]):
        ewc.before_batch(m)
        ewc.after_batch(m, None, [[torch.tensor(g, dtype=torch.float64)]])
        assert float(ewc.weights[0].max()) <= 1e-3
    assert float(ewc.weights[0][0]) == 1e-3  # capped: min, not max (DESIGN §5)
    assert float(ewc.weights[0][2]) < 1e-3  # small Fisher is not raised to max_F


def test_ewc_penalty_value_by_hand():
    m = Linear([1.0, 2.0])
    ewc = EWC(m, beta=4.0, max_f=1.0)
    ewc.before_batch(m)
    ewc.after_batch(m, None, [[torch.tensor([0.5, 0.1], dtype=torch.float64)]])
    ewc.before_batch(m)
    with torch.no_grad():
        m.w += torch.tensor([0.1, -0.2], dtype=torch.float64)
    expected = 4.0 / 2 * (0.25 * 0.1 ** 2 + 0.01 * 0.2 ** 2)  # β/2 Σ F̂ (θ − θ*)², Eq. 1
    assert abs(float(ewc.penalty(m).detach()) - expected) < 1e-12


def test_mas_importance_by_hand():
    m = Linear([0.5, -1.0])
    xs = torch.tensor([[1.0, 2.0], [3.0, -1.0]], dtype=torch.float64)
    mas = MAS(m, lam=0.5, predict=lambda x: 1.0 / m(x[0]).reshape(1, 1, 1, 1))  # G = 1 / predict = w·x
    mas.before_batch(m)
    mas.after_batch(m, xs[:1])
    mas.before_batch(m)
    mas.after_batch(m, xs[1:])
    w = m.w.detach()
    hand = sum((2 * (w * x).sum() * x).abs() for x in xs) / 2  # mean_j |∂(w·x_j)²/∂w|, Eq. 20
    torch.testing.assert_close(mas.weights[0], hand)


def test_si_importance_by_hand():
    m = Linear([0.0, 0.0])
    si = SI(m, lam=1.0, xi=0.1)
    si.before_batch(m)
    steps = [(torch.tensor([1.0, -2.0]), torch.tensor([-0.1, 0.2])),
             (torch.tensor([0.5, 1.0]), torch.tensor([-0.2, 0.1]))]
    omega = torch.zeros(2, dtype=torch.float64)
    for g, dth in steps:
        g, dth = g.double(), dth.double()
        with torch.no_grad():
            m.w += dth
        si.after_step(m, [g])
        omega -= g * dth  # ω −= g·Δθ
    si.after_batch(m)
    total = steps[0][1].double() + steps[1][1].double()
    torch.testing.assert_close(si.weights[0], omega.clamp(min=0) / (total ** 2 + 0.1))  # Eq. 21


def test_prox_step_by_hand():
    """One proximal step in Adam's metric: θ* + (x − θ*) / (1 + 2·P·c·w), P = lr / (√v̂ + ε)."""
    m = Linear([1.0, 2.0])
    ewc = EWC(m, beta=4.0, max_f=1.0)
    ewc.before_batch(m)
    ewc.after_batch(m, None, [[torch.tensor([0.5, 0.1], dtype=torch.float64)]])  # F̂ = [0.25, 0.01], θ* will be [1, 2]
    ewc.before_batch(m)
    opt = torch.optim.Adam([m.w], lr=0.5, betas=(0.9, 0.99), eps=1e-8)
    m.w.grad = torch.tensor([-0.2, 0.4], dtype=torch.float64)
    opt.step()  # first step: v̂ = g², so P = lr / (|g| + ε)
    x = m.w.detach().clone()
    ewc.prox(m, opt)
    P = 0.5 / (torch.tensor([0.2, 0.4], dtype=torch.float64) + 1e-8)
    star = torch.tensor([1.0, 2.0], dtype=torch.float64)
    expected = star + (x - star) / (1 + 2 * P * (4.0 / 2) * torch.tensor([0.25, 0.01], dtype=torch.float64))
    torch.testing.assert_close(m.w.detach(), expected)
    # it minimises β/2 F̂ (θ − θ*)² + (θ − x)² / (2P): that objective's gradient vanishes there
    grad = 4.0 * ewc.weights[0] * (m.w.detach() - star) + (m.w.detach() - x) / P
    assert float(grad.abs().max()) < 1e-9
    # the strength it records: the share of the displacement from θ* the step took back
    shrink = 1.0 - float((m.w.detach() - star).norm() / (x - star).norm())
    assert len(ewc.shrinks) == 1
    assert ewc.shrinks[0] == pytest.approx(shrink, rel=1e-12)
    assert 0.0 < shrink < 1.0


class Vector(nn.Module):
    def __init__(self, n):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(n))


@pytest.mark.parametrize("kind", ["ewc", "mas", "si"])
def test_prox_minimises_the_penalised_quadratic(kind):
    """Adam + prox converges to argmin of L_train + c·w·(θ − θ*)², the closed form, at every curvature.

    L_train = Σ_k a_k/2 (θ_k − 1)², θ* = 0, c·w = 10 ⇒ θ_k = a_k / (a_k + 20). Each coordinate is an
    independent 1-D problem under Adam. The scalar-lr prox (correct only for SGD) settles at
    ≈ 1/(2cw) = 0.05 for all three curvatures instead.
    """
    a = torch.tensor([1e-3, 1.0, 100.0])
    m = Vector(3)
    reg = {"ewc": lambda: EWC(m, beta=2.0, max_f=1.0), "mas": lambda: MAS(m, lam=0.5, predict=lambda x: x),
           "si": lambda: SI(m, lam=1.0, xi=0.1)}[kind]()
    reg.before_batch(m)  # θ* = 0
    reg.weights[0].fill_(10.0 / reg.coef)  # c·w = 10 whatever the regulariser's constant
    opt = make_adam([m.w], lr=1e-3)  # the optimiser the online loop uses
    for _ in range(3000):
        opt.zero_grad()
        (0.5 * a * (m.w - 1.0) ** 2).sum().backward()
        opt.step()
        reg.prox(m, opt)
    closed = a / (a + 20.0)
    got = m.w.detach()
    torch.testing.assert_close(got, closed, rtol=1e-3, atol=1e-6)
    # and it is a minimiser of the penalised objective: its gradient vanishes there
    assert float((a * (got - 1.0) + 20.0 * got).abs().max()) < 0.05


def test_prox_needs_adam():
    m = Linear([1.0])
    ewc = EWC(m, beta=2.0, max_f=1.0)
    with pytest.raises(ConfigError):
        ewc.prox(m, torch.optim.SGD([m.w], lr=0.1))


def test_make_regularizer_errors():
    m = Linear([0.0])
    with pytest.raises(ConfigError):
        make_regularizer("l2", m, AdaptConfig())
    with pytest.raises(ConfigError):
        make_regularizer("mas", m, AdaptConfig())
    with pytest.raises(ConfigError):
        EWC(m, 1.0, 1.0, anchor="nowhere")
    with pytest.raises(ConfigError):
        EWC(m, 1.0, 1.0, mode="both")


# ---------------------------------------------------------------- anchors and effect in the loop
@pytest.mark.parametrize("scheme", ["replay+ewc", "replay+mas", "replay+si", "ewc"])
def test_penalty_zero_at_anchor(scheme):
    ad = run(scheme, n=6)
    reg = ad.regularizer
    assert sum(float(w.abs().sum()) for w in reg.weights) > 0  # importance was consolidated
    reg.before_batch(ad.net)
    assert float(reg.penalty(ad.net)) == 0.0


@pytest.mark.parametrize("mode", ["prox", "penalty"])
@pytest.mark.parametrize(("scheme", "base"), [("replay+ewc", "replay"), ("replay+mas", "replay"),
                                         ("replay+si", "replay"), ("ewc", "recent")])
def test_regularizer_changes_trajectory_default_config(scheme, base, mode):
    a, b = run(scheme, mode=mode), run(base)
    assert a.cfg == AdaptConfig(scheme=scheme)  # the default configuration (steps, anchor, lr)
    assert [i.batch for i in a.history] == [i.batch for i in b.history]  # same data, same replay draws
    assert not torch.equal(flat(a.net), flat(b.net))
    assert max(i.loss.get("penalty", 0.0) for i in a.history) > 0


@pytest.mark.parametrize("mode", ["prox", "penalty"])
@pytest.mark.parametrize("scheme", ["replay+ewc", "replay+mas", "replay+si"])
def test_regularized_step_stays_closer_to_anchor(scheme, mode):
    ad = run(scheme, n=8, mode=mode)
    nxt = samples(9)[8]
    with_reg, without = copy.deepcopy(ad), copy.deepcopy(ad)
    without.regularizer = None
    weights = [w.clone() for w in ad.regularizer.weights]
    star = [p.detach().clone() for p in trainable(ad.net)]  # θ* = θ after the previous batch
    with_reg.add_keyframe(nxt)
    without.add_keyframe(nxt)

    def dist(model):
        return sum(float((w * (p.detach() - s) ** 2).sum()) for w, p, s in zip(weights, trainable(model), star))

    assert dist(with_reg.net) < dist(without.net)


def test_single_step_paper_penalty_is_inert_prox_and_lagged_are_not():
    """DESIGN §5: with one step per keyframe, the paper's θ* in the loss has zero gradient."""
    base = run("replay", steps_per_keyframe=1)
    paper = run("replay+ewc", steps_per_keyframe=1, mode="penalty")
    assert torch.equal(flat(base.net), flat(paper.net))
    prox = run("replay+ewc", steps_per_keyframe=1, mode="prox")
    assert not torch.equal(flat(base.net), flat(prox.net))
    lagged = AdaptConfig(scheme="replay+ewc", steps_per_keyframe=1)
    ad = OnlineAdapter(TinyNet(), lagged, torch.eye(3), seed=3, loss_fn=sparse_only_loss, val_fn=val_fn)
    ad.regularizer = EWC(ad.net, lagged.ewc_beta, lagged.ewc_max_f, anchor="lagged", mode="penalty")
    for s in samples(8):
        ad.add_keyframe(s)
    assert not torch.equal(flat(base.net), flat(ad.net))

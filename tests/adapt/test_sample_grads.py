"""Per-keyframe gradients from one batched pass (adapt/sample_grads.py) are those of one keyframe at a time."""

from __future__ import annotations

import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, freeze_encoder_stages
from mutualslam_cli.adapt.losses import train_loss
from mutualslam_cli.adapt.regularizers import trainable
from mutualslam_cli.adapt.sample_grads import per_sample_grads, plan
from mutualslam_cli.bench.finetune import make_step_batch

W, H = 96, 64


def _loss(net, batch, depth, b):
    one = slice(b, b + 1)
    return train_loss(depth, batch.target[one], [s[one] for s in batch.sources], batch.K[one],
                      [t[one] for t in batch.T_t2s], batch.uv[one], batch.d[one], batch.mask[one])[0]


def one_at_a_time(net, params, batch):
    out = []
    for b in range(batch.target.shape[0]):
        loss = _loss(net, batch, net.predict(batch.target[b:b + 1]), b)
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        out.append([torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)])
    return out


def in_one_pass(net, params, batch, scale=None):
    def losses():
        depth = net.predict(batch.target)
        return [_loss(net, batch, depth[b:b + 1], b) for b in range(depth.shape[0])]

    return per_sample_grads(plan(net, params), params, losses, scale)


@pytest.mark.parametrize(("frozen", "scale"), [(0, None), (3, None), (0, 1024.0)])
def test_one_pass_gives_each_keyframe_its_own_gradient(frozen, scale):
    torch.manual_seed(0)
    net = DepthNet().eval()
    freeze_encoder_stages(net, frozen)
    params = trainable(net)
    batch = make_step_batch(W, H, n_points=40, seed=1)
    batch.uv[1, 20:] = 0.0  # keyframes differ in their sparse points too
    batch.mask[1, 20:] = False
    want, got = one_at_a_time(net, params, batch), in_one_pass(net, params, batch, scale)
    assert len(got) == 2
    for k in range(2):
        for p, a, b in zip(params, want[k], got[k]):
            assert b.shape == p.shape
            assert b.dtype == p.dtype
            torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5 * float(a.abs().max()) + 1e-12)
    # the two keyframes' gradients are not the same thing (each has its own loss)
    flat = [torch.cat([g.flatten() for g in got[k]]) for k in range(2)]
    assert flat[0].abs().max() > 0
    assert not torch.allclose(flat[0], flat[1], rtol=1e-2)
    # and their sum is the gradient of the summed losses: nothing is lost or counted twice
    both = torch.autograd.grad(sum(_loss(net, batch, net.predict(batch.target)[b:b + 1], b) for b in range(2)),
                               params, allow_unused=True)
    for a, b0, b1 in zip(both, got[0], got[1]):
        if a is not None:
            torch.testing.assert_close(b0 + b1, a, rtol=1e-4, atol=1e-5 * float(a.abs().max()) + 1e-12)


def test_layers_it_cannot_split_send_the_caller_to_the_loop():
    net = DepthNet().eval()
    assert plan(net, trainable(net))  # the encoder's fc is trainable but never run: zeros, as in the loop
    training = DepthNet().train()
    assert plan(training, trainable(training)) is None  # batch statistics couple the keyframes
    conv = torch.nn.Conv2d(3, 3, 3, padding=1, padding_mode="reflect")
    assert plan(conv, list(conv.parameters())) is None
    mlp = torch.nn.Sequential(torch.nn.Conv2d(3, 2, 3), torch.nn.Flatten(), torch.nn.Linear(2 * 6 * 6, 1))
    params = list(mlp.parameters())
    layers = plan(mlp, params)
    assert layers == [mlp[0]]
    x = torch.rand(2, 3, 8, 8)
    assert per_sample_grads(layers, params, lambda: list(mlp(x)[:, 0])) is None  # the Linear is reached


def test_ewc_fisher_is_the_same_either_way(monkeypatch):
    """EWC's accumulated Fisher after a few keyframes: one pass per batch = one pass per keyframe."""
    import numpy as np

    from mutualslam_cli.adapt import online
    from mutualslam_cli.adapt.buffer import KeyframeSample
    from mutualslam_cli.config import AdaptConfig

    g = torch.Generator(device="cpu").manual_seed(0)
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    samples = []
    for k in range(6):
        T = np.eye(4)
        T[:3, 3] = [0.05 * k, 0.0, 0.01 * k]
        uv = torch.rand(30, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0])
        samples.append(KeyframeSample(k, torch.rand(3, H, W, generator=g), K, T, uv, 1 + torch.rand(30, generator=g)))

    def fisher(split: bool) -> list[torch.Tensor]:
        if not split:
            monkeypatch.setattr(online, "plan", lambda net, params: None)
        torch.manual_seed(0)
        # lr 1e-4 (configs/tuned.yaml's): the two paths' rounding grows with the step, and at the paper's 1e-3 six
        # keyframes carry it to 1.7e-3 of the norm, past the bound below that tells rounding from a wrong Fisher
        ad = online.OnlineAdapter(DepthNet(), AdaptConfig(scheme="replay+ewc", steps_per_keyframe=1, lr=1e-4), K,
                                  seed=0)
        for s in samples:
            ad.add_keyframe(s)
        assert ad.regularizer.batches >= 3
        return ad.regularizer.fisher_sum

    one_pass, loop = fisher(True), fisher(False)
    for a, b in zip(loop, one_pass):
        # the same sums through other kernels (a batch of N, not N batches of 1): on an AVX2 CPU the tensors
        # differed by up to 1.2e-4 of their norm (1.7e-4 of their largest entry), rounding amplified through
        # the photometric loss; a Fisher from the wrong keyframes or the wrong samples is off by O(1)
        assert float((b - a).norm()) <= 1e-3 * float(a.norm()) + 1e-20
        torch.testing.assert_close(b, a, rtol=0, atol=1e-3 * float(a.abs().max()) + 1e-20)

"""Per-keyframe gradients from one batched pass (adapt/sample_grads.py) are those of one keyframe at a time."""

from __future__ import annotations

import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, freeze_encoder_stages
from mutualslam_cli.adapt.losses import train_loss
from mutualslam_cli.adapt.regularizers import trainable
from mutualslam_cli.adapt.sample_grads import StepCapture, per_sample_grads, plan
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

    from mutualslam_cli.adapt import keyframe_grads, online
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
            monkeypatch.setattr(keyframe_grads, "plan", lambda net, params: None)
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


def _step_with_capture(net, params, batch, scale=None):
    """One Adam step on the batch's mean L_train, its passes recorded; the capture after it."""
    capture = StepCapture(plan(net, params))
    opt = torch.optim.Adam(params, lr=1e-3)
    opt.zero_grad(set_to_none=True)
    with capture.recording():
        depth = net.predict(batch.target)
    loss = train_loss(depth, batch.target, batch.sources, batch.K, batch.T_t2s, batch.uv, batch.d, batch.mask)[0]
    (loss if scale is None else loss * scale).backward()
    capture.after_backward(params, scale)
    opt.step()  # the weights move; the recorded inputs and output gradients are those of the step's passes
    return capture


@pytest.mark.parametrize(("frozen", "scale"), [(0, None), (3, None), (0, 1024.0)])
def test_the_last_step_gives_each_keyframe_its_own_gradient(frozen, scale):
    """Split from an optimiser step's own passes of the batch's mean loss = one batched pass of the per-keyframe
    losses at the parameters that step started from (adapt/sample_grads.py, "From the batch's last step")."""
    torch.manual_seed(0)
    net = DepthNet().eval()
    freeze_encoder_stages(net, frozen)
    params = trainable(net)
    batch = make_step_batch(W, H, n_points=40, seed=1)
    batch.mask[1, 20:] = False  # fewer points in one keyframe: each image still counts in the sparse mean
    want = in_one_pass(net, params, batch)  # before the step, at the parameters it starts from
    got = _step_with_capture(net, params, batch, scale).per_sample(params, 2)
    assert got is not None
    for k in range(2):
        for p, a, b in zip(params, want[k], got[k]):
            assert b.shape == p.shape
            torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5 * float(a.abs().max()) + 1e-12)


def test_the_last_step_is_refused_where_its_split_would_be_wrong():
    torch.manual_seed(0)
    net = DepthNet().eval()
    params = trainable(net)
    batch = make_step_batch(W, H, n_points=40, seed=1)
    capture = _step_with_capture(net, params, batch)
    assert capture.per_sample(params, 2, every_image_counts=False) is None  # an image left out of a term's mean
    capture = _step_with_capture(net, params, batch)
    capture.clear()
    assert capture.per_sample(params, 2) is None  # nothing recorded (an inf step, or cleared after a batch)
    mlp = torch.nn.Sequential(torch.nn.Conv2d(3, 2, 3), torch.nn.Flatten(), torch.nn.Linear(2 * 6 * 6, 1))
    mparams = list(mlp.parameters())
    capture = StepCapture(plan(mlp, mparams))
    with capture.recording():
        out = mlp(torch.rand(2, 3, 8, 8))
    out.sum().backward()
    capture.after_backward(mparams)
    assert capture.per_sample(mparams, 2) is None  # the Linear was reached: its per-keyframe parts are unknown


def test_the_adapter_takes_the_fisher_from_the_last_step_only_when_asked_and_after_two_steps():
    """``adapt.fisher_at: last_step`` with ≥ 2 steps: a batch's Fisher comes from its last step (no pass of its own);
    with 1 step, or by default (``end``, the paper's point), from a separate pass. Either way EWC consolidates every
    trained batch."""
    import numpy as np

    from mutualslam_cli.adapt import online
    from mutualslam_cli.adapt.buffer import KeyframeSample
    from mutualslam_cli.config import AdaptConfig

    g = torch.Generator(device="cpu").manual_seed(0)
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    for steps, at, from_step in ((2, "last_step", True), (1, "last_step", False), (2, "end", False)):
        torch.manual_seed(0)
        cfg = AdaptConfig(scheme="replay+ewc", steps_per_keyframe=steps, lr=1e-4, fisher_at=at)
        ad = online.OnlineAdapter(DepthNet(), cfg, K, seed=0)
        for k in range(4):
            T = np.eye(4)
            T[:3, 3] = [0.05 * k, 0.0, 0.01 * k]
            uv = torch.rand(30, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0])
            ad.add_keyframe(KeyframeSample(k, torch.rand(3, H, W, generator=g), K, T, uv,
                                           1 + torch.rand(30, generator=g)))
        batches = ad.regularizer.batches
        assert batches >= 2
        assert ad.kf_grads.from_step == (batches if from_step else 0)
        assert (ad.kf_grads.step_capture() is not None) == (at == "last_step")  # nothing recorded by default
        assert float(sum(f.sum() for f in ad.regularizer.fisher_sum)) > 0

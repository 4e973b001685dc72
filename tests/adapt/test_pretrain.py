"""Pre-training: the loss goes down on a fixed batch, files reload key-for-key, determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, make_adam
from mutualslam_cli.adapt.pretrain import QUICK as QUICK_CFG
from mutualslam_cli.adapt.pretrain import FramePool, pretrain, silog_loss, training_batch
from mutualslam_cli.adapt.weights import load_monodepth2
from mutualslam_cli.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see conftest


QUICK = {**QUICK_CFG, "steps": 3, "pool_size": 2, "scenes": ("planar", "room"), "fast": False, "threads": 1}
QUICK.pop("steps")


def test_silog_is_scale_aware_only_through_mean_term():
    gt = torch.rand(2, 1, 8, 8) + 1
    assert float(silog_loss(gt, gt)) == pytest.approx(0.0, abs=1e-7)
    assert float(silog_loss(2 * gt, gt, lam=1.0)) == pytest.approx(0.0, abs=1e-6)
    assert float(silog_loss(2 * gt, gt, lam=0.85)) == pytest.approx(0.15 * np.log(2) ** 2, rel=1e-4)
    gt[0, 0, 0, 0] = 0  # missing GT is ignored
    assert torch.isfinite(silog_loss(gt.clamp_min(0.5), gt))


def test_loss_decreases_on_fixed_batch():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    h, w = 64, 128
    depth = (1.0 + np.linspace(0, 2, h)[:, None] * np.ones((1, w))).astype(np.float16)[None].repeat(2, 0)
    rgb = (rng.random((2, h, w, 3)) * 255).astype(np.uint8)
    rgb[..., 0] = (depth * 60).astype(np.uint8)  # a cue the net can pick up
    x, gt = training_batch(FramePool(rgb, depth), np.array([0, 1]), rng, None, augment=False)
    net = DepthNet().train()
    opt = make_adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(5):
        loss = silog_loss(net.predict(x), gt)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_pretrain_quick_saves_reloadable_files(tmp_path):
    calls = []
    rec = pretrain(tmp_path / "m", steps=3, seed=1, progress=lambda i: calls.append((i["step"], i["steps"])), **QUICK)
    assert calls == [(1, 3), (2, 3), (3, 3)]
    saved = json.loads((tmp_path / "m" / "pretrain.json").read_text())
    assert saved["steps"] == 3
    assert saved["seed"] == 1
    assert saved["complete"] is True
    assert [c["step"] for c in saved["loss_curve"]] == [1, 2, 3]
    assert all(np.isfinite(c["loss"]) for c in saved["loss_curve"])
    assert rec["s_per_step"] > 0
    assert saved["n_sequences"] == 1 + 2  # one 2-frame sequence fills the pool, refreshed after steps 1, 2
    assert rec["time_s"] >= saved["train_s"]
    enc = torch.load(tmp_path / "m" / "encoder.pth", weights_only=True)
    assert enc["encoder.conv1.weight"].dtype == torch.float16
    assert enc["height"] == 64
    assert enc["width"] == 128
    net = load_monodepth2(tmp_path / "m")  # strict: every key present with the right shape
    assert set(net.state_dict()) == set(DepthNet().state_dict())
    # deterministic: the same seed gives the same weights
    pretrain(tmp_path / "m2", steps=3, seed=1, **QUICK)
    net2 = load_monodepth2(tmp_path / "m2")
    for k, v in net.state_dict().items():
        assert torch.equal(v, net2.state_dict()[k]), k


def test_pretrain_rejects_bad_sizes(tmp_path):
    with pytest.raises(ConfigError, match="multiples of 32"):
        pretrain(tmp_path, steps=1, width=100, height=64)
    with pytest.raises(ConfigError, match="crop"):
        pretrain(tmp_path, steps=1, width=128, height=64, crop=(64, 256))

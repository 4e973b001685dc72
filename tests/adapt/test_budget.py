"""The fine-tuning budget: steps per keyframe (fixed or realtime), training resolution, frozen encoder stages."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet, freeze_encoder_stages
from mutualslam_cli.adapt.online import OnlineAdapter, resample_batch
from mutualslam_cli.config import AdaptConfig, RunConfig, load_config
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.online.realtime import RealtimeClock
from mutualslam_cli.types import Intrinsics
from tests.adapt.test_online import SCENE, K, make_net

torch.set_num_threads(1)


def test_resampled_batch_keeps_the_geometry():
    """K and the sparse pixels at the training size are those of the same camera resized (pixel centres kept):
    a 3-D point projects with the new K exactly where its old pixel moved."""
    ad = OnlineAdapter(make_net(), AdaptConfig(scheme="replay"), K)
    for s in SCENE[:3]:
        ad.buffer.add(s, training=True)
    full = ad._make_batch([2, 1])
    small = resample_batch(full, 64, 32)
    assert small.target.shape[-2:] == (32, 64)
    assert all(x.shape[-2:] == (32, 64) for x in small.sources)
    cam = Intrinsics(width=96, height=64, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2]).scaled(64, 32)
    np.testing.assert_allclose(small.K[0].numpy(), cam.K(), rtol=1e-6)
    P = torch.tensor([0.3, -0.2, 2.0])
    uv_full = (full.K[0] @ P)[:2] / P[2]
    uv_small = (small.K[0] @ P)[:2] / P[2]
    moved = resample_batch(replace(full, uv=uv_full.reshape(1, 1, 2).expand(2, 1, 2)), 64, 32).uv[0, 0]
    torch.testing.assert_close(moved, uv_small)
    assert torch.allclose(small.target.mean(), full.target.mean(), atol=1e-3)  # area resampling
    assert resample_batch(full, 0, 0) is full
    assert resample_batch(full, 96, 64) is full


def test_training_at_a_smaller_size_trains_and_validates_at_full_size():
    ad = OnlineAdapter(make_net(), AdaptConfig(scheme="replay", steps_per_keyframe=2, train_width=64,
                                               train_height=32), K)
    seen = []
    predict = ad.net.predict
    ad.net.predict = lambda x: seen.append(tuple(x.shape[-2:])) or predict(x)
    infos = [ad.add_keyframe(s) for s in SCENE[:6]]
    assert any(i.trained for i in infos)
    assert (32, 64) in seen
    assert infos[5].is_validation
    assert np.isfinite(infos[5].l_val)
    assert seen[-1] == (64, 96)  # L_val of the validation keyframe: the stored, full-size image


@pytest.mark.parametrize("n", [0, 2, 5])
def test_frozen_stages_stay_put_and_the_rest_trains(n):
    net = DepthNet()
    ad = OnlineAdapter(net, AdaptConfig(scheme="replay", steps_per_keyframe=1, freeze_stages=n), K)
    enc = net.encoder.encoder
    before = {k: v.detach().clone() for k, v in net.named_parameters()}
    for s in SCENE[:3]:
        ad.add_keyframe(s)
    frozen = [f"encoder.encoder.{m}." for stage in (("conv1", "bn1"), ("layer1",), ("layer2",), ("layer3",),
                                                      ("layer4",))[:n] for m in stage]
    for k, v in net.named_parameters():
        moved = not torch.equal(v, before[k])
        if any(k.startswith(f) for f in frozen):
            assert not moved, k
            assert not v.requires_grad, k
    assert any(not torch.equal(v, before[k]) for k, v in net.named_parameters() if k.startswith("decoder."))
    assert (n < 5) == any(not torch.equal(v, before[k]) for k, v in net.named_parameters()
                          if k.startswith("encoder.encoder.layer4"))
    assert len(ad.params) == sum(p.requires_grad for p in net.parameters())
    assert (n == 0) == enc.conv1.weight.requires_grad
    assert freeze_encoder_stages(DepthNet(), 1) == enc.conv1.weight.numel() + 2 * enc.bn1.weight.numel()


def test_steps_given_per_keyframe():
    ad = OnlineAdapter(make_net(), AdaptConfig(scheme="replay", steps_per_keyframe=8), K)
    ad.add_keyframe(SCENE[0])
    info = ad.add_keyframe(SCENE[1], steps=3)
    assert info.trained
    assert info.steps == 3
    assert len(ad.step_ms) == 3
    info = ad.add_keyframe(SCENE[2], steps=0)
    assert not info.trained
    assert info.steps == 0
    assert len(ad.step_ms) == 3
    assert ad.add_keyframe(SCENE[3]).steps == 8
    assert len(ad.batch_ms) == len(ad.consolidate_ms) == len(ad.finetune_ms) == 2  # the trained keyframes
    assert all(c <= f for c, f in zip(ad.consolidate_ms, ad.finetune_ms))


def test_realtime_clock_trains_until_the_next_keyframe_and_charges_everything():
    clock = RealtimeClock(step_cost_ms=100.0, max_steps=20)
    assert clock.arrive(0.0) == 0.0
    clock.charge(30.0)  # the tick (batch assembly): wall ms here, no step timed yet → scale 1
    assert clock.steps_until(500.0) == 5  # steps that start before the next arrival: at 30, 130, …, 430
    clock.stepped([40.0] * 5)  # 5 steps on the modelled clock, 40 ms each here
    assert clock.now_ms == pytest.approx(530.0)
    assert clock.scale() == pytest.approx(2.5)
    clock.charge(20.0)  # consolidation: 20 ms here = 50 ms modelled
    clock.done()
    assert clock.now_ms == pytest.approx(580.0)
    assert clock.arrive(500.0) == pytest.approx(580.0)  # busy past the arrival: starts when free
    assert clock.steps_until(560.0) == 0  # the next keyframe came before it could start: only stored
    clock.done()
    assert clock.arrive(1000.0) == 1000.0
    assert clock.steps_until(1000.0 + 10_000) == 20
    measured = RealtimeClock(step_cost_ms=None, max_steps=32)
    measured.arrive(0.0)
    assert measured.steps_until(100.0) == 1  # nothing timed yet: one step, to time it
    measured.stepped([250.0])
    assert measured.now_ms == 250.0
    assert measured.scale() == 1.0
    assert measured.step_ms() == 250.0
    measured.done()
    measured.arrive(260.0)
    assert measured.steps_until(1000.0) == 3  # starts at 260, 510, 760


@pytest.mark.parametrize("bad", ["adapt.train_width=300", "adapt.train_height=224", "adapt.freeze_stages=6",
                                 "adapt.step_cost_ms=0", "adapt.max_steps=0", "adapt.step_cost_ms=guessed"])
def test_bad_budget_settings(bad):
    with pytest.raises(ConfigError):
        load_config(None, [bad])
    assert isinstance(load_config(None, []), RunConfig)
    assert load_config(None, ["adapt.step_cost_ms=measured"]).adapt.step_cost_ms == "measured"


def test_l_val_over_an_even_spread_of_the_validation_keyframes():
    ad = OnlineAdapter(make_net(), AdaptConfig(scheme="replay", steps_per_keyframe=1, validate_every=2, val_max=3), K)
    infos = [ad.add_keyframe(s) for s in SCENE[:11]]
    assert ad.buffer.validation_ids == [2, 4, 6, 8, 10]
    assert infos[10].is_validation
    assert infos[10].l_val == pytest.approx(np.mean(list(ad.per_keyframe_val_loss([2, 6, 10]).values())))
    assert infos[10].l_val != pytest.approx(np.mean(list(ad.per_keyframe_val_loss([2, 4, 6, 8, 10]).values())))

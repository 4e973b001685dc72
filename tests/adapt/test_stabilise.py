"""The settings that keep online fine-tuning from rewriting the network (adapt/stabilise.py, the scale alignment of
adapt/losses.py) and the per-keyframe health figures (adapt/health.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.health import HealthMonitor
from mutualslam_cli.adapt.losses import label_scale, sparse_depth_loss
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.adapt.stabilise import TrustRegion, WeightAverage, param_groups
from mutualslam_cli.config import AdaptConfig
from tests.adapt.test_online import SCENE, K, flat, make_net

torch.set_num_threads(1)


def _points(n: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    uv = torch.stack([torch.rand(n, generator=g) * 31, torch.rand(n, generator=g) * 23], -1)[None]
    return uv, torch.ones(1, n, dtype=torch.bool), g.seed()


def test_label_scale_is_the_median_ratio_and_one_without_points():
    depth = torch.full((2, 1, 24, 32), 4.0)
    uv, mask, _ = _points()
    d = torch.full((1, uv.shape[1]), 2.0)
    s = label_scale(depth, uv.repeat(2, 1, 1), torch.cat([d, d]), torch.cat([mask, torch.zeros_like(mask)]))
    assert s.tolist() == pytest.approx([0.5, 1.0])
    assert label_scale(depth, torch.zeros(2, 0, 2), torch.zeros(2, 0), torch.zeros(2, 0, dtype=torch.bool)).tolist() \
        == [1.0, 1.0]


def test_aligned_loss_has_no_gradient_along_the_networks_scale():
    # D·s(D) does not change when D is scaled, so the loss cannot push the network's own scale (the runaway that
    # saturated the sigmoid when s was a detached constant)
    torch.manual_seed(0)
    base = 1.0 + torch.rand(1, 1, 24, 32)
    uv, mask, _ = _points()
    d = 0.3 * (1.0 + torch.rand(1, uv.shape[1]))
    log_c = torch.zeros((), requires_grad=True)
    depth = base * log_c.exp()
    loss = sparse_depth_loss(depth * label_scale(depth, uv, d, mask).view(-1, 1, 1, 1), uv, d, mask)
    loss.backward()
    assert float(loss.detach()) > 0.01
    assert abs(float(log_c.grad)) < 1e-5
    log_c.grad = None  # detached, the same loss does pull on the scale
    depth = base * log_c.exp()
    loss = sparse_depth_loss(depth * label_scale(depth, uv, d, mask).detach().view(-1, 1, 1, 1), uv, d, mask)
    loss.backward()
    assert abs(float(log_c.grad)) > 1e-3


def test_trust_region_cuts_long_steps_to_the_radius_only():
    big, small = torch.nn.Parameter(torch.ones(100)), torch.nn.Parameter(torch.ones(4))
    tr = TrustRegion([big, small], radius=0.01)
    tr.before()
    with torch.no_grad():
        big.add_(1.0)       # step norm 10 = 100 % of ‖θ‖: cut to 1 %
        small.add_(0.001)   # 0.1 %: kept
    tr.after()
    assert float((big - 1).norm()) == pytest.approx(0.01 * 10.0, rel=1e-5)
    assert torch.allclose(big - 1, torch.full((100,), 0.01))  # along the proposed direction
    assert torch.allclose(small, torch.full((4,), 1.001))
    assert tr.clipped == [0.5]


def test_weight_average_predicts_while_training_goes_on_from_its_own_weights():
    p = torch.nn.Parameter(torch.zeros(3))
    avg = WeightAverage([p], decay=0.75)
    avg.to_trained()
    with torch.no_grad():
        p.fill_(4.0)        # a batch's training
    avg.to_average()
    assert torch.allclose(p, torch.full((3,), 1.0))  # 0.75·0 + 0.25·4
    avg.to_trained()
    assert torch.allclose(p, torch.full((3,), 4.0))  # the next batch starts where training stopped
    avg.to_average()
    avg.to_average()  # twice: no second fold
    assert torch.allclose(p, torch.full((3,), 0.75 * 1.0 + 0.25 * 4.0))


def test_encoder_share_of_the_rate():
    net = DepthNet()
    params = [q for q in net.parameters() if q.requires_grad]
    assert len(param_groups(net, params, 1e-3, 1.0)) == 1
    enc, dec = param_groups(net, params, 1e-3, 0.1)
    assert enc["lr"] == pytest.approx(1e-4)
    assert dec["lr"] == 1e-3
    assert len(enc["params"]) == len(list(net.encoder.parameters()))
    assert len(enc["params"]) + len(dec["params"]) == len(params)


def test_health_figures():
    net = DepthNet()
    hm = HealthMonitor(net)
    assert hm.of_weights() == {"drift_enc": 0.0, "drift_dec": 0.0}
    depth = torch.full((1, 1, 24, 32), 2.0)
    depth[..., :4, :] = 20.0  # 1/6 of the pixels ten times deeper than the median
    uv, mask, _ = _points()
    h = hm.of_prediction(depth, uv, torch.full((1, uv.shape[1]), 1.0), mask)
    assert h["far"] == pytest.approx(4 / 24)
    assert h["disp_range"] == pytest.approx(10.0)
    assert h["label_spread"] < 0.7
    with torch.no_grad():
        next(net.decoder.parameters()).mul_(2.0)
    assert hm.of_weights()["drift_dec"] > 0
    assert hm.of_weights()["drift_enc"] == 0.0
    h = hm.of_prediction(depth, uv, torch.zeros(1, uv.shape[1]), mask)
    assert math.isnan(h["label_scale"])


def run(**over) -> OnlineAdapter:
    ad = OnlineAdapter(make_net(), AdaptConfig(scheme="replay+ewc", **over), K, seed=0)
    for s in SCENE[:8]:
        ad.add_keyframe(s)
    return ad


def test_the_stable_settings_change_the_run_and_record_its_health():
    paper, stable = run(), run(scale="align", trust=1e-3, average=0.5, encoder_lr=0.5)
    assert not torch.allclose(flat(paper.net), flat(stable.net))
    trained = [h for h in stable.history if h.trained]
    assert trained
    assert all({"far", "disp_range", "grad_enc", "grad_dec", "drift_enc", "drift_dec"} <= set(h.health)
                           for h in trained)
    assert stable.trust is not None
    assert max(stable.trust.clipped) > 0
    # between batches the network holds the average, the optimiser its own weights
    assert stable.average is not None
    assert not torch.allclose(flat(stable.net), torch.cat(
        [t.flatten() for t in stable.average.trained]))
    assert np.isfinite([h.l_val for h in stable.history if h.is_validation]).all()


def test_align_keeps_the_maps_units_in_the_networks_unit():
    net = DepthNet()
    ad = OnlineAdapter(net, AdaptConfig(scheme="replay", scale="align", steps_per_keyframe=1), K, seed=0)
    for s in SCENE[:3]:
        ad.add_keyframe(s)
    assert float(net.unit) != 1.0
    s = SCENE[2]
    every = torch.ones(1, len(s.depth), dtype=torch.bool)
    with torch.no_grad():
        scale = label_scale(net.predict(s.image[None]), s.uv[None], s.depth[None], every)
    assert float(scale) == pytest.approx(1.0, rel=0.3)  # the network now predicts in map units
    fresh = DepthNet()
    with torch.no_grad():
        before = label_scale(fresh.predict(s.image[None]), s.uv[None], s.depth[None], every)
    assert abs(float(before) - 1.0) > 0.5  # which it did not before


def test_the_benchs_default_step_stays_in_its_trust_region():
    from mutualslam_cli.adapt.depthnet import make_adam
    from mutualslam_cli.bench.finetune import finetune_step, make_step_batch

    torch.manual_seed(0)
    net = DepthNet()
    params = [q for q in net.parameters() if q.requires_grad]
    before = [q.detach().clone() for q in params]
    opt = make_adam(params, lr=1e-2)  # a rate whose steps the region must cut
    finetune_step(net, opt, make_step_batch(96, 64), fast=False, trust=TrustRegion(params, 1e-3))
    rel = [float((q - b).norm() / b.norm()) for q, b in zip(params, before) if float(b.norm()) > 0]
    assert max(rel) <= 1e-3 * (1 + 1e-4)
    assert max(rel) > 0.9e-3

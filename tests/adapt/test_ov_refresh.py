"""The OpenVINO predictor that takes new weights without a new conversion (adapt/ov_refresh.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from mutualslam_cli.adapt.depthnet import DepthNet, predict_depth
from mutualslam_cli.adapt.inference import openvino_available
from mutualslam_cli.adapt.ov_refresh import BF16_REL_TOL, NotRefreshable, RefreshablePredictor, _bn_pairs, _folded_copy


def _net_with_statistics(seed: int = 0) -> DepthNet:
    """A DepthNet whose BatchNorms hold non-trivial statistics and affine terms (a fresh one folds to identity)."""
    torch.manual_seed(seed)
    net = DepthNet().eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.1, 0.1)
    return net


def test_folding_the_batchnorms_keeps_the_network_s_depth():
    net = _net_with_statistics()
    folded = _folded_copy(net)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in folded.modules())
    assert len(_bn_pairs(net)) == sum(isinstance(m, nn.BatchNorm2d) for m in net.modules()) > 0
    x = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        ref, got = net.predict(x), folded.predict(x)
    assert torch.allclose(got, ref, rtol=1e-4, atol=1e-5)
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.modules())  # the network itself is untouched


def test_a_batchnorm_without_its_convolution_is_refused():
    class Odd(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = nn.Conv2d(3, 4, 3)
            self.norm = nn.BatchNorm2d(4)

    with pytest.raises(NotRefreshable, match="follows no convolution"):
        _bn_pairs(Odd())


@pytest.mark.skipif(not openvino_available(), reason="needs OpenVINO")
def test_a_refresh_predicts_with_the_new_weights_as_a_new_conversion_would():
    net = _net_with_statistics(1)
    x = torch.rand(2, 3, 64, 96)
    rp = RefreshablePredictor(net, 96, 64, threads=1)
    tol = BF16_REL_TOL if rp.precision == "bf16" else 1e-4
    before = rp(x)
    assert np.abs(before / predict_depth(net, x) - 1).mean() < tol
    with torch.no_grad():  # a new model: every weight and statistic moves
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p) * p.abs().mean())
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.add_(0.1)
            if isinstance(m, nn.Conv2d) and m.out_channels == 1:
                m.bias.add_(1.0)  # the disparity heads: a random network's depth is nearly flat otherwise
    ref = predict_depth(net, x)
    assert np.abs(before / ref - 1).mean() > 10 * tol  # the old compilation is far from the new model
    rp.refresh(net)
    assert len(rp.refresh_s) == 1
    assert rp.refresh_s[0] > 0
    assert np.abs(rp(x) / ref - 1).mean() < tol

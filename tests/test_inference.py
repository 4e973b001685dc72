"""The evaluation's OpenVINO runtime: same depth as PyTorch, chosen as documented."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt import inference
from mutualslam_cli.adapt.depthnet import DepthNet, fast_path_supported, predict_depth
from mutualslam_cli.errors import ConfigError


def test_runtime_resolution(monkeypatch):
    monkeypatch.setattr(inference, "openvino_available", lambda: True)
    assert inference.resolve_runtime("auto", True) == "openvino"
    assert inference.resolve_runtime("auto", False) == "torch"  # net.fast off keeps fp32 eager PyTorch
    assert inference.resolve_runtime("torch", True) == "torch"
    assert inference.resolve_runtime("openvino", False) == "openvino"
    monkeypatch.setattr(inference, "openvino_available", lambda: False)
    assert inference.resolve_runtime("auto", True) == "torch"
    with pytest.raises(ConfigError, match="not installed"):
        inference.resolve_runtime("openvino", True)
    with pytest.raises(ConfigError, match="expected auto, torch or openvino"):
        inference.resolve_runtime("onnx", True)


@pytest.mark.skipif(not inference.openvino_available(), reason="openvino not installed")
def test_openvino_matches_pytorch_and_copies_the_weights():
    torch.manual_seed(0)
    net = DepthNet().eval()
    x = torch.rand(3, 3, 64, 96)
    ref = predict_depth(net, x, fast=False)
    got = inference.openvino_predictor(net, 96, 64, threads=1)(x)
    assert got.shape == ref.shape == (3, 64, 96) and got.dtype == np.float32
    tol = 0.03 if fast_path_supported() else 1e-4  # bf16 inference where the CPU has it
    assert np.median(np.abs(got / ref - 1)) < tol
    with torch.no_grad():  # the compiled model holds the weights of its conversion
        for p in net.parameters():
            p.mul_(1.5)
    assert not np.allclose(predict_depth(net, x, fast=False), ref, rtol=1e-3)
    f = inference.openvino_predictor(net, 96, 64, threads=1)
    assert np.median(np.abs(f(x) / predict_depth(net, x, fast=False) - 1)) < tol

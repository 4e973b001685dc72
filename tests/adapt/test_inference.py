"""The evaluation's OpenVINO runtime: same depth as PyTorch, chosen as documented."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt import inference
from mutualslam_cli.adapt.depthnet import DepthNet, fast_path_supported, predict_depth
from mutualslam_cli.errors import ConfigError


@pytest.mark.parametrize("bf16", [True, False])
def test_runtime_resolution(monkeypatch, bf16):
    monkeypatch.setattr(inference, "openvino_available", lambda: True)
    monkeypatch.setattr(inference, "fast_path_supported", lambda: bf16)
    # OpenVINO in bf16 or fp32, never int8 unless asked: int8 moves an adapted model's PCD by points
    assert inference.resolve_runtime("auto", "auto") == "openvino"
    assert inference.resolve_runtime("auto", "on") == "openvino"
    assert inference.openvino_precision(int8=False) == ("bf16" if bf16 else "f32")
    assert inference.resolve_runtime("auto", "off") == "torch"  # net.fast off keeps fp32 eager PyTorch
    assert inference.resolve_runtime("torch", "auto") == "torch"
    assert inference.resolve_runtime("openvino", "off") == "openvino"
    assert inference.resolve_runtime("openvino-int8", "auto") == "openvino-int8"
    monkeypatch.setattr(inference, "openvino_available", lambda: False)
    assert inference.resolve_runtime("auto", "auto") == "torch"
    for rt in ("openvino", "openvino-int8"):
        with pytest.raises(ConfigError, match="not installed"):
            inference.resolve_runtime(rt, "auto")
    with pytest.raises(ConfigError, match="expected one of auto, torch, openvino, openvino-int8"):
        inference.resolve_runtime("onnx", "auto")


@pytest.mark.skipif(not inference.openvino_available(), reason="openvino not installed")
@pytest.mark.parametrize("fp32", [False, True])
def test_openvino_matches_pytorch_and_copies_the_weights(monkeypatch, fp32):
    """``fp32``: the precision ``auto`` compiles for on a CPU without bf16 (AVX2), forced on this one."""
    if fp32:
        monkeypatch.setattr(inference, "fast_path_supported", lambda: False)
    torch.manual_seed(0)
    net = DepthNet().eval()
    x = torch.rand(3, 3, 64, 96)
    ref = predict_depth(net, x, fast=False)
    got = inference.openvino_predictor(net, 96, 64, threads=1)(x)
    assert got.shape == ref.shape == (3, 64, 96)
    assert got.dtype == np.float32
    tol = 0.03 if fast_path_supported() and not fp32 else 1e-4  # bf16 inference where the CPU has it
    assert np.median(np.abs(got / ref - 1)) < tol
    with torch.no_grad():  # the compiled model holds the weights of its conversion
        for p in net.parameters():
            p.mul_(1.5)
    assert not np.allclose(predict_depth(net, x, fast=False), ref, rtol=1e-3)
    f = inference.openvino_predictor(net, 96, 64, threads=1)
    assert np.median(np.abs(f(x) / predict_depth(net, x, fast=False) - 1)) < tol


@pytest.mark.skipif(not inference.openvino_available(), reason="openvino not installed")
def test_openvino_conversion_sends_no_telemetry(monkeypatch):
    """OpenVINO's converter posts usage telemetry, from one new process per event, when no consent
    file says otherwise (in a spawned grid worker each re-imports torch: evaluation 3× slower)."""
    telemetry = pytest.importorskip("openvino_telemetry")
    sent = []
    monkeypatch.setattr(telemetry.Telemetry, "send_event", lambda self, *a, **k: sent.append(a))
    net = DepthNet().eval()
    inference.openvino_predictor(net, 96, 64, threads=1)(torch.rand(1, 3, 64, 96))
    assert sent == []


@pytest.mark.skipif(not inference.openvino_available(), reason="openvino not installed")
def test_openvino_pins_threads_only_when_it_may_use_every_core():
    # pinned, two single-threaded grid workers land on the same core (2x slower each, measured)
    import os

    net = DepthNet().eval()
    one = inference.openvino_predictor(net, 96, 64, threads=1).compiled
    assert one.get_property("ENABLE_CPU_PINNING") is ((os.cpu_count() or 1) <= 1)


def _bn_net(seed: int) -> DepthNet:
    """A random network with non-trivial batch-norm statistics (as trained weights have)."""
    torch.manual_seed(seed)
    net = DepthNet().eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_var.uniform_(0.5, 2.0)
                m.running_mean.uniform_(-0.1, 0.1)
    return net


def test_fake_quantised_network_keeps_the_listed_layers_and_rounds_the_others():
    from mutualslam_cli.adapt.quantize import KEEP_FP32, calibrate, fake_quantized

    net = _bn_net(0)
    x = torch.rand(2, 3, 64, 96)
    ranges = calibrate(net, x)
    q = fake_quantized(net, ranges)
    convs = {n for n, m in q.named_modules() if isinstance(m, torch.nn.Conv2d)}
    quant = {n for n, m in q.named_modules() if type(m).__name__ == "_QuantConv"}
    kept = {n for n in convs if not any(n.startswith(q_ + ".") for q_ in quant)} & set(ranges)
    assert kept == {n for n in ranges if n.startswith(KEEP_FP32)}
    assert len(quant) == len(ranges) - len(kept) > 18
    # the kept names are what KEEP_FP32's comment says
    dec = net.decoder
    assert "encoder.encoder.conv1" in kept
    for key, prefix in ((("upconv", 3, 0), "decoder.decoder.2."), (("upconv", 2, 0), "decoder.decoder.4."),
                        (("upconv", 2, 1), "decoder.decoder.5."), (("upconv", 1, 1), "decoder.decoder.7."),
                        (("upconv", 0, 0), "decoder.decoder.8."), (("upconv", 0, 1), "decoder.decoder.9."),
                        (("dispconv", 0), "decoder.decoder.10.")):
        assert dec.decoder[dec._index[key]] is dict(net.named_modules())[prefix[:-1]]
    ref = predict_depth(net, x)
    got = predict_depth(q, x)
    rel = np.abs(got / ref - 1)
    assert 0 < np.median(rel) < 0.02  # rounded, but close
    assert all(p.requires_grad for p in net.parameters())  # the original is untouched


@pytest.mark.skipif(not inference.openvino_available(), reason="openvino not installed")
def test_openvino_int8_runs_int8_kernels_close_to_fp32():
    net = _bn_net(1)
    x = torch.rand(3, 3, 64, 96)
    ref = predict_depth(net, x, fast=False)
    f = inference.openvino_predictor(net, 96, 64, threads=1, calibration=x[:2])
    got = f(x)
    assert got.shape == ref.shape
    assert np.median(np.abs(got / ref - 1)) < 0.03
    ops = f.compiled.get_runtime_model().get_ordered_ops()
    precisions = [op.get_rt_info()["runtimePrecision"].astype(str) for op in ops
                  if op.get_rt_info()["layerType"].astype(str) == "Convolution"]
    assert precisions.count("u8") >= 18, precisions  # int8 kernels, not an fp32 simulation


def test_int8_runtime_needs_calibration_frames():
    from mutualslam_cli.adapt.inputs import make_predictor
    from mutualslam_cli.config import load_config

    cfg = load_config(None, ["net.runtime=openvino-int8"])
    if not inference.openvino_available():
        pytest.skip("openvino not installed")
    with pytest.raises(ConfigError, match="calibration"):
        make_predictor(DepthNet(), cfg.net, False)

"""DepthNet architecture: Monodepth2 key names, shapes, fast path agreement."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.depthnet import (
    DepthNet,
    disp_to_depth,
    fast_context,
    fast_path_supported,
    predict_depth,
    prepare,
)
from mutualslam_cli.adapt.networks import DepthDecoder, ResnetEncoder
from mutualslam_cli.errors import ShapeError

# Facts about Monodepth2's released files (nianticlabs/monodepth2, networks/resnet_encoder.py,
# networks/depth_decoder.py, layers.py; torchvision's resnet18 module naming):
# encoder.pth = torchvision resnet18 state_dict under "encoder." (122 entries incl. 20
# num_batches_tracked buffers and fc) + height/width/use_stereo; depth.pth = 10 ConvBlocks
# (decoder.0..9.conv.conv.{weight,bias}) + 4 dispconvs (decoder.10..13.conv.{weight,bias}).
ENC_FIRST = ["encoder.conv1.weight", "encoder.bn1.weight", "encoder.bn1.bias", "encoder.bn1.running_mean",
             "encoder.bn1.running_var", "encoder.bn1.num_batches_tracked", "encoder.layer1.0.conv1.weight"]
ENC_LAST = ["encoder.layer4.1.bn2.running_var", "encoder.layer4.1.bn2.num_batches_tracked",
            "encoder.fc.weight", "encoder.fc.bias"]
ENC_SOME = ["encoder.layer2.0.downsample.0.weight", "encoder.layer2.0.downsample.1.running_mean",
            "encoder.layer3.1.conv2.weight", "encoder.layer4.0.downsample.1.bias"]
DEC_FIRST = ["decoder.0.conv.conv.weight", "decoder.0.conv.conv.bias", "decoder.1.conv.conv.weight"]
DEC_LAST = ["decoder.12.conv.bias", "decoder.13.conv.weight", "decoder.13.conv.bias"]
RESNET18_PARAMS = 11_689_512  # torchvision resnet18 incl. fc


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see conftest


def test_encoder_keys_match_monodepth2():
    enc = ResnetEncoder(18)
    keys = list(enc.state_dict())
    assert len(keys) == 122
    assert keys[: len(ENC_FIRST)] == ENC_FIRST
    assert keys[-len(ENC_LAST):] == ENC_LAST
    assert set(ENC_SOME) <= set(keys)
    assert sum(k.endswith("num_batches_tracked") for k in keys) == 20
    assert sum(p.numel() for p in enc.parameters()) == RESNET18_PARAMS
    sd = enc.state_dict()
    assert tuple(sd["encoder.conv1.weight"].shape) == (64, 3, 7, 7)
    assert tuple(sd["encoder.fc.weight"].shape) == (1000, 512)


def test_decoder_keys_match_monodepth2():
    dec = DepthDecoder([64, 64, 128, 256, 512])
    sd = dec.state_dict()
    keys = list(sd)
    assert len(keys) == 28
    assert keys[:3] == DEC_FIRST
    assert keys[-3:] == DEC_LAST
    assert tuple(sd["decoder.0.conv.conv.weight"].shape) == (256, 512, 3, 3)   # upconv(4, 0)
    assert tuple(sd["decoder.1.conv.conv.weight"].shape) == (256, 512, 3, 3)   # upconv(4, 1): 256 + 256 skip
    assert tuple(sd["decoder.7.conv.conv.weight"].shape) == (32, 96, 3, 3)     # upconv(1, 1): 32 + 64 skip
    assert tuple(sd["decoder.9.conv.conv.weight"].shape) == (16, 16, 3, 3)     # upconv(0, 1): no skip
    for s, n in zip(range(4), range(10, 14)):
        assert tuple(sd[f"decoder.{n}.conv.weight"].shape) == (1, (16, 32, 64, 128)[s], 3, 3)


def test_forward_shapes_and_range():
    torch.manual_seed(0)
    net = DepthNet(scales=(0, 1, 2, 3)).eval()
    x = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        out = net.forward_scales(x)
    assert sorted(out) == [0, 1, 2, 3]
    for s, d in out.items():
        assert d.shape == (2, 1, 64 >> s, 96 >> s)
        assert d.dtype == torch.float32
        assert float(d.min()) > 0
        assert float(d.max()) < 1
    with torch.no_grad():
        depth = net.predict(x)
        assert torch.allclose(net(x), out[0])
    assert float(depth.min()) >= 0.1 - 1e-6
    assert float(depth.max()) <= 100 + 1e-3


def test_bad_input_shape_raises():
    net = DepthNet()
    with pytest.raises(ShapeError, match="multiples of 32"):
        net(torch.rand(1, 3, 60, 96))
    with pytest.raises(ShapeError, match=r"\(B, 3, H, W\)"):
        net(torch.rand(1, 1, 64, 96))


def test_disp_to_depth_endpoints():
    scaled, depth = disp_to_depth(torch.tensor([0.0, 1.0, 0.5]), 0.1, 100.0)
    assert torch.allclose(depth[:2], torch.tensor([100.0, 0.1]))
    assert torch.allclose(scaled, 1 / depth)
    assert 0.1 < float(depth[2]) < 0.2 + 1e-6  # disp is linear in inverse depth


def test_channels_last_same_output():
    torch.manual_seed(0)
    net = DepthNet().eval()
    x = torch.rand(1, 3, 64, 64)
    ref = net(x).detach()
    prepare(net, fast=True)
    assert net.encoder.encoder.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    got = net(x).detach()
    prepare(net, fast=False)
    assert torch.allclose(ref, got, atol=1e-5)


def test_predict_depth_layouts():
    torch.manual_seed(0)
    net = DepthNet()
    img = np.random.default_rng(0).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    a = predict_depth(net, img)
    b = predict_depth(net, torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255)
    assert a.shape == (1, 64, 96)
    assert a.dtype == np.float32
    np.testing.assert_allclose(a, b, rtol=1e-5)
    assert net.training  # mode restored


@pytest.mark.skipif(not fast_path_supported(), reason="no native bf16 on this CPU")
def test_bf16_depth_close_to_fp32():
    torch.manual_seed(0)
    net = DepthNet().eval()
    x = torch.rand(1, 3, 64, 96)
    ref = net.predict(x).detach()
    with fast_context(True):
        got = prepare(net, True).predict(x).detach()
    assert got.dtype == torch.float32
    rel = ((got - ref).abs() / ref).median()
    assert float(rel) < 0.02  # bf16 keeps 8 mantissa bits; random-init net is a hard case

"""Monodepth2 file format: strict key-for-key loading, fp16 storage, default model location."""

from __future__ import annotations

import pytest
import torch

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.weights import default_weights_dir, load_default, load_monodepth2, save_monodepth2
from mutualslam_cli.errors import ConfigError


def _released_style(tmp_path, net, drop=None, rename=None, reshape=None, extra=None):
    """Write files the way Monodepth2 does: torch.save(state_dict + height/width/use_stereo)."""
    enc = dict(net.encoder.state_dict())
    dec = dict(net.decoder.state_dict())
    if drop:
        (enc if drop.startswith("encoder.") else dec).pop(drop)
    if rename:
        old, new = rename
        d = enc if old.startswith("encoder.") else dec
        d[new] = d.pop(old)
    if reshape:
        d = enc if reshape.startswith("encoder.") else dec
        d[reshape] = torch.zeros(3, 3)
    if extra:
        dec[extra] = torch.zeros(1)
    enc.update(height=192, width=640, use_stereo=True)
    torch.save(enc, tmp_path / "encoder.pth")
    torch.save(dec, tmp_path / "depth.pth")
    return tmp_path


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(3)
    n = DepthNet()
    with torch.no_grad():  # make BN statistics non-trivial so that buffers matter
        for m in n.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return n.eval()


def test_released_format_loads_identically(tmp_path, net):
    loaded = load_monodepth2(_released_style(tmp_path, net))
    x = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.equal(loaded(x), net(x))
    assert (loaded.feed_height, loaded.feed_width) == (192, 640)
    assert not loaded.training


def test_save_roundtrip_keys_and_output(tmp_path, net):
    save_monodepth2(net, tmp_path, height=192, width=640)
    enc = torch.load(tmp_path / "encoder.pth", weights_only=True)
    dec = torch.load(tmp_path / "depth.pth", weights_only=True)
    assert set(enc) == set(net.encoder.state_dict()) | {"height", "width", "use_stereo"}
    assert set(dec) == set(net.decoder.state_dict())
    assert enc["height"] == 192
    assert enc["width"] == 640
    assert enc["use_stereo"] is False
    loaded = load_monodepth2(tmp_path, max_depth=50.0)
    assert loaded.max_depth == 50.0
    for k, v in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k


def test_half_storage_converts_back(tmp_path, net):
    save_monodepth2(net, tmp_path, 192, 640, half=True)
    enc = torch.load(tmp_path / "encoder.pth", weights_only=True)
    assert enc["encoder.conv1.weight"].dtype == torch.float16
    loaded = load_monodepth2(tmp_path)
    assert loaded.encoder.encoder.conv1.weight.dtype == torch.float32
    x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        rel = ((loaded.predict(x) - net.predict(x)).abs() / net.predict(x)).max()
    assert float(rel) < 1e-2


@pytest.mark.parametrize(("case", "pattern"), [
    (dict(drop="encoder.layer2.1.conv1.weight"), r"encoder\.pth.*missing keys: encoder\.layer2\.1\.conv1\.weight"),
    (dict(rename=("decoder.3.conv.conv.bias", "decoder.3.conv.bias")),
     r"depth\.pth.*missing keys: decoder\.3\.conv\.conv\.bias; unexpected keys: decoder\.3\.conv\.bias"),
    (dict(reshape="decoder.12.conv.weight"), r"depth\.pth.*shape mismatch.*decoder\.12\.conv\.weight \(3, 3\)"),
    (dict(extra="decoder.14.conv.weight"), r"depth\.pth.*unexpected keys: decoder\.14\.conv\.weight"),
    (dict(drop="encoder.fc.weight"), r"encoder\.pth.*missing keys: encoder\.fc\.weight"),
])
def test_bad_files_raise_one_clear_error(tmp_path, net, case, pattern):
    folder = _released_style(tmp_path, net, **case)
    with pytest.raises(ConfigError, match=pattern):
        load_monodepth2(folder)


def test_tolerated_absences(tmp_path, net):
    enc = {k: v for k, v in net.encoder.state_dict().items()
           if not k.endswith("num_batches_tracked") and not k.startswith("encoder.fc.")}
    enc.update(height=96, width=320, use_stereo=False)
    torch.save(enc, tmp_path / "encoder.pth")
    torch.save(net.decoder.state_dict(), tmp_path / "depth.pth")
    loaded = load_monodepth2(tmp_path)
    x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        assert torch.equal(loaded(x), net(x))


def test_missing_and_garbage_files(tmp_path, net):
    with pytest.raises(ConfigError, match=r"encoder.pth: file not found"):
        load_monodepth2(tmp_path)
    (tmp_path / "encoder.pth").write_text("not a checkpoint")
    with pytest.raises(ConfigError, match=r"encoder.pth: cannot read"):
        load_monodepth2(tmp_path)


def test_default_location(tmp_path, monkeypatch, net):
    monkeypatch.setenv("MSLAM_WEIGHTS", str(tmp_path / "w"))
    assert default_weights_dir() == tmp_path / "w"
    with pytest.raises(ConfigError, match=r"no default model at .*: run `mslam pretrain`"):
        load_default()
    save_monodepth2(net, tmp_path / "w", 192, 640, half=True)
    assert isinstance(load_default(), DepthNet)
    monkeypatch.delenv("MSLAM_WEIGHTS")
    assert default_weights_dir().parts[-3:] == ("mutualslam_cli", "weights", "default")

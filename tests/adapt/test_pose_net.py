"""Monodepth2 pose network: released key names and shapes, strict loading, the pose convention."""

from __future__ import annotations

import json
import math

import pytest
import torch

from mutualslam_cli.adapt.networks import PoseNet, ResnetEncoder
from mutualslam_cli.adapt.networks.pose import pose_matrix, rot_from_axisangle
from mutualslam_cli.adapt.weights import load_pose, save_pose
from mutualslam_cli.errors import ConfigError

# pose.pth of Monodepth2's released models (num_input_features=1, num_frames_to_predict_for=2), written out by hand
RELEASED_POSE_DECODER = {
    "net.0.weight": (256, 512, 1, 1), "net.0.bias": (256,),
    "net.1.weight": (256, 256, 3, 3), "net.1.bias": (256,),
    "net.2.weight": (256, 256, 3, 3), "net.2.bias": (256,),
    "net.3.weight": (12, 256, 1, 1), "net.3.bias": (12,),
}


def _released_style(folder, seed=0, mutate=None):
    """pose_encoder.pth = a ResNet-18 state dict with a 6-channel conv1; pose.pth from the hand-written table."""
    g = torch.Generator().manual_seed(seed)
    enc = {k: (torch.randn(v.shape, generator=g) * 0.05 if v.is_floating_point() else v.clone())
           for k, v in ResnetEncoder().state_dict().items()}
    enc["encoder.conv1.weight"] = torch.randn(64, 6, 7, 7, generator=g) * 0.05
    for k in enc:
        if k.endswith("running_var"):
            enc[k] = enc[k].abs() + 1.0
    dec = {k: torch.randn(s, generator=g) * 0.05 for k, s in RELEASED_POSE_DECODER.items()}
    if mutate:
        mutate(enc, dec)
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(enc, folder / "pose_encoder.pth")
    torch.save(dec, folder / "pose.pth")
    return enc, dec


def test_released_files_load_key_for_key(tmp_path):
    enc, dec = _released_style(tmp_path)
    net = load_pose(tmp_path)
    assert net.decoder.num_frames_to_predict_for == 2
    assert torch.equal(net.encoder.state_dict()["encoder.conv1.weight"], enc["encoder.conv1.weight"])
    assert torch.equal(net.decoder.state_dict()["net.3.weight"], dec["net.3.weight"])
    assert set(net.decoder.state_dict()) == set(RELEASED_POSE_DECODER)


def test_save_load_round_trip_same_output(tmp_path):
    torch.manual_seed(0)
    net = PoseNet().eval()
    a, b = torch.rand(2, 1, 3, 64, 96).unbind(0)
    save_pose(net, tmp_path)
    assert {"net.0.weight", "net.3.bias"} <= set(torch.load(tmp_path / "pose.pth", weights_only=True))
    again = load_pose(tmp_path)
    with torch.no_grad():
        assert torch.equal(net(a, b), again(a, b))


@pytest.mark.parametrize(("mutate", "needle"), [
    (lambda e, d: d.__setitem__("convs.pose_0.weight", d.pop("net.1.weight")), "net.1.weight"),
    (lambda e, d: e.__setitem__("encoder.conv1.weight", torch.zeros(64, 3, 7, 7)), "encoder.conv1.weight"),
    (lambda e, d: d.__setitem__("net.3.weight", torch.zeros(7, 256, 1, 1)), "net.3.weight"),
    (lambda e, d: e.pop("encoder.layer4.1.bn2.weight"), "encoder.layer4.1.bn2.weight"),
])
def test_wrong_key_or_shape_fails_naming_it(tmp_path, mutate, needle):
    _released_style(tmp_path, mutate=mutate)
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        load_pose(tmp_path)


def test_missing_file_fails(tmp_path):
    _released_style(tmp_path)
    (tmp_path / "pose.pth").unlink()
    with pytest.raises(ConfigError, match=r"pose.pth"):
        load_pose(tmp_path)


def test_rodrigues_closed_form():
    th = 0.3
    R = rot_from_axisangle(torch.tensor([[0.0, 0.0, th]], dtype=torch.float64))[0]
    expect = torch.tensor([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]],
                          dtype=torch.float64)
    assert torch.allclose(R, expect, atol=1e-7)
    assert torch.allclose(rot_from_axisangle(torch.zeros(1, 3))[0], torch.eye(3))
    T = pose_matrix(torch.tensor([[0.1, -0.2, 0.05]]), torch.tensor([[1.0, 2.0, 3.0]]))[0]
    assert torch.allclose(T[:3, :3] @ T[:3, :3].T, torch.eye(3), atol=1e-6)
    assert torch.equal(T[:3, 3], torch.tensor([1.0, 2.0, 3.0]))
    assert torch.equal(T[3], torch.tensor([0.0, 0, 0, 1]))


def test_decoder_scale_and_first_prediction():
    # a decoder whose last conv outputs a constant: the pose is 0.01 × that constant (Monodepth2), frame 0 only
    net = PoseNet().eval()
    with torch.no_grad():
        net.decoder.net[3].weight.zero_()
        net.decoder.net[3].bias.copy_(torch.tensor([0, 0, 0, 10.0, -20.0, 30.0] + [5.0] * 6))
        T = net(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64))
    assert torch.allclose(T[0, :3, :3], torch.eye(3))
    assert torch.allclose(T[0, :3, 3], torch.tensor([0.1, -0.2, 0.3]))


def test_init_from_single_image_matches_on_identical_frames():
    # conv1 repeated and divided by n: two identical frames give the single-image encoder's features
    torch.manual_seed(1)
    single = ResnetEncoder().eval()
    net = PoseNet().eval()
    net.encoder.init_from_single_image(single)
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        assert torch.allclose(net.encoder(torch.cat([x, x], 1))[-1], single(x)[-1], atol=1e-5)


def test_pretrain_pose_fits_relative_poses_and_writes_loadable_files(tmp_path):
    from mutualslam_cli.adapt.pretrain_pose import pose_batch, pose_loss, pretrain_pose

    first, second, T = pose_batch("room", 0, 2, 64, 64)
    assert first.shape == (2, 3, 64, 64)
    assert torch.equal(first[1], second[0])
    assert float(pose_loss(T, T)) == 0.0
    assert float(pose_loss(torch.eye(4).expand(2, 4, 4), T)) > 0
    rec = pretrain_pose(tmp_path, steps=12, width=64, height=64, batch_size=2, lr=1e-3, refresh=False)
    # measured: 0.028 → 0.005
    losses = [c["loss"] for c in rec["loss_curve"]]
    assert min(losses[-3:]) < 0.5 * losses[0], losses  # one fixed batch: the optimiser must fit it
    net = load_pose(tmp_path)  # BatchNorm statistics learnt on the source frames were saved too
    assert float(net.encoder.state_dict()["encoder.bn1.running_mean"].abs().sum()) > 0
    with torch.no_grad():
        assert torch.isfinite(net(first, second)).all()
    with pytest.raises(ConfigError, match="steps"):
        pretrain_pose(tmp_path, steps=0)


def test_cli_pretrain_pose_writes_half_precision_weights_initialised_from_the_depth_encoder(tmp_path):
    from typer.testing import CliRunner

    from mutualslam_cli.cli import app

    r = CliRunner().invoke(app, ["pretrain", "--pose", "--quick", "--out", str(tmp_path), "--max-minutes", "5"])
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "pretrain_pose.json").read_text())
    assert rec["init_from_depth_encoder"]
    assert rec["half"]
    assert rec["steps_done"] == 3
    raw = torch.load(tmp_path / "pose_encoder.pth", map_location="cpu")
    assert {v.dtype for v in raw.values() if torch.is_tensor(v) and v.is_floating_point()} == {torch.float16}
    assert torch.isfinite(load_pose(tmp_path)(torch.rand(1, 3, 32, 64), torch.rand(1, 3, 32, 64))).all()

"""Scheme comoda, fairness of the baseline: the pose network starts from the run's weights folder when
it has pose files (and says so), and BatchNorm is frozen as CoMoDa's code freezes it (eval mode and
affine parameters out of the optimiser) in both networks."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from synth import make_sequence

from mutualslam_cli.adapt.comoda import ComodaAdapter
from mutualslam_cli.adapt.comoda_pose import RANDOM_POSE, make_pose_net
from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.networks import PoseNet
from mutualslam_cli.adapt.weights import POSE_DECODER_FILE, POSE_ENCODER_FILE, save_monodepth2, save_pose
from mutualslam_cli.config import AdaptConfig

W, H = 96, 64
BN = (torch.nn.BatchNorm2d,)


def _weights_folder(folder: Path, seed: int, pose: bool = True) -> Path:
    """A Monodepth2-format folder: encoder.pth + depth.pth, and pose_encoder.pth + pose.pth if ``pose``."""
    torch.manual_seed(seed)
    save_monodepth2(DepthNet(), folder, H, W)
    if pose:
        save_pose(PoseNet(), folder)
    return folder


def _file_tensors(folder: Path) -> dict[str, dict[str, torch.Tensor]]:
    return {name: torch.load(folder / name, weights_only=True) for name in (POSE_ENCODER_FILE, POSE_DECODER_FILE)}


def _assert_equals_files(net: PoseNet, folder: Path) -> None:
    files = _file_tensors(folder)
    for module, name in ((net.encoder, POSE_ENCODER_FILE), (net.decoder, POSE_DECODER_FILE)):
        own = module.state_dict()
        assert set(files[name]) == set(own)
        for k, v in files[name].items():
            assert torch.equal(own[k], v), (name, k)


def test_pose_net_comes_from_the_depth_weights_folder_when_it_has_pose_files(tmp_path, caplog):
    caplog.set_level("INFO")
    empty_default = tmp_path / "default"
    empty_default.mkdir()
    weights = _weights_folder(tmp_path / "w", seed=1)
    depth = DepthNet()
    net, source = make_pose_net(depth, AdaptConfig(), default_dir=empty_default, weights_dir=str(weights))
    _assert_equals_files(net, weights)
    assert source == str(weights.resolve())
    assert not net.training
    assert str(weights.resolve()) in caplog.text
    # no pose files beside the depth weights (and none in the default folder): random, and said so
    no_pose = _weights_folder(tmp_path / "np", seed=2, pose=False)
    net2, source2 = make_pose_net(depth, AdaptConfig(), default_dir=empty_default, weights_dir=str(no_pose))
    assert source2 == RANDOM_POSE
    assert source2.startswith("random")
    w = depth.encoder.state_dict()["encoder.conv1.weight"]
    assert torch.allclose(net2.encoder.state_dict()["encoder.conv1.weight"], torch.cat([w, w], 1) / 2)
    # ... but the default folder's pose files when it has them
    default = _weights_folder(tmp_path / "d", seed=3)
    net3, source3 = make_pose_net(depth, AdaptConfig(), default_dir=default, weights_dir=str(no_pose))
    _assert_equals_files(net3, default)
    assert source3 == str(default.resolve())


def test_comoda_pose_weights_takes_precedence_over_net_weights(tmp_path):
    weights = _weights_folder(tmp_path / "w", seed=1)
    explicit = _weights_folder(tmp_path / "explicit", seed=4)
    cfg = AdaptConfig(comoda_pose_weights=str(explicit))
    net, source = make_pose_net(DepthNet(), cfg, default_dir=weights, weights_dir=str(weights))
    _assert_equals_files(net, explicit)
    assert source == str(explicit.resolve())


def _bn_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {f"{name}.{k}": v.detach().clone() for name, m in net.named_modules() if isinstance(m, BN)
            for k, v in m.state_dict().items()}


def _other_params(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    bn = {f"{name}.{k}" for name, m in net.named_modules() if isinstance(m, BN) for k, _ in m.named_parameters()}
    return {k: p.detach().clone() for k, p in net.named_parameters() if k not in bn}


def test_updates_leave_batchnorm_untouched_in_both_networks():
    seq = make_sequence("room", n=5, width=W, height=H, seed=0)
    torch.manual_seed(0)
    depth, pose = DepthNet(max_depth=20.0), PoseNet()
    pose.encoder.init_from_single_image(depth.encoder)
    cfg = dataclasses.replace(AdaptConfig(scheme="comoda"), comoda_replay_from="sequence",
                              comoda_replay_per_step=0, comoda_lr=1e-3)
    ad = ComodaAdapter(depth, pose, cfg, seq.intrinsics.K(), seed=0)
    nets = {"depth": depth, "pose": pose}
    bn0 = {k: _bn_state(n) for k, n in nets.items()}
    other0 = {k: _other_params(n) for k, n in nets.items()}
    assert all(len(bn0[k]) > 0 for k in nets)
    optimised = {id(p) for g in ad.optimizer.param_groups for p in g["params"]}
    for n in nets.values():
        for m in n.modules():
            if isinstance(m, BN):
                assert all(id(p) not in optimised and not p.requires_grad for p in m.parameters())
    frames = [torch.from_numpy(im).permute(2, 0, 1).contiguous() for im in seq.rgb]
    for i, f in enumerate(frames):
        if i == 3:  # a caller switching to train mode must not let BatchNorm statistics move
            depth.train()
            pose.train()
        ad.add_frame(f)
    assert sum(s.trained for s in ad.history) == 3
    for k, n in nets.items():
        for name, v in _bn_state(n).items():  # weight, bias, running_mean, running_var, num_batches_tracked
            assert torch.equal(v, bn0[k][name]), (k, name)
        changed = [name for name, v in _other_params(n).items() if not torch.equal(v, other0[k][name])]
        assert "encoder.encoder.conv1.weight" in changed, (k, changed[:5])
        assert len(changed) > 10, (k, len(changed))
    assert not depth.training
    assert not pose.training

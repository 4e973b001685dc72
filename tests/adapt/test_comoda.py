"""Scheme comoda: CoMoDa-style end-to-end adaptation (depth + pose networks, per-frame triplets, replay)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch
from synth import make_sequence

from mutualslam_cli.adapt.comoda import ComodaAdapter, automasked_min_reprojection, se3_inv_torch
from mutualslam_cli.adapt.comoda_pose import make_pose_net
from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.networks import PoseNet
from mutualslam_cli.adapt.weights import save_pose
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.metrics.trajectory import ate
from mutualslam_cli.types import Trajectory

W, H = 96, 64


@pytest.fixture(scope="module")
def seq():
    return make_sequence("room", n=7, width=W, height=H, seed=0)


def _frames(seq):
    return [torch.from_numpy(im).permute(2, 0, 1).contiguous() for im in seq.rgb]  # uint8 (3, H, W)


def _adapter(seq, seed=0, **kw):
    torch.manual_seed(seed)
    depth = DepthNet(max_depth=20.0)
    pose = PoseNet()
    pose.encoder.init_from_single_image(depth.encoder)
    cfg = dataclasses.replace(AdaptConfig(scheme="comoda"), **kw)
    return ComodaAdapter(depth, pose, cfg, seq.intrinsics.K(), seed=seed)


def test_lags_one_frame_replays_and_chains_a_trajectory(seq):
    ad = _adapter(seq, comoda_replay_per_step=2)
    steps = [ad.add_frame(f) for f in _frames(seq)]
    assert [s.trained for s in steps] == [False, False] + [True] * 5
    assert [s.target for s in steps[2:]] == [1, 2, 3, 4, 5]  # triplet (t−1, t, t+1) trained when t+1 arrives
    assert steps[2].batch == [1]
    assert steps[3].batch == [2, 1]
    for s in steps[4:]:
        assert s.batch[0] == s.target
        assert len(s.batch) == 3
        assert all(r < s.target for r in s.batch[1:])
        assert len(set(s.batch)) == 3
    traj = ad.trajectory()
    assert traj.shape == (7, 4, 4)
    assert np.allclose(traj[0], np.eye(4))
    assert not np.allclose(traj[1], traj[0])
    res = ate(Trajectory(seq.timestamps, seq.poses), Trajectory(seq.timestamps, traj), align="sim3")
    assert np.isfinite(res.rmse)


def test_source_bank_is_replayed_with_its_own_intrinsics_and_never_grows(seq):
    from mutualslam_cli.adapt.comoda_source import source_triplets
    from mutualslam_cli.datasets.synthetic import synthetic_intrinsics

    bank, K_src = source_triplets(4, W, H)
    assert bank.shape == (4, 3, 3, H, W)
    assert bank.dtype == torch.uint8
    assert np.allclose(K_src.numpy(), synthetic_intrinsics(W, H).K())
    assert all(not torch.equal(bank[k, 0], bank[k, 1]) for k in range(4))  # consecutive frames, a moving camera
    assert torch.equal(source_triplets(4, W, H)[0], bank)  # fixed before the run: same seeds, same bank
    torch.manual_seed(0)
    depth = DepthNet(max_depth=20.0)
    cfg = dataclasses.replace(AdaptConfig(scheme="comoda"), comoda_replay_per_step=3)
    ad = ComodaAdapter(depth, PoseNet(), cfg, seq.intrinsics.K(), seed=0, replay_bank=(bank, K_src))
    steps = [ad.add_frame(f) for f in _frames(seq)]
    for s in steps[2:]:
        assert s.batch[0] == s.target
        assert len(s.batch) == 4
        assert sorted(s.batch[1:]) == sorted(set(s.batch[1:]))
        assert all(-4 <= r <= -1 for r in s.batch[1:])
    assert len(ad.replay) == 4
    assert ad.n_seen_triplets == 0
    # each sample is warped with its own camera: the source K in place of the sequence's changes the loss
    trip = torch.stack([bank[0], bank[1]])
    own, _ = ad._loss(trip, K_src.expand(2, 3, 3))
    other, _ = ad._loss(trip, ad.K_net.expand(2, 3, 3))
    assert float(own) != float(other)


def test_source_bank_is_rendered_once_per_cache_and_rerendered_when_unreadable(tmp_path, monkeypatch):
    from mutualslam_cli.adapt import comoda_source
    from mutualslam_cli.datasets import synthetic

    bank, K = comoda_source.source_triplets(3, W, H, cache_dir=tmp_path)
    (path,) = tmp_path.glob("*.npy")

    def no_render(*a, **k):
        raise AssertionError("rendered although the bank is cached")

    with monkeypatch.context() as m:
        m.setattr(synthetic, "iter_render", no_render)
        again, K2 = comoda_source.source_triplets(3, W, H, cache_dir=tmp_path)
    assert torch.equal(again, bank)
    assert torch.equal(K2, K)
    path.write_bytes(b"not an array")
    assert torch.equal(comoda_source.source_triplets(3, W, H, cache_dir=tmp_path)[0], bank)


def test_no_replay_and_capacity_bound(seq):
    ad = _adapter(seq, comoda_replay_per_step=0)
    assert all(len(s.batch) <= 1 for s in (ad.add_frame(f) for f in _frames(seq)))
    ad = _adapter(seq, comoda_replay_capacity=2, comoda_replay_per_step=3)
    steps = [ad.add_frame(f) for f in _frames(seq)]
    assert len(ad.replay) == 2
    assert ad.n_seen_triplets == 5
    assert max(len(s.batch) for s in steps) == 3  # current + both stored


def test_updates_lower_the_photometric_loss(seq):
    ad = _adapter(seq, comoda_replay_per_step=0)  # CoMoDa's lr 1e-4
    frames = _frames(seq)
    fixed = torch.stack(frames[2:5])[None]
    before = ad.loss_on(fixed)["photo"]
    for _ in range(4):  # four updates on the same triplet
        assert ad.train_triplet(3, fixed[0]).trained
    after = ad.loss_on(fixed)["photo"]
    assert after < 0.5 * before, (before, after)  # measured: 0.068 → 0.015


def test_deterministic_for_a_seed(seq):
    a, b = _adapter(seq, seed=3), _adapter(seq, seed=3)
    for f in _frames(seq)[:5]:
        la, lb = a.add_frame(f), b.add_frame(f)
        assert la.loss == lb.loss
        assert la.batch == lb.batch
    assert np.array_equal(a.trajectory(), b.trajectory())


def test_motion_gate_skips_static_triplets(seq):
    still = [_frames(seq)[0]] * 4
    ad = _adapter(seq, comoda_min_motion=0.01)
    steps = [ad.add_frame(f) for f in still]
    assert [s.static for s in steps] == [False, False, True, True]
    assert not any(s.trained for s in steps)
    assert ad.replay == []
    ad = _adapter(seq, comoda_min_motion=0.0)
    assert [ad.add_frame(f).trained for f in still] == [False, False, True, True]


def test_automask_and_min_reprojection_with_true_geometry(seq):
    # ground-truth depth and poses: the warped source explains the target better than the unwarped one
    f = torch.from_numpy(seq.rgb).permute(0, 3, 1, 2).float() / 255.0
    depth = torch.from_numpy(seq.depth)[:, None].float()
    K = torch.from_numpy(seq.intrinsics.K()).float()[None]
    T = [torch.from_numpy(se3_inv(seq.poses[s]) @ seq.poses[3]).float()[None] for s in (2, 4)]
    loss, mask = automasked_min_reprojection(f[3:4], [f[2:3], f[4:5]], depth[3:4], K, T)
    ident, _ = automasked_min_reprojection(f[3:4], [f[2:3], f[4:5]], depth[3:4], K,
                                           [torch.eye(4)[None]] * 2)
    assert mask.float().mean() > 0.5
    assert float(loss) < float(ident)
    # a static camera: identity reprojection is exact, the auto-mask removes every pixel
    T_any = torch.from_numpy(se3_inv(seq.poses[4]) @ seq.poses[3]).float()[None]
    loss0, mask0 = automasked_min_reprojection(f[3:4], [f[3:4], f[3:4]], depth[3:4] * 2, K, [T_any] * 2)
    assert not bool(mask0.any())
    assert float(loss0) < 1e-4


def test_se3_inverse():
    T = torch.from_numpy(make_sequence("room", n=3, width=W, height=H).poses[2]).float()[None]
    assert torch.allclose(se3_inv_torch(T) @ T, torch.eye(4)[None], atol=1e-5)


@pytest.mark.parametrize(("key", "value"), [("comoda_lr", 0.0), ("comoda_steps_per_frame", 0),
                                        ("comoda_replay_per_step", -1), ("comoda_replay_capacity", 0),
                                        ("comoda_smoothness", -1.0), ("comoda_min_motion", -0.1),
                                        ("comoda_replay_from", "future")])
def test_bad_settings_fail_naming_the_key(seq, key, value):
    with pytest.raises(ConfigError, match=key):
        _adapter(seq, **{key: value})


def test_pose_net_default_and_files(tmp_path, caplog):
    depth = DepthNet()
    net, source = make_pose_net(depth, AdaptConfig(), default_dir=str(tmp_path))
    assert "pose encoder initialised from the depth encoder" in caplog.text
    assert source.startswith("random")
    w = depth.encoder.state_dict()["encoder.conv1.weight"]
    assert torch.allclose(net.encoder.state_dict()["encoder.conv1.weight"], torch.cat([w, w], 1) / 2)
    save_pose(net, tmp_path / "p")
    again, _ = make_pose_net(depth, AdaptConfig(comoda_pose_weights=str(tmp_path / "p")), default_dir=str(tmp_path))
    assert torch.equal(again.decoder.net[3].weight, net.decoder.net[3].weight)
    with pytest.raises(ConfigError, match=r"pose_encoder.pth"):
        make_pose_net(depth, AdaptConfig(comoda_pose_weights=str(tmp_path / "none")))


# slow (~60 s in CI): a whole run; tests/stages/test_comoda_stage.py covers the stage in CI
@pytest.mark.slow
def test_run_sequence_reports_a_posenet_ate(tmp_path):
    from synth import make_tum_dir

    from mutualslam_cli.config import CONFIG_DIR, load_config
    from mutualslam_cli.pipeline import run_sequence

    root = make_tum_dir(tmp_path, n=6, width=W, height=H)
    cfg = load_config(CONFIG_DIR / "smoke.yaml", ["adapt.scheme=comoda", "ba.enabled=false"])
    s = run_sequence(str(root), cfg, out=tmp_path / "res").summary
    assert np.isfinite(s["trajectory"]["ate_rmse_m"]["posenet"])
    assert s["timing"]["finetune_ms"] > 0
    assert s["depth"]["pcd"]["lsq"]["adapted"] is not None
    folder = tmp_path / "res" / root.name / "comoda" / "seed0"
    rows = pd.read_csv(folder / "frames.csv")
    assert len(rows) == 6
    assert rows["trained"].sum() == 4
    assert len((folder / "traj_posenet.txt").read_text().splitlines()) == 7  # header + 6 poses
    s = run_sequence(str(root), load_config(CONFIG_DIR / "smoke.yaml", ["adapt.scheme=none", "ba.enabled=false"]),
                     out=tmp_path / "res").summary
    assert s["trajectory"]["ate_rmse_m"]["posenet"] is None
    assert "no pose network" in s["notes"]["trajectory.ate_rmse_m.posenet"]


def test_bench_comoda_step_runs_a_full_batch():
    from mutualslam_cli.bench.finetune import bench_comoda_step

    out = bench_comoda_step(W, H, repeats=1, warmup=0, replay=2)
    assert out["batch"] == 3
    assert out["ms"] > 0
    assert len(out["times_ms"]) == 1


class _OraclePose(torch.nn.Module):
    """Returns the ground-truth T_{first→second} of the sequence's frames (found by image equality)."""

    def __init__(self, seq):
        super().__init__()
        self.images = torch.from_numpy(seq.rgb).permute(0, 3, 1, 2).float() / 255.0
        self.poses = seq.poses

    def _index(self, img):
        return next(i for i, x in enumerate(self.images) if torch.allclose(x, img, atol=1e-6))

    def forward(self, first, second):
        T = [se3_inv(self.poses[self._index(b)]) @ self.poses[self._index(a)] for a, b in zip(first, second)]
        return torch.from_numpy(np.stack(T)).float()


def test_chained_trajectory_follows_the_pose_convention(seq):
    # with a pose network that is exactly right, the chained trajectory is the GT one (relative to frame 0)
    torch.manual_seed(0)
    ad = ComodaAdapter(DepthNet(max_depth=20.0), _OraclePose(seq), AdaptConfig(comoda_replay_per_step=0),
                       seq.intrinsics.K())
    for f in _frames(seq)[:4]:
        ad.add_frame(f)
    expect = np.stack([se3_inv(seq.poses[0]) @ p for p in seq.poses[:4]])
    assert np.allclose(ad.trajectory(), expect, atol=1e-4)

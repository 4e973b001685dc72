"""The comoda stage starts its pose network from the run's ``net.weights`` folder when that folder has
Monodepth2 pose files, and names the pose network it used in ``summary.json`` (``adaptation.pose_network``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from synth import make_tum_dir

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.networks import PoseNet
from mutualslam_cli.adapt.weights import (
    POSE_DECODER_FILE,
    POSE_ENCODER_FILE,
    load_monodepth2,
    save_monodepth2,
    save_pose,
)
from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.stages import comoda as stage
from mutualslam_cli.stages.context import RunContext

KEY = "adaptation.pose_network"


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("comoda_seq"), n=3, width=64, height=48)


@pytest.fixture
def captured(monkeypatch) -> list[dict[str, torch.Tensor]]:
    """The pose network's state when the stage hands it to the adapter (before any update)."""
    states: list[dict[str, torch.Tensor]] = []
    real = stage.ComodaAdapter

    def spy(depth_net, pose_net, *a, **k):
        states.append({k2: v.detach().clone() for k2, v in pose_net.state_dict().items()})
        return real(depth_net, pose_net, *a, **k)

    monkeypatch.setattr(stage, "ComodaAdapter", spy)
    return states


def _run(seq_dir: Path, tmp_path: Path, weights: Path, extra: list[str] | None = None) -> RunContext:
    cfg = load_config(CONFIG_DIR / "smoke.yaml", ["adapt.scheme=comoda", f"net.weights={weights}",
                                                   "adapt.comoda_replay_per_step=0", *(extra or []),
                                                   "adapt.comoda_min_motion=1.0"])  # all static: no update, fast
    run = RunContext(load_sequence(str(seq_dir)), cfg, tmp_path / "run", tmp_path)
    run.folder.mkdir(parents=True)
    stage.run_stage(run, load_monodepth2(weights), fast=False)
    json.dumps(run.summary.to_dict())  # JSON-safe
    return run


def _folder(path: Path, seed: int, pose: bool) -> Path:
    torch.manual_seed(seed)
    save_monodepth2(DepthNet(), path, 64, 96)
    if pose:
        save_pose(PoseNet(), path)
    return path


def _assert_from_files(state: dict[str, torch.Tensor], folder: Path) -> None:
    enc = torch.load(folder / POSE_ENCODER_FILE, weights_only=True)
    dec = torch.load(folder / POSE_DECODER_FILE, weights_only=True)
    files = {**{f"encoder.{k}": v for k, v in enc.items()}, **{f"decoder.{k}": v for k, v in dec.items()}}
    assert set(files) == set(state)
    assert all(torch.equal(state[k], v) for k, v in files.items())


def test_pose_network_from_net_weights_and_named_in_the_summary(seq_dir, tmp_path, captured, monkeypatch, caplog):
    caplog.set_level("INFO")
    monkeypatch.setenv("MSLAM_WEIGHTS", str(tmp_path / "no_default"))  # no default pose files to fall back on
    weights = _folder(tmp_path / "w", seed=1, pose=True)
    run = _run(seq_dir, tmp_path / "a", weights)
    _assert_from_files(captured[-1], weights)
    assert run.summary.to_dict()["adaptation"]["pose_network"] == str(weights.resolve())
    assert f"pose network: {weights.resolve()}" in caplog.text
    # without pose files beside the depth weights: random, described
    bare = _folder(tmp_path / "bare", seed=2, pose=False)
    run = _run(seq_dir, tmp_path / "b", bare)
    value = run.summary.to_dict()["adaptation"]["pose_network"]
    assert value.startswith("random")
    assert "depth encoder" in value
    # adapt.comoda_pose_weights still wins over net.weights
    explicit = _folder(tmp_path / "explicit", seed=3, pose=True)
    run = _run(seq_dir, tmp_path / "c", weights, [f"adapt.comoda_pose_weights={explicit}"])
    _assert_from_files(captured[-1], explicit)
    assert run.summary.to_dict()["adaptation"]["pose_network"] == str(explicit.resolve())

"""The figures of ``mslam report`` (running accuracy, trajectories against GT), from hand-made run folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PolyCollection
from synth import make_tum_dir

from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import exp_so3
from mutualslam_cli.report import plots as rp
from mutualslam_cli.report import trajectories as tp
from mutualslam_cli.report.tables import build_tables, collect, write_report
from mutualslam_cli.results.run_folder import run_dir, write_json, write_yaml
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.types import Trajectory


def _run(root: Path, seq: str, scheme: str, seed: int, *, running: tuple[float, float] | None = None,
         seq_root: Path | None = None) -> Path:
    """A complete run folder: ``summary.json``, ``config.yaml``, optionally ``per_frame.csv`` (running
    PCD of the pre-trained and adapted model rising linearly to ``running``) and a ``manifest.json``
    naming the sequence folder."""
    folder = run_dir(root, seq, scheme, seed)
    folder.mkdir(parents=True)
    s = Summary()
    s.set("sequence.name", seq)
    s.set("scheme", scheme)
    s.set("seed", seed)
    write_json(folder / "summary.json", s.to_dict())
    write_yaml(folder / "config.yaml", {"seed": seed, "data": {"data_root": None}, "adapt": {"scheme": scheme},
                                            "eval": {"ate_max_dt": 0.02}})
    if running is not None:
        frames = np.arange(10)
        pd.DataFrame({"frame": frames, "pretrained_pcd_lsq_running": running[0] * frames / 9,
                      "adapted_pcd_lsq_running": running[1] * frames / 9}).to_csv(folder / "per_frame.csv",
                                                                                  index=False)
    if seq_root is not None:
        write_json(folder / "manifest.json", {"sequence": {"name": seq, "root": str(seq_root)}})
    return folder


def _lines(ax) -> dict[str, np.ndarray]:
    return {ln.get_gid(): np.asarray(ln.get_ydata()) for ln in ax.get_lines() if ln.get_gid()}


# --------------------------------------------------------------------------- accuracy over frames


def test_accuracy_one_panel_per_sequence_one_line_per_scheme(tmp_path: Path):
    for seed, top in ((0, 40.0), (1, 60.0)):
        _run(tmp_path, "seqA", "replay+ewc", seed, running=(20.0, top))
    _run(tmp_path, "seqA", "recent", 0, running=(20.0, 30.0))
    _run(tmp_path, "seqB", "replay+ewc", 0, running=(10.0, 50.0))
    fig = rp.accuracy_figure(collect([tmp_path]))
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in axes] == ["seqA", "seqB"]
    a = _lines(axes[0])
    assert set(a) == {"pretrained", "recent|", "replay+ewc|"}
    np.testing.assert_allclose(a["replay+ewc|"][-1], 50.0)  # mean of the two seeds' 40 and 60
    np.testing.assert_allclose(a["pretrained"][-1], 20.0)
    band = [c for c in axes[0].collections if isinstance(c, PolyCollection)]
    assert len(band) == 1  # only replay+ewc has several seeds
    lo, hi = band[0].get_paths()[0].vertices[:, 1].min(), band[0].get_paths()[0].vertices[:, 1].max()
    assert (lo, hi) == pytest.approx((0.0, 60.0))  # min-max over seeds
    assert not [c for c in axes[1].collections if isinstance(c, PolyCollection)]
    colours = {ln.get_gid(): ln.get_color() for ax in axes for ln in ax.get_lines()}
    assert colours["replay+ewc|"] == rp.SCHEME_COLOURS["replay+ewc"]
    assert colours["recent|"] == rp.SCHEME_COLOURS["recent"]
    legend = fig.legends[0]
    assert "min–max over seeds" in legend.get_title().get_text()
    assert {t.get_text() for t in legend.get_texts()} == {"pre-trained", "recent", "replay+ewc"}
    assert axes[0].get_xlabel() == "frame"
    assert "PCD (%)" in axes[0].get_ylabel()


def test_accuracy_is_drawn_from_the_online_scores_when_the_run_has_them(tmp_path: Path):
    folder = _run(tmp_path, "seqA", "replay+ewc", 0, running=(20.0, 60.0))
    pf = pd.read_csv(folder / "per_frame.csv")
    pf["online_pcd_lsq_running"] = 35.0 * pf["frame"] / 9  # the model of each frame's time: lower
    pf.to_csv(folder / "per_frame.csv", index=False)
    fig = rp.accuracy_figure(collect([tmp_path]))
    a = _lines(fig.axes[0])
    np.testing.assert_allclose(a["replay+ewc|"][-1], 35.0)
    assert "model of its time" in fig.legends[0].get_title().get_text()
    _run(tmp_path, "seqA", "recent", 0, running=(20.0, 30.0))  # a run without online scores: its final model
    fig = rp.accuracy_figure(collect([tmp_path]))
    np.testing.assert_allclose(_lines(fig.axes[0])["recent|"][-1], 30.0)
    assert "else the final model" in fig.legends[0].get_title().get_text()


def test_scheme_colours_are_fixed():
    assert rp.scheme_colour("replay") == rp.SCHEME_COLOURS["replay"]
    c = rp.scheme_colour("my+scheme")
    assert c in rp.EXTRA_COLOURS
    assert rp.scheme_colour("my+scheme") == c
    assert len(set(rp.SCHEME_COLOURS.values())) == len(rp.SCHEME_COLOURS)


def test_accuracy_without_per_frame_writes_nothing(tmp_path: Path):
    _run(tmp_path / "runs", "seqA", "replay", 0)
    runs = collect([tmp_path / "runs"])
    assert rp.accuracy_figure(runs) is None
    assert not rp.plot_accuracy(runs, tmp_path / "acc.png")
    assert not (tmp_path / "acc.png").exists()


# --------------------------------------------------------------------------- trajectories


def _sim3(traj: Trajectory, s: float, rng: np.random.Generator, noise: float = 0.0) -> Trajectory:
    """``traj`` in another frame: positions ``s·R·p + t`` (plus Gaussian noise, metres before scaling)."""
    R, t = exp_so3(rng.normal(size=(1, 3)))[0], rng.normal(size=3)
    poses = traj.poses.copy()
    poses[:, :3, :3] = R @ poses[:, :3, :3]
    poses[:, :3, 3] = s * (traj.positions + rng.normal(scale=noise, size=traj.positions.shape)) @ R.T + t
    return Trajectory(traj.timestamps, poses)


@pytest.fixture
def seq_dir(tmp_path: Path) -> Path:
    return make_tum_dir(tmp_path, n=12)


def test_track_row_aligns_each_file_like_the_pipeline(seq_dir: Path, tmp_path: Path, rng):
    gt = load_sequence(seq_dir).gt
    folder = _run(tmp_path / "runs", "synth", "replay", 0, seq_root=seq_dir)
    write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 0.3, rng))
    write_tum_trajectory(folder / "traj_kf.txt", _sim3(gt.subset(np.arange(0, 12, 3)), 2.0, rng))
    write_tum_trajectory(folder / "traj_all_ba.txt", _sim3(gt, 0.5, rng, noise=0.002))
    row = tp.track_row(folder, gt, 0.02, "replay · seed 0")
    assert set(row.stages) == {"vo", "ba"}
    assert not row.problems
    _t, p = row.stages["vo"]
    np.testing.assert_allclose(p, gt.positions, atol=1e-5)  # an exact Sim(3) copy aligns back onto GT
    assert row.ate_text[0] == "VO 0.0000 / 0.0000"
    assert row.ate_text[1].startswith("after BA — / 0.00")
    assert row.ate_text[1] != "after BA — / 0.0000"
    np.testing.assert_array_equal(row.gt_t, gt.timestamps)


def test_trajectory_figure_one_row_per_run(seq_dir: Path, tmp_path: Path, rng):
    gt = load_sequence(seq_dir).gt
    for scheme in ("replay", "replay+ewc"):
        for seed in (0, 1):
            folder = _run(tmp_path / "runs", "synth", scheme, seed, seq_root=seq_dir)
            write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 0.4, rng, noise=0.001))
    write_tum_trajectory(folder / "traj_all_ba.txt", _sim3(gt, 0.4, rng))  # replay+ewc seed 1 only
    runs = collect([tmp_path / "runs"])
    files, notes = tp.trajectory_figures(runs, tmp_path / "out")
    assert notes == []
    assert [f.name for f in files] == ["trajectories_synth.png"]
    assert files[0].is_file()
    folders = [Path(f) for f in runs["folder"]]
    rows = [tp.track_row(f, gt, 0.02) for f in folders]
    fig = tp.trajectory_figure(rows, "synth", tp.vertical_axis(gt.poses[:, :3, :3]), "time (s)")
    assert len(fig.axes) == 2 * len(rows) == 8
    gids = [{ln.get_gid() for ln in ax.get_lines()} - {"start"} for ax in fig.axes]
    with_ba = [f == folder for f in folders for _ in ("top", "height")]
    assert sum(with_ba) == 2
    assert gids == [{"gt", "vo", "ba"} if b else {"gt", "vo"} for b in with_ba]
    top, height = fig.axes[:2]
    assert top.get_aspect() == 1.0
    assert top.get_xlabel().endswith("(m)")
    assert height.get_ylabel().endswith("(m)")
    assert {t.get_text() for t in fig.legends[0].get_texts()} >= {"GT reference", "VO (Sim(3)-aligned)",
                                                                   "after global BA (Sim(3)-aligned)"}


def test_trajectory_pages_hold_at_most_max_rows(seq_dir: Path, tmp_path: Path, rng, monkeypatch):
    monkeypatch.setattr(tp, "MAX_ROWS", 1)
    gt = load_sequence(seq_dir).gt
    for scheme in ("recent", "replay"):
        folder = _run(tmp_path / "runs", "synth", scheme, 0, seq_root=seq_dir)
        write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 1.0, rng))
    files, _ = tp.trajectory_figures(collect([tmp_path / "runs"]), tmp_path / "out")
    assert [f.name for f in files] == ["trajectories_synth_p1.png", "trajectories_synth_p2.png"]


def test_missing_gt_is_one_line_in_the_report(tmp_path: Path):
    _run(tmp_path / "runs", "nowhere_seq", "replay", 0, running=(10.0, 20.0))
    rep = build_tables(collect([tmp_path / "runs"]))
    files = write_report(rep, tmp_path / "out")
    md = (tmp_path / "out" / "report.md").read_text()
    notes = [ln for ln in md.splitlines() if ln.startswith("Trajectories of nowhere_seq")]
    assert len(notes) == 1
    assert "GT poses not found" in notes[0]
    assert "nowhere_seq" in notes[0]
    assert not (tmp_path / "out" / "trajectories").exists()
    assert (tmp_path / "out" / "accuracy_over_frames.png") in files
    assert "![accuracy_over_frames](accuracy_over_frames.png)" in md


def test_report_links_the_trajectory_figures(seq_dir: Path, tmp_path: Path, rng):
    gt = load_sequence(seq_dir).gt
    folder = _run(tmp_path / "runs", "synth", "replay", 0, seq_root=seq_dir)
    write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 1.0, rng))
    write_report(build_tables(collect([tmp_path / "runs"])), tmp_path / "out")
    md = (tmp_path / "out" / "report.md").read_text()
    assert "![trajectories_synth](trajectories/trajectories_synth.png)" in md
    assert (tmp_path / "out" / "trajectories" / "trajectories_synth.png").is_file()


@pytest.mark.parametrize(("world_up", "expected"), [((0, 0, 1), (2, 1.0)), ((0, -1, 0), (1, -1.0))])
def test_vertical_axis(world_up, expected, rng):
    """Cameras with zero roll, any heading and pitch: camera y (down) is −up, camera x horizontal."""
    up = np.asarray(world_up, dtype=float)
    horiz = [np.roll(up, 1), np.roll(up, 2)]
    rots = []
    for yaw, pitch in rng.uniform(-0.6, 0.6, size=(20, 2)):
        right = np.cos(yaw) * horiz[0] + np.sin(yaw) * horiz[1]
        fwd = np.cross(right, -up)
        down = -(np.cos(pitch) * up + np.sin(pitch) * fwd)
        fwd = np.cross(right, down)
        rots.append(np.stack([right, down, fwd], axis=1))
    assert tp.vertical_axis(np.asarray(rots)) == expected


def test_segment_starts_bridges_and_relocalisations_are_marked(seq_dir: Path, tmp_path: Path, rng):
    """The manifest's front-end events become marks on the trajectory and lines over time; a bridged
    segment is drawn as one, with its own curve."""
    gt = load_sequence(seq_dir).gt
    folder = _run(tmp_path / "runs", "synth", "replay+ewc", 0, seq_root=seq_dir)
    write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 0.4, rng, noise=0.001))
    write_tum_trajectory(folder / "traj_all_bridged.txt", _sim3(gt, 0.4, rng, noise=0.001))
    t = gt.timestamps
    m = json.loads((folder / "manifest.json").read_text())
    m["vo_meta"] = {"segment_starts": [{"segment": 0, "frame": 0, "timestamp": t[0]},
                                       {"segment": 1, "frame": 5, "timestamp": t[5]},
                                       {"segment": 2, "frame": 8, "timestamp": t[8]}],
                    "relocalisations": [{"frame": 3, "timestamp": t[3]}]}
    m["bridges"] = [{"segment": 2, "onto": 1}]
    write_json(folder / "manifest.json", m)
    assert tp.run_events(folder) == [(t[3], "relocalised"), (t[5], "segment"), (t[8], "bridge")]
    row = tp.track_row(folder, gt, 0.02)
    assert set(row.stages) == {"vo", "bridged"}
    fig = tp.trajectory_figure([row], "synth", tp.vertical_axis(gt.poses[:, :3, :3]), "time (s)")
    top, height = fig.axes
    assert {ln.get_gid() for ln in top.get_lines()} >= {"bridged", "event-relocalised", "event-segment", "event-bridge"}
    assert sum(ln.get_gid() == "event-bridge" for ln in height.get_lines()) == 1
    assert {t.get_text() for t in fig.legends[0].get_texts()} >= {"relocalised", "new segment (re-initialised)",
                                                                   "new segment, bridged"}
    assert tp.run_events(tmp_path) == []  # no manifest: no marks


def test_loops_closed_are_drawn_as_edges(seq_dir: Path, tmp_path: Path, rng):
    """Each loop of the manifest joins its new and its old keyframe on the trajectory after BA."""
    gt = load_sequence(seq_dir).gt
    folder = _run(tmp_path / "runs", "synth", "replay+ewc", 0, seq_root=seq_dir)
    write_tum_trajectory(folder / "traj_all.txt", _sim3(gt, 0.4, rng, noise=0.001))
    write_tum_trajectory(folder / "traj_all_ba.txt", _sim3(gt, 0.4, rng, noise=0.001))
    t = gt.timestamps
    m = json.loads((folder / "manifest.json").read_text())
    m["loops"] = [{"query": 9, "match": 1, "timestamp": t[9], "match_timestamp": t[1]}]
    write_json(folder / "manifest.json", m)
    assert tp.run_loops(folder) == [(t[9], t[1])]
    row = tp.track_row(folder, gt, 0.02)
    fig = tp.trajectory_figure([row], "synth", tp.vertical_axis(gt.poses[:, :3, :3]), "time (s)")
    top, height = fig.axes
    (edge,) = [ln for ln in top.get_lines() if ln.get_gid() == "loop"]
    ts, ps = row.stages["ba"]
    ends = np.c_[edge.get_xdata(), edge.get_ydata()]
    h, v = [i for i in range(3) if i != tp.vertical_axis(gt.poses[:, :3, :3])[0]]
    for x, ti in zip(ends, (t[9], t[1])):  # the edge ends where the trajectory was at the two times
        np.testing.assert_allclose(x, ps[int(np.argmin(np.abs(ts - ti)))][[h, v]])
    assert sum(ln.get_gid() == "loop" for ln in height.get_lines()) == 1
    assert "loop closed (new ↔ old keyframe)" in {x.get_text() for x in fig.legends[0].get_texts()}
    assert tp.run_loops(tmp_path) == []

"""Every figure ``mslam report`` writes (and every picture a run draws that the report copies) keeps its text
inside its canvas: each text drawn while the PNG is saved lies within the saved figure (1 px of slack).

The check sits in ``Figure.savefig`` itself, so it sees exactly what is written: the dpi of the save, the
layout (constrained or tight) as it is run for the save, and only the texts that are drawn (not the labels of
ticks outside the view, nor anything in a hidden axes).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure
from matplotlib.text import Text
from synth import make_tum_dir

from mutualslam_cli.datasets.associate import write_tum_trajectory
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.report import plots, trajectories
from mutualslam_cli.report.budget import budget_table, frontier_figure
from mutualslam_cli.report.maps import plot_maps
from mutualslam_cli.report.tables import collect
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import run_dir, write_json, write_yaml
from mutualslam_cli.results.summary import Summary

SLACK_PX = 1.0


class Saved:
    """What the intercepted ``savefig`` calls drew: one ``(file name, texts outside the canvas)`` per save."""

    def __init__(self) -> None:
        self.figures: list[tuple[str, list[str]]] = []
        self.saving: Figure | None = None

    def outside(self) -> list[str]:
        return [f"{name}: {line}" for name, bad in self.figures for line in bad]


@pytest.fixture
def saved(monkeypatch: pytest.MonkeyPatch) -> Saved:
    rec = Saved()
    draw_text, save = Text.draw, Figure.savefig

    def draw(self: Text, renderer: Any) -> None:
        draw_text(self, renderer)
        fig = rec.saving
        if fig is None or not self.get_visible() or not self.get_text().strip():
            return
        ext, box = self.get_window_extent(renderer), fig.bbox  # pixels of the save, both
        if (ext.x0 < box.x0 - SLACK_PX or ext.y0 < box.y0 - SLACK_PX or ext.x1 > box.x1 + SLACK_PX
                or ext.y1 > box.y1 + SLACK_PX):
            text = " ".join(self.get_text().split())
            line = (f"{text[:70]!r} spans x {ext.x0:.0f}..{ext.x1:.0f}, y {ext.y0:.0f}.."
                    f"{ext.y1:.0f} of a {box.width:.0f}×{box.height:.0f} canvas")
            if line not in rec.figures[-1][1]:  # a save may draw a text twice (layout, then the picture)
                rec.figures[-1][1].append(line)

    def savefig(self: Figure, fname: Any, *args: Any, **kwargs: Any) -> Any:
        rec.figures.append((Path(str(fname)).name, []))
        rec.saving = self
        try:
            return save(self, fname, *args, **kwargs)
        finally:
            rec.saving = None

    monkeypatch.setattr(Text, "draw", draw)
    monkeypatch.setattr(Figure, "savefig", savefig)
    return rec


def _check(saved: Saved, n: int) -> None:
    assert len(saved.figures) == n, saved.figures
    bad = saved.outside()
    assert not bad, "text outside the saved figure:\n" + "\n".join(bad)


def test_the_check_sees_text_outside_the_canvas(saved: Saved, tmp_path: Path):
    fig = plots.pyplot().figure(figsize=(3, 2))
    fig.text(0.5, 0.5, "a caption far wider than a figure three inches wide can ever hold", ha="center")
    plots.save_png(fig, tmp_path / "x.png")
    assert len(saved.figures) == 1
    assert saved.outside()
    assert "far wider" in saved.outside()[0]


# --------------------------------------------------------------------------- run folders


def _run(root: Path, seq: str, scheme: str, seed: int, running: bool = True, seq_root: Path | None = None) -> Path:
    """A run folder the report reads: summary, config, and a ``per_frame.csv`` with running PCD columns."""
    folder = run_dir(root, seq, scheme, seed)
    folder.mkdir(parents=True)
    s = Summary()
    for k, v in (("sequence.name", seq), ("scheme", scheme), ("seed", seed)):
        s.set(k, v)
    write_json(folder / "summary.json", s.to_dict())
    write_yaml(folder / "config.yaml", {"seed": seed, "data": {"data_root": None}, "adapt": {"scheme": scheme},
                                            "eval": {"ate_max_dt": 0.02}})
    if running:
        f = np.arange(40)
        pd.DataFrame({"frame": f, "pretrained_pcd_lsq_running": 20 + f / 4, "adapted_pcd_lsq_running": 30 + f / 2,
                      "online_pcd_lsq_running": 25 + f / 3}).to_csv(folder / "per_frame.csv", index=False)
    if seq_root is not None:
        write_json(folder / "manifest.json", {"sequence": {"name": seq, "root": str(seq_root)}})
    return folder


# --------------------------------------------------------------------------- the figures


@pytest.mark.parametrize("n_seqs", [1, 2, 3, 4])
def test_accuracy_over_frames(saved: Saved, tmp_path: Path, n_seqs: int):
    """``accuracy_over_frames.png`` as ``make demo`` draws it (one sequence, one run) and with more panels,
    seeds and schemes, and a run without online scores (the longest caption)."""
    for i in range(n_seqs):
        for seed in range(1 + (i > 0)):
            _run(tmp_path, f"rgbd_dataset_freiburg3_long_office_household_{i}", "replay+ewc", seed)
        if i:
            _run(tmp_path, f"rgbd_dataset_freiburg3_long_office_household_{i}", "recent", 0)
    if n_seqs > 2:
        folder = _run(tmp_path, "rgbd_dataset_freiburg3_long_office_household_0", "a_scheme_of_a_long_name", 0)
        pf = pd.read_csv(folder / "per_frame.csv").drop(columns="online_pcd_lsq_running")
        pf.to_csv(folder / "per_frame.csv", index=False)
    assert plots.plot_accuracy(collect([tmp_path]), tmp_path / "accuracy_over_frames.png")
    _check(saved, 1)


def test_frontier(saved: Saved, tmp_path: Path):
    rows = []
    for config, secs, pcd in (("adapt.steps_per_keyframe=8", 100.0, 45.0), ("adapt.steps_per_keyframe=4", 50.0, 35.0),
                              ("adapt.steps_per_keyframe=16, adapt.lr=0.0002, adapt.train_width=320", 160.0, 55.0)):
        for seq in ("a", "b"):
            rows.append({"scheme": "replay+ewc", "config": config, "sequence.name": seq, "depth.pcd.lsq.adapted": pcd,
                         "depth.pcd.median.adapted": pcd, "adaptation.steps": 40, "timing.finetune_ms": 250.0,
                         "timing.stage_s.adaptation": secs, "timing.total_s": secs + 10})
    assert frontier_figure(budget_table(pd.DataFrame(rows)), tmp_path / "frontier.png")
    _check(saved, 1)


def test_trajectories(saved: Saved, tmp_path: Path, rng: np.random.Generator):
    seq_dir = make_tum_dir(tmp_path, n=12)
    gt = load_sequence(seq_dir).gt
    for scheme in ("replay", "replay+ewc"):
        folder = _run(tmp_path / "runs", "synth", scheme, 0, seq_root=seq_dir)
        est = gt.positions + rng.normal(scale=0.002, size=gt.positions.shape)
        poses = gt.poses.copy()
        poses[:, :3, 3] = est
        write_tum_trajectory(folder / "traj_all.txt", type(gt)(gt.timestamps, poses))
        write_tum_trajectory(folder / "traj_all_bridged.txt", gt)
        write_tum_trajectory(folder / "traj_all_ba.txt", gt)
        write_json(folder / "manifest.json", {
            "sequence": {"name": "synth", "root": str(seq_dir)},
            "vo_meta": {"segment_starts": [{"segment": 0, "timestamp": float(gt.timestamps[0])},
                                           {"segment": 1, "timestamp": float(gt.timestamps[5])},
                                           {"segment": 2, "timestamp": float(gt.timestamps[7])}],
                        "relocalisations": [{"timestamp": float(gt.timestamps[8])}]},
            "bridges": [{"segment": 1}],
            "loops": [{"timestamp": float(gt.timestamps[10]), "match_timestamp": float(gt.timestamps[1])}]})
    late = gt.poses[:3].copy()  # keyframes outside GT's time span: a problem line under the row's title
    write_tum_trajectory(folder / "traj_kf.txt", type(gt)(gt.timestamps[:3] + 1000.0, late))
    files, notes = trajectories.trajectory_figures(collect([tmp_path / "runs"]), tmp_path / "out")
    assert len(files) == 1
    assert not notes
    _check(saved, 1)


def test_maps(saved: Saved, tmp_path: Path):
    folder = run_dir(tmp_path, "seqA", "replay+ewc", 0)
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)) * [1.0, 0.5, 0.3] + [0, 0, 3]
    err = rng.normal(scale=0.3, size=300)
    write_ply(folder / "map_vo.ply", pts, err)  # no culled and no BA map: two lines say why
    (folder / "traj_kf.txt").write_text("0 0 0 0 0 0 0 1\n1 0.1 0 0 0 0 0 1\n2 0.2 0.05 0 0 0 0 1\n")
    flat = {"map.points.vo": 300, "map.esi.vo": 0.5,
            "notes": {"map.points.culled": "disabled (ba.culling=false): BA without culling",
                      "map.points.ba": "disabled (ba.enabled=false)"}}
    heading = ("rgbd_dataset_freiburg3_long_office_household · replay+ewc · seed0 · adapt.lr=0.0002, "
               "adapt.steps_per_keyframe=4, adapt.train_width=0, ba.culling=False")
    assert plot_maps(folder, tmp_path / "maps.png", flat, heading)
    _check(saved, 1)


def test_scale_drift(saved: Saved, tmp_path: Path):
    """``scale_drift.png``, a run's figure the report links."""
    from mutualslam_cli.stages.scale_drift import figure

    n = 20
    k = np.arange(n)
    rows = [pd.DataFrame({"map": m, "start_s": k * 0.1, "segment": k // 12, "relative_scale": 1 + 0.05 * np.sin(k),
                          "local_rmse_m": 0.01 + 0.001 * k, "global_rmse_m": 0.03}) for m in ("vo", "ba")]
    figure(pd.concat(rows, ignore_index=True), tmp_path / "scale_drift.png", "seqA · replay+ewc · seed 0")
    _check(saved, 1)


def test_depth_picture(saved: Saved, tmp_path: Path):
    """``depth.png``, a run's picture the report copies."""
    from mutualslam_cli.stages.depth_export import depth_picture

    rng = np.random.default_rng(0)
    rgbs = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    depth = {m: [rng.uniform(0.5, 4.0, (48, 64)) for _ in range(3)] for m in ("pretrained", "adapted")}
    gts = [rng.uniform(0.5, 4.0, (48, 64)), None, rng.uniform(0.5, 4.0, (48, 64))]
    depth_picture(tmp_path / "depth.png", rgbs, depth, gts, [0.0, 1.5, 3.0], [0, 45, 90],
                  "rgbd_dataset_freiburg3_long_office_household · replay+ewc · seed 0")
    _check(saved, 1)


def test_dense_picture(saved: Saved, tmp_path: Path):
    """``dense.png``, a run's picture the report copies."""
    pytest.importorskip("open3d")
    from mutualslam_cli.dense.picture import dense_picture
    from mutualslam_cli.dense.tsdf import Mesh

    v = np.array([[-1.0, -1.0, 3.0], [1.0, -1.0, 3.0], [1.0, 1.0, 3.0], [-1.0, 1.0, 3.0]])
    mesh = Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.6))
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 0.1, 0.2]
    scores = {"pretrained": {"fscore_5cm": 0.41, "accuracy_m": 0.081, "completeness_m": 0.072},
              "adapted": {"fscore_5cm": 0.52, "accuracy_m": 0.061, "completeness_m": 0.055}, "gt": {}}
    dense_picture(tmp_path / "dense.png", {"pretrained": mesh, "adapted": mesh, "gt": mesh}, poses, scores,
                  "rgbd_dataset_freiburg3_long_office_household · replay+ewc · seed 0 · dense.voxel_m=0.02")
    _check(saved, 1)

"""``mslam datasets splice``: ranges of a TUM folder's frames, re-stamped, with their depth and GT, as a new folder."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.datasets.associate import read_list_file
from mutualslam_cli.datasets.splice import splice_sequence
from mutualslam_cli.errors import DatasetError

REPO = Path(__file__).resolve().parents[2]
N = 8
T0 = 100.0  # source frame i at T0 + 0.1 i s
DEPTH_FRAMES = range(5)  # depth for frames 0-4 only, 5 ms after the colour frame
NO_GT = 6  # frame 6's nearest GT sample is 50 ms away: no GT


@pytest.fixture
def src(tmp_path: Path) -> Path:
    """A tiny TUM folder: 8 colour frames (links into a store, as redkitchen_whole's), depth for 0-4, GT but for 6."""
    root, store = tmp_path / "src", tmp_path / "store"
    for d in (root / "rgb", root / "depth", store):
        d.mkdir(parents=True)
    rgb, depth, gt = ["# color images", "# timestamp filename"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for i in range(N):
        t = T0 + 0.1 * i
        cv2.imwrite(str(store / f"c{i}.png"), np.full((6, 8, 3), 20 * i, np.uint8))
        os.symlink(store / f"c{i}.png", root / "rgb" / f"c{i}.png")
        rgb.append(f"{t:.6f} rgb/c{i}.png")
        if i in DEPTH_FRAMES:
            cv2.imwrite(str(root / "depth" / f"d{i}.png"), np.full((6, 8), 1000 + i, np.uint16))
            depth.append(f"{t + 0.005:.6f} depth/d{i}.png")
        gt.append(f"{t + (0.05 if i == NO_GT else 0.003):.6f} {i}.5 0 0 0 0 0 1")
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", gt)):
        (root / name).write_text("\n".join(lines) + "\n")
    (root / "camera-intrinsics.txt").write_text("5 0 4\n0 5 3\n0 0 1\n")
    return root


def _entries(path: Path) -> list[tuple[float, list[str]]]:
    lf = read_list_file(path, min_fields=2)
    return list(zip(lf.timestamps.tolist(), lf.columns))


def test_splice_restamps_the_kept_frames_in_order_with_their_depth_and_gt(src: Path, tmp_path: Path):
    out = tmp_path / "out"
    info = splice_sequence(src, out, [(5, 8), (0, 3)], rate_hz=30.0)  # a kidnap back to the start
    sources = [5, 6, 7, 0, 1, 2]
    assert info.sources == sources
    assert info.joins == [3]
    assert (info.depth, info.gt) == (3, 5)
    rgb = _entries(out / "rgb.txt")
    np.testing.assert_allclose([t for t, _ in rgb], T0 + np.arange(6) / 30.0, atol=1e-6)  # monotone, at the rate
    for (_, (name,)), i in zip(rgb, sources):
        link = out / name
        assert os.path.isabs(os.readlink(link))
        assert Path(os.readlink(link)).parent == tmp_path / "store"  # the real file, not the source's link
        assert link.read_bytes() == (src / "rgb" / f"c{i}.png").read_bytes()
    new_time = {i: T0 + k / 30.0 for k, i in enumerate(sources)}
    depth = _entries(out / "depth.txt")  # frames 0-2 of the kept ones have depth (3, 4 are cut; 5-7 have none)
    assert [int(cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)[0, 0]) - 1000 for _, (name,) in depth] == [0, 1, 2]
    np.testing.assert_allclose([t for t, _ in depth], [new_time[i] for i in (0, 1, 2)], atol=1e-6)
    gt = _entries(out / "groundtruth.txt")  # frame 6 has no GT sample within 20 ms
    assert [c[0] for _, c in gt] == [f"{i}.5" for i in (5, 7, 0, 1, 2)]
    assert all(len(c) == 7 for _, c in gt)
    np.testing.assert_allclose([t for t, _ in gt], [new_time[i] for i in (5, 7, 0, 1, 2)], atol=1e-6)
    assert (out / "camera-intrinsics.txt").read_text() == (src / "camera-intrinsics.txt").read_text()
    manifest = json.loads((out / "splice.json").read_text())
    assert manifest["source"] == str(src.resolve())
    assert manifest["keep"] == [[5, 8], [0, 3]]
    assert manifest["source_frames"] == sources
    assert manifest["joins"] == [3]
    assert not (tmp_path / "out.tmp").exists()


def test_overlapping_ranges_repeat_frames_under_their_own_names(src: Path, tmp_path: Path):
    info = splice_sequence(src, tmp_path / "out", [(0, 4), (2, 5)], rate_hz=10.0)
    assert info.sources == [0, 1, 2, 3, 2, 3, 4]
    names = [c[0] for _, c in _entries(tmp_path / "out" / "rgb.txt")]
    assert len(set(names)) == 7
    assert (tmp_path / "out" / names[2]).read_bytes() == (tmp_path / "out" / names[4]).read_bytes()
    assert info.depth == 7  # a repeated frame keeps its depth each time


def test_an_earlier_splice_is_replaced_and_another_folder_is_not(src: Path, tmp_path: Path):
    out = tmp_path / "out"
    splice_sequence(src, out, [(0, 8)])
    assert splice_sequence(src, out, [(1, 3)]).sources == [1, 2]
    assert len(list((out / "rgb").iterdir())) == 2
    (tmp_path / "mine").mkdir()
    with pytest.raises(DatasetError, match=r"splice\.json"):
        splice_sequence(src, tmp_path / "mine", [(0, 2)])


@pytest.mark.parametrize("keep", [[(3, 3)], [(-1, 2)], [(0, N + 1)], [(0, 2), (5, 4)], []])
def test_a_bad_range_names_the_argument(src: Path, tmp_path: Path, keep):
    with pytest.raises(DatasetError, match=r"^keep") as e:
        splice_sequence(src, tmp_path / "out", keep)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "out.tmp").exists()


def test_a_folder_without_rgb_txt_is_refused(src: Path, tmp_path: Path):
    (src / "rgb.txt").unlink()
    with pytest.raises(DatasetError, match=r"rgb\.txt: not found"):
        splice_sequence(src, tmp_path / "out", [(0, 2)])


def test_cli_prints_one_line(src: Path, tmp_path: Path):
    r = CliRunner().invoke(app, ["datasets", "splice", str(src), str(tmp_path / "out"), "--keep", "0:3",
                                 "--keep", "6:8"])
    assert r.exit_code == 0, r.output
    assert len(r.output.strip().splitlines()) == 1
    assert "wrote 5 frames" in r.output


@pytest.mark.parametrize("keep", ["5:99", "5-7"])
def test_cli_bad_range_is_one_line_and_exit_1(src: Path, tmp_path: Path, keep: str):
    r = CliRunner().invoke(app, ["datasets", "splice", str(src), str(tmp_path / "out"), "--keep", keep])
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1, r.output
    assert lines[0].startswith("error:")
    assert "keep" in lines[0]


@pytest.mark.data
def test_redkitchen_cut_builds_and_loads_from_its_registry_entry(tmp_path: Path):
    from mutualslam_cli.datasets.registry import load_sequence

    whole = REPO / "_built" / "redkitchen_whole"
    if not (whole / "rgb.txt").is_file():
        pytest.skip("_built/redkitchen_whole not built (make redkitchen-whole)")
    make = (REPO / "Makefile").read_text()
    keep = [(int(a), int(b)) for a, b in re.findall(r"(\d+):(\d+)", re.search(r"RK_CUT_KEEP :=(.*)", make)[1])]
    entry = yaml.safe_load((REPO / "datasets.yaml").read_text())["datasets"]["redkitchen_cut"]
    (tmp_path / "datasets.yaml").write_text(yaml.safe_dump({"datasets": {"redkitchen_cut": entry}}))
    splice_sequence(whole, tmp_path / entry["root"], keep)
    seq = load_sequence("redkitchen_cut", registry_path=tmp_path / "datasets.yaml")
    frames = sum(b - a for a, b in keep)
    assert len(seq.frames) == frames == 820
    assert sum(f.pose is not None for f in seq.frames) == frames
    assert sum(f.depth_path is not None for f in seq.frames) == 300  # redkitchen_whole's depth: frames 0-299
    j = keep[0][1] - keep[0][0]
    before, after = seq.frames[j - 1].pose, seq.frames[j].pose
    assert np.linalg.norm(before[:3, 3] - after[:3, 3]) > 0.4  # a jump tracking cannot bridge (1.42 m)

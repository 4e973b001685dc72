"""mslam eval-depth: another network's predictions scored exactly as mslam run scores ours (issue 12)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import load_config
from mutualslam_cli.datasets.predictions import match_predictions, prediction_files, read_pfm, read_prediction
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.errors import ConfigError, DatasetError
from mutualslam_cli.eval_depth import eval_depth
from mutualslam_cli.metrics import depth as dm
from mutualslam_cli.results.summary import read_summary
from mutualslam_cli.vo.camera import Undistorter

runner = CliRunner()


@pytest.fixture(scope="module")
def far(tmp_path_factory) -> Path:
    """6 frames of the synthetic 'far' room at 64×48: GT depth 3–8.5 m, so a shift in inverse depth matters."""
    return make_tum_dir(tmp_path_factory.mktemp("ext"), scene="far", n=6, width=64, height=48)


def write_pfm_like_midas(path: Path, image: np.ndarray, little_endian: bool = True) -> None:
    """What MiDaS's utils.write_pfm writes for a grey float32 map: 'Pf', 'W H', the scale with the byte
    order in its sign (negative = little-endian), then the rows bottom-up."""
    a = np.flipud(np.asarray(image, dtype="<f4" if little_endian else ">f4"))
    head = b"Pf\n" + b"%d %d\n" % (a.shape[1], a.shape[0]) + (b"-1.000000\n" if little_endian else b"1.000000\n")
    path.write_bytes(head + a.tobytes())


def write(path: Path, a: np.ndarray) -> Path:
    """Save ``a`` in the format of ``path``'s extension (PNG: ``a`` must already be uint16)."""
    ext = path.suffix
    if ext == ".npy":
        np.save(path, a)
    elif ext == ".npz":
        np.savez(path, a)
    elif ext == ".png":
        assert cv2.imwrite(str(path), a)
    else:
        write_pfm_like_midas(path, a)
    return path


def predict(seq_dir: Path, out: Path, fn: Callable[[np.ndarray], np.ndarray], ext: str = ".npy",
            name: Callable[[Path, float], str] = lambda rgb, t: rgb.stem) -> Path:
    """One file per frame with GT depth: ``fn(GT depth)`` named ``name(rgb path, timestamp) + ext``."""
    seq = load_sequence(seq_dir)
    out.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(seq.frames):
        if f.depth_path is not None:
            write(out / (name(Path(f.rgb_path), f.timestamp) + ext), fn(seq.load_depth(i).astype(np.float64)))
    return out


def relative_inverse(g: np.ndarray) -> np.ndarray:
    """0.3/GT + 0.05: MiDaS-like relative inverse depth (missing GT → any finite value)."""
    with np.errstate(divide="ignore"):
        return np.where(g > 0, 0.3 / g + 0.05, 1.0)


# ----------------------------------------------------------------------------- the must-shows


def test_gt_times_2_7_scores_100_under_lsq_and_median(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "x2.7", lambda g: 2.7 * g)
    r = eval_depth(far, preds, "gtx2.7", "depth", out=tmp_path / "res")
    d = r.summary.nested()["depth"]
    assert d["pcd"]["lsq"]["adapted"] == 100.0
    assert d["pcd"]["median"]["adapted"] == 100.0
    assert d["pcd"]["none"]["adapted"] == 0.0  # 2.7× is 170 % off without scaling: the scalings are what fixes it
    assert d["esi"]["adapted"] == pytest.approx(0.0, abs=1e-6)
    assert d["frames_evaluated"] == 6
    assert r.folder == tmp_path / "res" / far.name / "gtx2.7" / "seed0"


def test_relative_inverse_scores_100_with_scale_and_shift_and_clearly_less_without(far: Path,
                                                                                   tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "midas", relative_inverse)
    aligned = eval_depth(far, preds, "midas", "relative-inverse", out=tmp_path / "res").summary.nested()["depth"]
    for scaling in ("lsq", "median", "none"):  # aligned to 1/GT: metric depth, so even unscaled is exact
        assert aligned["pcd"][scaling]["adapted"] == pytest.approx(100.0)
    plain = eval_depth(far, preds, "midas-noshift", "inverse", out=tmp_path / "res").summary.nested()["depth"]
    assert plain["pcd"]["lsq"]["adapted"] < 50.0
    assert plain["pcd"]["median"]["adapted"] < 50.0
    assert plain["esi"]["adapted"] > 0.05 > aligned["esi"]["adapted"]
    pf = pd.read_csv(tmp_path / "res" / far.name / "midas" / "seed0" / "per_frame.csv")
    np.testing.assert_allclose(pf["adapted_align_scale"], 1 / 0.3, rtol=1e-6)  # s·x + t = 1/GT
    np.testing.assert_allclose(pf["adapted_align_shift"], -0.05 / 0.3, rtol=1e-6)


def test_a_folder_missing_one_frame_fails_naming_that_frame(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g)
    (preds / "0.100000.npy").unlink()
    with pytest.raises(DatasetError, match=r"no prediction for frame 3 \(rgb/0\.100000\.png, t=0\.100000\): "
                                           r"looked for 0\.100000\.npy") as e:
        eval_depth(far, preds, "m", out=tmp_path / "res")
    assert "more frame" not in str(e.value)
    assert not (tmp_path / "res" / far.name / "m").exists()  # failed before writing anything


# ----------------------------------------------------------------------------- formats


@pytest.mark.parametrize("ext", [".npy", ".npz", ".png", ".pfm"])
def test_every_format_round_trips_and_scores_like_npy(far: Path, tmp_path: Path, ext: str) -> None:
    v, u = np.mgrid[0:5, 0:7]
    a = (1000 + 37 * u + 911 * v).astype(np.float64)  # asymmetric: a flip or a transpose would show
    f = write(tmp_path / f"a{ext}", a.astype(np.uint16) if ext == ".png" else a)
    np.testing.assert_array_equal(read_prediction(f, scale=0.5), 0.5 * a)
    fn = (lambda g: np.round(2.7 * g * 1000).astype(np.uint16)) if ext == ".png" else (lambda g: 2.7 * g)
    preds = predict(far, tmp_path / "p", fn, ext)
    s = eval_depth(far, preds, "m", scale=1e-3 if ext == ".png" else 1.0, out=tmp_path / "res").summary
    assert s.get("depth.pcd.lsq.adapted") == 100.0
    assert s.get("external.ext") == ext[1:]


def test_pfm_byte_order_and_orientation_as_midas_writes_it(tmp_path: Path) -> None:
    a = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.25 - 1.0
    for little in (True, False):
        write_pfm_like_midas(tmp_path / "a.pfm", a, little)
        raw = (tmp_path / "a.pfm").read_bytes()
        assert raw.startswith(b"Pf\n4 3\n" + (b"-1" if little else b"1"))
        np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), a)  # top row first again
    (tmp_path / "short.pfm").write_bytes(raw[:-4])
    with pytest.raises(DatasetError, match="44 bytes of samples, expected 48"):
        read_pfm(tmp_path / "short.pfm")


def test_npz_with_several_arrays_needs_a_key_and_png_must_be_16_bit(tmp_path: Path) -> None:
    np.savez(tmp_path / "a.npz", depth=np.ones((2, 3)), conf=np.zeros((2, 3)))
    with pytest.raises(DatasetError, match=r"2 arrays \(it holds depth, conf\); name the prediction's array"):
        read_prediction(tmp_path / "a.npz")
    assert read_prediction(tmp_path / "a.npz", npz_key="depth").sum() == 6
    cv2.imwrite(str(tmp_path / "b.png"), np.ones((2, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"uint8 with 1 channel.*16-bit"):
        read_prediction(tmp_path / "b.png")
    np.save(tmp_path / "c.npy", np.ones((1, 4, 5, 1)))
    assert read_prediction(tmp_path / "c.npy").shape == (4, 5)
    np.save(tmp_path / "d.npy", np.ones((2, 4, 5)))
    with pytest.raises(DatasetError, match=r"shape \(2, 4, 5\); expected one map"):
        read_prediction(tmp_path / "d.npy")


# ----------------------------------------------------------------------------- matching and errors


def test_matching_by_timestamp_and_midas_suffix(far: Path, tmp_path: Path) -> None:
    seq = load_sequence(far)
    frames = list(range(len(seq)))
    by_t = predict(far, tmp_path / "t", lambda g: g, name=lambda rgb, t: f"{t:.4f}")  # not the stem 0.033333
    assert {i: p.name for i, p in match_predictions(seq, frames, prediction_files(by_t)).items()}[1] == "0.0333.npy"
    midas = predict(far, tmp_path / "m", lambda g: g, ".pfm", name=lambda rgb, t: f"{rgb.stem}-dpt_beit_large_512")
    assert match_predictions(seq, frames, prediction_files(midas))[2].name == "0.066667-dpt_beit_large_512.pfm"
    write(midas / "0.066667.pfm", np.ones((2, 2)))
    with pytest.raises(DatasetError, match=r"frame 2 \(rgb/0\.066667\.png\): 2 prediction files match it"):
        match_predictions(seq, frames, prediction_files(midas))


def test_several_formats_need_ext_and_missing_frames_are_counted(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g, ".pfm")
    predict(far, preds, lambda g: np.ones_like(g, dtype=np.uint16), ".png")  # as MiDaS: a PNG beside each PFM
    with pytest.raises(DatasetError, match=r"several formats \(6 \.pfm, 6 \.png\); choose one with --ext"):
        prediction_files(preds)
    assert len(prediction_files(preds, "pfm")) == 6
    with pytest.raises(ConfigError, match="--ext 'jpg'"):
        prediction_files(preds, "jpg")
    for stem in ("0.100000", "0.133333"):
        (preds / f"{stem}.pfm").unlink()
    with pytest.raises(DatasetError, match=r"frame 3 .*; 1 more frame\(s\) have none"):
        match_predictions(load_sequence(far), list(range(6)), prediction_files(preds, "pfm"))


@pytest.mark.parametrize(("bad", "kind", "message"), [
    (lambda g: np.full_like(g, np.nan), "relative-inverse", "values are NaN or infinite"),
    (lambda g: -g, "depth", "values are negative"),
    (lambda g: -g, "inverse", "values are negative"),
])
def test_bad_values_are_one_error_naming_the_file(far: Path, tmp_path: Path, bad, kind: str, message: str) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g + 1.0)
    write(preds / "0.033333.npy", bad(np.ones((48, 64))))
    with pytest.raises(DatasetError, match=rf"0\.033333\.npy: .*{message}"):
        eval_depth(far, preds, "m", kind, out=tmp_path / "res")


def test_a_mis_sized_frame_is_one_error_naming_it(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g)
    write(preds / "0.066667.npy", np.ones((24, 32)))
    with pytest.raises(DatasetError, match=r"0\.066667\.npy \(frame 2, rgb/0\.066667\.png\): prediction is 24×32 "
                                           r"but 0\.000000\.npy is 48×64"):
        eval_depth(far, preds, "m", out=tmp_path / "res")
    transposed = predict(far, tmp_path / "t", lambda g: g.T.copy())
    with pytest.raises(DatasetError, match="transposed"):
        eval_depth(far, transposed, "m", out=tmp_path / "res")


def test_name_may_not_be_a_scheme_and_kind_is_checked(far: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="one of our models"):
        eval_depth(far, tmp_path, "replay+ewc")
    with pytest.raises(ConfigError, match="--kind 'disparity'"):
        eval_depth(far, tmp_path, "m", "disparity")


# ----------------------------------------------------------------------------- resolution and geometry


def test_compared_at_gt_resolution_like_mslam_run(far: Path, tmp_path: Path) -> None:
    """A half-resolution prediction is resized to GT's resolution before scoring (n_valid = GT pixels)."""
    preds = predict(far, tmp_path / "p", lambda g: cv2.resize(2.7 * g, (32, 24), interpolation=cv2.INTER_AREA))
    eval_depth(far, preds, "half", out=tmp_path / "res")
    pf = pd.read_csv(tmp_path / "res" / far.name / "half" / "seed0" / "per_frame.csv")
    assert (pf["n_valid"] == 48 * 64).all()
    assert (pf["adapted_pcd_lsq"] > 80).all()
    ref = load_sequence(far)
    x = cv2.resize(cv2.resize(2.7 * ref.load_depth(0).astype(np.float64), (32, 24), interpolation=cv2.INTER_AREA),
                   (64, 48), interpolation=cv2.INTER_LINEAR)
    assert pf["adapted_pcd_lsq"][0] == pytest.approx(dm.percent_correct(x, ref.load_depth(0), "lsq"))


def test_distorted_camera_predictions_are_remapped_like_gt(far: Path, tmp_path: Path) -> None:
    """Predictions of the raw (distorted) images go through the GT's undistortion: GT×2.7 stays exact."""
    seq = load_sequence(far)
    seq = dataclasses.replace(seq, intrinsics=dataclasses.replace(seq.intrinsics, dist=(0.4, -0.2, 0.0, 0.0, 0.0)))
    preds = predict(far, tmp_path / "p", lambda g: 2.7 * g)
    s = eval_depth(seq, preds, "m", out=tmp_path / "res").summary
    assert s.get("depth.pcd.lsq.adapted") == 100.0
    und, raw = Undistorter(seq.intrinsics), seq.load_depth(0)
    assert dm.percent_correct(2.7 * raw, und.depth(raw), "lsq") < 95.0  # left raw, the case would fail


# ----------------------------------------------------------------------------- the result folder and the CLI


def test_result_folder_reads_like_a_run(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: 2.0 * g)
    r = eval_depth(far, preds, "ext", out=tmp_path / "res", command=["mslam", "eval-depth"])
    names = {p.name for p in r.folder.iterdir()}
    assert {"config.yaml", "manifest.json", "per_frame.csv", "summary.json"} <= names
    s = read_summary(r.folder)
    assert s.version == 2
    assert s.get("scheme") == "ext"
    assert s.get("external.model") == "ext"
    assert s.get("external.kind") == "depth"
    assert s.get("depth.pcd.lsq.pretrained") is None
    assert "not adapted" in s.notes["depth.pcd.lsq.pretrained"]
    assert s.get("trajectory.ate_rmse_m.vo") is None
    assert "depth predictions only" in s.notes[
        "trajectory.ate_rmse_m.vo"]
    pf = pd.read_csv(r.folder / "per_frame.csv")
    assert list(pf["frame"]) == list(range(6))
    assert not pf["is_keyframe"].any()
    assert pf["adapted_pcd_lsq_running"].iloc[-1] == 100.0
    assert json.loads((r.folder / "manifest.json").read_text())["external"]["predictions"] == str(preds.resolve())
    again = eval_depth(far, preds, "ext", out=tmp_path / "res")
    assert again.skipped
    assert not eval_depth(far, preds, "ext", out=tmp_path / "res", force=True).skipped


def test_max_frames_and_eval_stride_choose_the_frames_as_in_a_run(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g)
    (preds / "0.166667.npy").unlink()  # frame 5: not scored with max_frames 4, so not needed
    cfg = load_config(None, ["data.max_frames=4", "eval.stride=2"])
    s = eval_depth(far, preds, "m", cfg=cfg, out=tmp_path / "res").summary
    assert s.get("depth.frames_evaluated") == 2
    assert s.get("depth.eval_stride") == 2


def test_cli_eval_depth_then_report_shows_the_external_row(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "midas", relative_inverse, ".pfm")
    out = tmp_path / "res"
    r = runner.invoke(app, ["eval-depth", str(far), str(preds), "--name", "midas", "--kind", "relative-inverse",
                            "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert r.output.count("│ 100 ") == 3
    assert "external, no adaptation" in r.output
    r = runner.invoke(app, ["report", str(out), "--out", str(tmp_path / "report")])
    assert r.exit_code == 0, r.output
    assert r.output.count("midas (external, no adaptation)") >= 3  # Tables 1, 2 and 6
    t6 = pd.read_csv(tmp_path / "report" / "table6_esi.csv").set_index("method")
    assert t6.loc["midas (external, no adaptation)", f"{far.name} mean"] == pytest.approx(0.0, abs=1e-6)
    t1 = pd.read_csv(tmp_path / "report" / "table1_pcd.csv").set_index("sequence")
    assert t1.loc[far.name, "midas (external, no adaptation) mean"] == pytest.approx(100.0)


def test_cli_missing_frame_is_one_red_line(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", lambda g: g)
    (preds / "0.000000.npy").unlink()
    r = runner.invoke(app, ["eval-depth", str(far), str(preds), "--name", "m", "--out", str(tmp_path / "res")])
    assert r.exit_code == 1
    assert "Traceback" not in r.output
    assert "no prediction for frame 0 (rgb/0.000000.png" in r.output



def test_external_result_sits_in_the_same_table_as_runs_of_the_same_config(far: Path, tmp_path: Path) -> None:
    """config.yaml is the resolved config (not the model's settings), so report groups it with our runs."""
    from mutualslam_cli.config import to_dict
    from mutualslam_cli.report.paper import paper_tables
    from mutualslam_cli.report.tables import collect
    from mutualslam_cli.results.run_folder import run_dir, write_json, write_yaml
    from mutualslam_cli.results.summary import Summary

    out = tmp_path / "res"
    eval_depth(far, predict(far, tmp_path / "p", lambda g: 2.0 * g), "ext", "depth", out=out)
    ours = run_dir(out, far.name, "replay+ewc", 0)  # a run of ours, as mslam run leaves it
    write_yaml(ours / "config.yaml", to_dict(load_config()))
    s = Summary()
    for key, v in (("depth.pcd.lsq.pretrained", 40.0), ("depth.pcd.lsq.adapted", 55.0)):
        s.set(key, v)
    s.set("sequence.name", far.name)
    s.set("scheme", "replay+ewc")
    s.set("seed", 0)
    write_json(ours / "summary.json", s.to_dict())
    runs = collect([out])
    assert set(runs["config"]) == {""}
    (t1,) = [t for t in paper_tables(runs) if t.name.startswith("table1_pcd")]
    row = t1.display.set_index("Sequence").loc[far.name]
    assert (row["Pre-trained"], row["Ours"], row["ext (external, no adaptation)"]) == ("40.00", "55.00", "100.00")


def test_a_frame_without_a_fit_is_null_with_a_reason_not_zero(far: Path, tmp_path: Path) -> None:
    preds = predict(far, tmp_path / "p", relative_inverse)
    write(preds / "0.033333.npy", np.full((48, 64), 0.4))  # constant: no scale-and-shift fit
    r = eval_depth(far, preds, "m", "relative-inverse", out=tmp_path / "res")
    pf = pd.read_csv(r.folder / "per_frame.csv")
    assert pf.loc[1, ["adapted_pcd_lsq", "adapted_esi", "adapted_align_scale"]].isna().all()
    assert r.summary.get("depth.pcd.lsq.adapted") == pytest.approx(100.0)  # the mean of the other 5
    assert r.summary.notes["depth.pcd.lsq.adapted"].startswith("1 of 6 frames have no score")

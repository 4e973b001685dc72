"""The command line: one-line errors with exit code 1, and the commands that need no network."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.errors import ConfigError, GeometryError, ShapeError, TransitionError

runner = CliRunner()


def _one_line_error(result, *needles: str) -> None:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    text = " ".join(lines)
    assert text.startswith("error:"), result.output
    for n in needles:
        assert n in text, (n, result.output)


@pytest.fixture
def tum_dir(tmp_path: Path) -> Path:
    return make_tum_dir(tmp_path, scene="room", n=6, width=64, height=48)


def test_check_good_folder(tum_dir: Path):
    r = runner.invoke(app, ["datasets", "check", str(tum_dir)])
    assert r.exit_code == 0, r.output
    assert "6" in r.output
    assert "100.0 %" in r.output


def test_missing_rgb_txt(tum_dir: Path):
    (tum_dir / "rgb.txt").unlink()
    r = runner.invoke(app, ["datasets", "check", str(tum_dir)])
    _one_line_error(r, "rgb.txt")


def test_malformed_gt_line(tum_dir: Path):
    gt = tum_dir / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    idx = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    lines[idx + 1] = "0.1 1.0 2.0 oops"
    gt.write_text("\n".join(lines) + "\n")
    r = runner.invoke(app, ["datasets", "check", str(tum_dir)])
    _one_line_error(r, "groundtruth.txt", f":{idx + 2}")


def test_8bit_depth_png(tum_dir: Path):
    first = sorted((tum_dir / "depth").iterdir())[0]
    cv2.imwrite(str(first), np.full((48, 64), 100, np.uint8))
    r = runner.invoke(app, ["datasets", "check", str(tum_dir)])
    _one_line_error(r, first.name, "16-bit")


def test_no_gt_overlap(tum_dir: Path):
    gt = tum_dir / "groundtruth.txt"
    out = []
    for ln in gt.read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            out.append(ln)
            continue
        f = ln.split()
        out.append(" ".join([f"{float(f[0]) + 1000:.6f}", *f[1:]]))
    gt.write_text("\n".join(out) + "\n")
    r = runner.invoke(app, ["datasets", "check", str(tum_dir)])
    _one_line_error(r, "no GT overlap")


def test_datasets_sub_commands_have_their_own_help():
    """``mslam datasets download --help`` is download's, not the group's; ``check`` has no download options."""
    def shown(*words: str) -> str:
        r = runner.invoke(app, [*words, "--help"], env={"COLUMNS": "100"})
        assert r.exit_code == 0, r.output
        return r.output

    out = shown("datasets", "download")
    assert "datasets download" in out
    assert "Fetch, verify and unpack" in out
    for opt in ("--base-url", "--force", "--max-unpack-gb", "--sample", "--registry", "--data-root", "--config",
                "--set"):
        assert opt in out, opt
    out = shown("datasets", "check")
    assert "--sample" in out
    assert "--registry" in out
    assert "--base-url" not in out
    out = shown("datasets")
    for sub in ("list", "check", "download"):
        assert f"│ {sub} " in out, (sub, out)


def test_run_missing_folder(tmp_path: Path):
    r = runner.invoke(app, ["run", str(tmp_path / "nope"), "--out", str(tmp_path / "res")])
    _one_line_error(r)


def test_run_unknown_scheme(tum_dir: Path, tmp_path: Path):
    r = runner.invoke(app, ["run", str(tum_dir), "--scheme", "bogus", "--out", str(tmp_path / "res")])
    _one_line_error(r, "replay+ewc")


def test_device_option_is_checked_before_any_work(tum_dir: Path, tmp_path: Path, monkeypatch):
    import torch

    r = runner.invoke(app, ["run", str(tum_dir), "--device", "gpu", "--out", str(tmp_path / "res")])
    _one_line_error(r, "cuda:N")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    r = runner.invoke(app, ["run", str(tum_dir), "--device", "cuda", "--out", str(tmp_path / "res")])
    _one_line_error(r, "CUDA is not available")
    assert not (tmp_path / "res").exists() or not any((tmp_path / "res").rglob("summary.json"))


def test_bad_set_override(tum_dir: Path):
    r = runner.invoke(app, ["run", str(tum_dir), "--set", "adapt.lr=abc"])
    _one_line_error(r, "adapt.lr")


def test_ate_command(tmp_path: Path):
    ts = np.arange(20) / 30.0
    pos = np.round(np.c_[np.cos(ts), np.sin(ts), ts], 3)  # exactly representable in the 6-decimal files
    rows = [f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1" for t, (x, y, z) in zip(ts, pos)]
    (tmp_path / "ref.txt").write_text("\n".join(rows) + "\n")
    est = [f"{t:.6f} {2 * x + 1:.6f} {2 * y:.6f} {2 * z:.6f} 0 0 0 1" for t, (x, y, z) in zip(ts, pos)]
    (tmp_path / "est.txt").write_text("\n".join(est) + "\n")
    r = runner.invoke(app, ["ate", str(tmp_path / "ref.txt"), str(tmp_path / "est.txt")])
    assert r.exit_code == 0, r.output
    assert "0.000000" in r.output
    assert "0.500000" in r.output
    r = runner.invoke(app, ["ate", str(tmp_path / "ref.txt"), str(tmp_path / "est.txt"), "--align", "none"])
    assert r.exit_code == 0
    assert "0.000000 " not in r.output.split("none")[1][:40]
    r = runner.invoke(app, ["ate", str(tmp_path / "ref.txt"), str(tmp_path / "missing.txt")])
    _one_line_error(r, "missing.txt")



def _ate_files(tmp_path: Path) -> tuple[str, str]:
    rng = np.random.default_rng(1)
    ts = np.arange(30) / 30.0
    pos = np.c_[np.cos(ts), np.sin(ts), ts]
    est = 0.5 * pos + rng.normal(scale=0.01, size=pos.shape)
    for name, p in (("ref.txt", pos), ("est.txt", est)):
        rows = [f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1" for t, (x, y, z) in zip(ts, p)]
        (tmp_path / name).write_text("\n".join(rows) + "\n")
    return str(tmp_path / "ref.txt"), str(tmp_path / "est.txt")


def test_ate_json_prints_the_table_numbers(tmp_path: Path):
    ref, est = _ate_files(tmp_path)
    table = runner.invoke(app, ["ate", ref, est])
    assert table.exit_code == 0, table.output
    cells = next(ln for ln in table.stdout.splitlines() if "sim3" in ln).strip("│ ").split("│")
    r = runner.invoke(app, ["ate", ref, est, "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)  # the whole of stdout is one JSON object
    assert set(d) == {"ref", "est", "align", "max_dt_s", "pairs", "scale", "ate_rmse_m", "ate_mean_m",
                      "ate_median_m", "ate_max_m"}
    assert [str(d["pairs"]), d["align"]] + [f"{d[k]:.6f}" for k in ("scale", "ate_rmse_m", "ate_mean_m",
                                                                     "ate_median_m", "ate_max_m")] \
        == [c.strip() for c in cells]
    assert d["pairs"] == 30
    assert d["ate_rmse_m"] > 0.001
    assert d["scale"] == pytest.approx(2.0, rel=0.05)
    assert d["max_dt_s"] == 0.02
    assert d["ref"] == ref
    none = json.loads(runner.invoke(app, ["ate", ref, est, "--json", "--align", "none"]).stdout)
    assert none["align"] == "none"
    assert none["scale"] == 1.0
    assert none["ate_rmse_m"] > d["ate_rmse_m"]


def _wide_runs(root: Path) -> None:
    """Two hand-made complete runs whose depth table is wider than 80 columns."""
    from mutualslam_cli.results.run_folder import run_dir, write_json
    from mutualslam_cli.results.summary import Summary

    for seq in ("a_rather_long_sequence_name", "another_long_sequence_name"):
        folder = run_dir(root, seq, "replay+ewc", 0)
        folder.mkdir(parents=True)
        s = Summary()
        for k, v in (("sequence.name", seq), ("scheme", "replay+ewc"), ("seed", 0),
                     ("depth.pcd.lsq.pretrained", 21.5), ("depth.pcd.lsq.adapted", 40.25),
                     ("depth.pcd.median.pretrained", 22.0), ("depth.pcd.median.adapted", 37.5),
                     ("depth.esi.pretrained", 0.34), ("depth.esi.adapted", 0.22)):
            s.set(k, v)
        write_json(folder / "summary.json", s.to_dict())


@pytest.fixture
def fresh_console(monkeypatch):
    """The CLI's console made anew under the test's environment (it is made once, at import)."""
    import mutualslam_cli.cli.common as cli

    for var in ("COLUMNS", "FORCE_COLOR", "TTY_COMPATIBLE"):
        monkeypatch.delenv(var, raising=False)

    def make() -> None:
        monkeypatch.setattr(cli, "console", cli._Console(stderr=False))

    assert isinstance(cli.console, cli._Console)
    return make


def test_piped_report_tables_are_not_wrapped_at_80_columns(tmp_path: Path, fresh_console):
    _wide_runs(tmp_path / "runs")
    fresh_console()
    r = runner.invoke(app, ["report", str(tmp_path / "runs"), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    header = next(ln for ln in r.stdout.splitlines() if "PCD lsq pre" in ln)
    assert len(header) > 100
    for col in ("sequence", "scheme", "PCD lsq adapt", "PCD med adapt", "e_si pre", "e_si adapt", "seeds"):
        assert col in header, (col, header)
    assert any("a_rather_long_sequence_name" in ln and "40.25" in ln for ln in r.stdout.splitlines())  # as in report.md


def test_report_prints_brackets_as_text(tmp_path: Path, fresh_console):
    """A name in brackets ("[vo.inject_outliers=0.1]" names a config group) is text, not rich markup."""
    from mutualslam_cli.results.run_folder import run_dir, write_json
    from mutualslam_cli.results.summary import Summary

    folder = run_dir(tmp_path / "runs", "room[v2]", "replay+ewc", 0)
    folder.mkdir(parents=True)
    s = Summary()
    for k, v in (("sequence.name", "room[v2]"), ("scheme", "replay+ewc"), ("seed", 0),
                 ("depth.pcd.lsq.pretrained", 21.5), ("depth.pcd.lsq.adapted", 40.25)):
        s.set(k, v)
    write_json(folder / "summary.json", s.to_dict())
    fresh_console()
    r = runner.invoke(app, ["report", str(tmp_path / "runs"), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "room[v2]" in r.stdout


def test_columns_env_sets_the_piped_width(tmp_path: Path, fresh_console, monkeypatch):
    _wide_runs(tmp_path / "runs")
    monkeypatch.setenv("COLUMNS", "90")
    fresh_console()
    r = runner.invoke(app, ["report", str(tmp_path / "runs"), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert max(len(ln) for ln in r.stdout.splitlines()) <= 90

def test_synth_command(tmp_path: Path):
    r = runner.invoke(app, ["synth", str(tmp_path / "s"), "--scene", "planar", "--frames", "3", "--size", "64x48"])
    assert r.exit_code == 0, r.output
    assert len(list((tmp_path / "s" / "rgb").iterdir())) == 3
    r = runner.invoke(app, ["synth", str(tmp_path / "t"), "--scene", "cave", "--frames", "3", "--size", "64x48"])
    _one_line_error(r, "room")


@pytest.mark.parametrize("exc", [ConfigError("adapt.lr: bad"), GeometryError("degenerate")])
def test_boundary_turns_user_errors_into_one_line_and_exit_1(exc, tum_dir: Path, tmp_path: Path, monkeypatch):
    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr("mutualslam_cli.pipeline.run_sequence", fail)
    _one_line_error(runner.invoke(app, ["run", str(tum_dir), "--out", str(tmp_path / "res")]), str(exc))


@pytest.mark.parametrize("exc", [ShapeError("x: expected shape [3], got (2,)"), TransitionError("bug"),
                                 KeyError("bug")])
def test_boundary_lets_bugs_through(exc, tum_dir: Path, tmp_path: Path, monkeypatch):
    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr("mutualslam_cli.pipeline.run_sequence", fail)
    r = runner.invoke(app, ["run", str(tum_dir), "--out", str(tmp_path / "res")])
    assert isinstance(r.exception, type(exc))
    assert r.exit_code != 0


def test_every_command_is_behind_the_one_boundary():
    """No command carries its own try/except for MslamError: the group's ``invoke`` is the boundary."""
    import inspect

    from mutualslam_cli.cli import data, grid, run

    for mod in (data, grid, run):
        assert "except MslamError" not in inspect.getsource(mod), mod.__name__


def test_shape_error_in_a_command_keeps_its_traceback(tum_dir: Path, tmp_path: Path, monkeypatch):
    def boom(*args, **kwargs):
        raise ShapeError("Trajectory.poses: expected shape [3, 4, 4], got (3, 3, 3)")

    monkeypatch.setattr("mutualslam_cli.pipeline.run_sequence", boom)
    r = runner.invoke(app, ["run", str(tum_dir), "--out", str(tmp_path / "res")])
    assert isinstance(r.exception, ShapeError), r.output
    assert not r.output.lstrip().startswith("error:")
    assert r.exc_info is not None
    assert r.exc_info[2] is not None

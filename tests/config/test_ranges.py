"""Every value of a run config is checked once, before any work, against the range declared beside its field:
a refusal names the key, the value and what was expected (issue 48, kind 1)."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import AdaptConfig, RunConfig, load_config, with_overrides
from mutualslam_cli.config.checks import RULE, check_config
from mutualslam_cli.errors import ConfigError

runner = CliRunner()


def _sections() -> list[tuple[str, type]]:
    hints = typing.get_type_hints(RunConfig)
    return [("", RunConfig)] + [(f.name, hints[f.name]) for f in dataclasses.fields(RunConfig)
                                if dataclasses.is_dataclass(hints[f.name])]


def test_every_number_of_every_section_has_its_range_beside_it():
    """A new int or float field without a rule would be accepted at any value (inf, 0, -1): this fails then."""
    missing = []
    for name, cls in _sections():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            numeric = tp in (int, float) or int in typing.get_args(tp) or float in typing.get_args(tp)
            if numeric and RULE not in f.metadata:
                missing.append(f"{name}.{f.name}" if name else f.name)
    assert not missing, f"fields without a range: {missing}"


@pytest.mark.parametrize(("override", "message"), [
    ("adapt.lr=.inf", "adapt.lr = inf: expected a finite number > 0"),
    ("adapt.lr=-.inf", "adapt.lr = -inf: expected a finite number > 0"),
    ("adapt.lr=1e999", "adapt.lr = inf: expected a finite number > 0"),
    ("eval.stride=0", "eval.stride = 0: expected an integer ≥ 1 (frames)"),
    ("eval.pcd_threshold=.inf", "eval.pcd_threshold = inf: expected a finite number > 0"),
    ("eval.max_depth=.nan", "eval.max_depth = nan: expected a finite number"),
    ("seed=-1", "seed = -1: expected an integer in [0, 4294967295]"),
    ("seed=4294967296", "seed = 4294967296: expected an integer in [0, 4294967295]"),
    ("seed=18446744073709551616", "seed = 18446744073709551616: expected an integer in [0, 4294967295]"),
    ("vo.max_fts=99999999999", "vo.max_fts = 99999999999: expected an integer ≤ 2147483647"),
    ("vo.max_fts=20", "vo.max_fts = 20: expected ≥ min_tracked (30)"),
    ("adapt.replay_capacity=2", "adapt.replay_capacity = 2: expected 0 or an integer ≥ 3"),
    ("adapt.train_width=1024", "adapt.train_width = 1024: expected ≤ net.width (640"),
    ("net.width=0", "net.width = 0: expected a multiple of 32 in [32, 8192]"),
    ("ba.image_scale=0", "ba.image_scale = 0.0: expected a number in (0, 1]"),
    ("dense.depth_max=0.05", "dense.depth_min = 0.1: expected < depth_max (0.05)"),
    ("experiment.seeds=[0, -3]", "experiment.seeds[1] = -3: expected an integer in [0, 4294967295]"),
    ("experiment.seeds=[1, 1]", "experiment.seeds = [1, 1]: expected no seed named twice"),
    ("experiment.variants={.hidden: []}", "experiment.variants = {'.hidden': []}: expected labels that are folder"),
    ("device=gpu", "device = 'gpu': expected one of auto, cpu, cuda, cuda:N"),
    ("out=''", "out = '': expected a non-empty string"),
    ("threads=100000", "threads = 100000: expected an integer in [0, 4096]"),
])
def test_a_value_out_of_its_range_is_refused_naming_key_value_and_expectation(override, message):
    with pytest.raises(ConfigError) as e:
        load_config(None, [override])
    assert str(e.value).startswith(message), str(e.value)


def test_a_config_file_is_checked_as_set_is(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("eval:\n  pcd_threshold: .inf\n")
    with pytest.raises(ConfigError, match=r"^eval.pcd_threshold = inf: expected a finite number > 0"):
        load_config(f)
    f.write_text("eval:\n  stride: 0\n")
    with pytest.raises(ConfigError, match=r"^eval.stride = 0"):
        load_config(f)


def test_overrides_made_in_code_are_checked_too():
    with pytest.raises(ConfigError, match=r"^seed = 18446744073709551616"):
        with_overrides(RunConfig(), seed=2**64)


def test_records_built_in_code_are_checked_by_the_same_rules():
    with pytest.raises(ConfigError, match=r"^adapt.luo_window = 1: expected an integer ≥ 2"):
        check_config(AdaptConfig(luo_window=1), "adapt")
    with pytest.raises(ConfigError, match=r"^adapt.labels = 'later': expected one of \['causal', 'hindsight'\]"):
        check_config(AdaptConfig(labels="later"), "adapt")  # type: ignore[arg-type]
    check_config(RunConfig())  # the defaults are inside every range


def test_every_shipped_config_is_inside_the_ranges():
    from mutualslam_cli.book.spec import load_book
    from mutualslam_cli.config import CONFIG_DIR

    for f in sorted(CONFIG_DIR.glob("*.yaml")):
        if f.name.startswith("book"):  # a results book (mslam book), not a run config: its own reader
            for g in load_book(f).grids.values():
                for sets in g.variants.values():
                    load_config(CONFIG_DIR.parent / g.preset, list(g.sets) + list(sets))
        else:
            load_config(f)


@pytest.fixture
def tum_dir(tmp_path: Path) -> Path:
    return make_tum_dir(tmp_path, scene="room", n=6, width=64, height=48)


@pytest.mark.parametrize(("args", "needle"), [
    (["--set", "adapt.lr=.inf"], "adapt.lr = inf: expected a finite number > 0"),
    (["--set", "seed=-1"], "seed = -1: expected an integer in [0, 4294967295]"),
    (["--seed", "18446744073709551616"], "seed = 18446744073709551616"),
    (["--set", "eval.stride=0"], "eval.stride = 0"),
])
def test_cli_refuses_in_one_line_before_any_work(tum_dir: Path, tmp_path: Path, args, needle):
    out = tmp_path / "res"
    r = runner.invoke(app, ["run", str(tum_dir), "--out", str(out), *args])
    assert r.exit_code == 1, r.output
    assert ("Traceback" not in r.output and r.exception is None) or isinstance(r.exception, SystemExit)
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1, r.output
    assert lines[0].startswith("error:"), r.output
    assert needle in lines[0], r.output
    assert not out.exists()  # nothing written: refused before any work

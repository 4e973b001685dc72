"""A YAML file a user wrote is read strictly: a key given twice, an alias bomb, a top level that is not a
mapping, text that is not UTF-8 and a path that is not a file are each refused in one line naming the file
(issue 48, kind 2)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.config import RunConfig, load_config
from mutualslam_cli.config.yaml_file import ALIAS_BUDGET, parse_yaml, read_yaml_mapping
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.errors import ConfigError, DatasetError

runner = CliRunner()

BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{b}: &{b} [{', '.join([f'*{a}'] * 9)}]\n" for a, b in zip("abcdefgh", "bcdefghi"))


def test_a_key_given_twice_is_refused_with_both_lines(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("adapt:\n  steps_per_keyframe: 2\nseed: 0\nadapt:\n  steps_per_keyframe: 8\n")
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert str(e.value) == (f"{f}:4: key 'adapt' is given twice in one mapping (first on line 1); "
                            "the second would silently replace the first")


def test_a_key_given_twice_inside_a_section_is_refused(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("vo:\n  max_fts: 100\n  max_fts: 200\n")
    with pytest.raises(ConfigError, match=rf"^{f}:3: key 'max_fts' is given twice"):
        load_config(f)


def test_a_merge_key_may_be_overridden():
    assert parse_yaml("base: &b {x: 1, y: 2}\nuse:\n  <<: *b\n  x: 3\n", "t") == \
        {"base": {"x": 1, "y": 2}, "use": {"x": 3, "y": 2}}


def test_an_alias_bomb_is_refused_at_once(tmp_path: Path):
    f = tmp_path / "bomb.yaml"
    f.write_text(BOMB)
    t = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert time.perf_counter() - t < 2.0
    assert str(e.value).startswith(f"{f}:")
    assert f"more than {ALIAS_BUDGET} aliases" in str(e.value)
    assert parse_yaml("a: &a 1\nb: [*a, *a]\n", "t") == {"a": 1, "b": [1, 1]}  # a few aliases are fine


def test_an_alias_bomb_in_a_set_value_is_refused():
    bomb = "[" + ", ".join(["&a [1]"] + ["*a"] * (ALIAS_BUDGET + 1)) + "]"
    with pytest.raises(ConfigError, match=r"^--set 'experiment.seeds=.*more than 16 aliases"):
        load_config(None, [f"experiment.seeds={bomb}"])


@pytest.mark.parametrize(("text", "what"), [("- 1\n- 2\n", "list"), ("42\n", "int"), ("just words\n", "str")])
def test_a_top_level_that_is_not_a_mapping_is_refused(tmp_path: Path, text, what):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert str(e.value) == f"{f}: expected a mapping (key: value lines) at the top of the YAML config file, got {what}"


def test_an_empty_file_is_the_defaults(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("# nothing but a comment\n")
    assert load_config(f) == RunConfig()  # the dataclass defaults: the paper's values


def test_text_that_is_not_utf8_is_refused_naming_the_byte(tmp_path: Path):
    f = tmp_path / "latin1.yaml"
    f.write_bytes("adapt:\n  scheme: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert str(e.value) == f"{f}: not UTF-8 text (byte 0xe9 at offset 20); save it as UTF-8"


def test_a_folder_or_a_pipe_is_not_a_config_file(tmp_path: Path):
    with pytest.raises(ConfigError, match=rf"^{tmp_path}: is a folder, not a YAML config file$"):
        load_config(tmp_path)
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match=r"pipe.yaml: not a regular file"):
        load_config(fifo)  # never opened: reading a pipe would wait for a writer
    with pytest.raises(ConfigError, match=r"missing.yaml: not found"):
        load_config(tmp_path / "missing.yaml")


def test_the_dataset_registry_is_read_by_the_same_reader(tmp_path: Path):
    make_tum_dir(tmp_path / "seqs", scene="room", n=4, width=64, height=48)
    reg = tmp_path / "datasets.yaml"
    reg.write_text("datasets:\n  a: {root: ./seqs, format: tum}\n  a: {root: ./other, format: tum}\n")
    with pytest.raises(DatasetError, match=rf"^{reg}:3: key 'a' is given twice"):
        load_sequence("a", registry_path=reg)
    reg.write_bytes(b"datasets:\n  a: {root: ./s\xff, format: tum}\n")
    with pytest.raises(DatasetError, match=r"not UTF-8 text \(byte 0xff"):
        load_sequence("a", registry_path=reg)


def test_the_reader_raises_the_callers_error_class(tmp_path: Path):
    f = tmp_path / "x.yaml"
    f.write_text("[1]\n")
    with pytest.raises(DatasetError, match="got list"):
        read_yaml_mapping(f, DatasetError)


@pytest.mark.parametrize(("make", "needle"), [
    (lambda d: d, "is a folder, not a YAML config file"),
    (lambda d: (d / "b.yaml").write_text(BOMB) and d / "b.yaml", "aliases"),
    (lambda d: (d / "d.yaml").write_text("seed: 1\nseed: 2\n") and d / "d.yaml", "key 'seed' is given twice"),
    (lambda d: (d / "u.yaml").write_bytes(b"seed: \xff\n") and d / "u.yaml", "not UTF-8 text"),
])
def test_cli_names_the_file_in_one_line(tmp_path: Path, make, needle):
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    path = make(cfg_dir)
    out = tmp_path / "res"
    r = runner.invoke(app, ["run", str(tmp_path / "no-such-seq"), "--config", str(path), "--out", str(out)])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 1, r.output
    assert len(lines) == 1, r.output
    assert lines[0].startswith(f"error: {path}"), r.output
    assert needle in lines[0], r.output
    assert not out.exists()


def test_a_camera_file_with_a_key_given_twice_is_refused_not_read_as_text(tmp_path: Path):
    from mutualslam_cli.datasets.recordings.camera_file import read_camera_file

    f = tmp_path / "cam.yaml"
    f.write_text("camera_matrix: {rows: 3, cols: 3, data: [500, 0, 32, 0, 500, 24, 0, 0, 1]}\n"
                 "camera_matrix: {rows: 3, cols: 3, data: [100, 0, 32, 0, 100, 24, 0, 0, 1]}\n")
    with pytest.raises(DatasetError, match=rf"^{f}: line 2: key 'camera_matrix' is given twice"):
        read_camera_file(f)

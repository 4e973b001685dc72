"""Result files: atomic writes, summary nulls with reasons, manifest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mutualslam_cli import results as res


def test_summary_absent_values_are_null_with_reason():
    s = res.Summary()
    s.set("depth.pcd.lsq.adapted", 71.5)
    s.set("map.esi.vo", float("nan"), "no map point has GT depth")
    d = s.to_dict()
    assert d["depth"]["pcd"]["lsq"]["adapted"] == 71.5
    assert d["map"]["esi"]["vo"] is None and d["notes"]["map.esi.vo"] == "no map point has GT depth"
    # Every required key exists; the unset ones are null with a reason, never 0.
    flat = res.flatten(d)
    for k in res.SUMMARY_KEYS:
        assert k in flat
        if k not in ("depth.pcd.lsq.adapted",):
            assert flat[k] is None and k in d["notes"]


def test_atomic_write_keeps_old_file_on_failure(tmp_path: Path, monkeypatch):
    p = tmp_path / "summary.json"
    res.write_json(p, {"a": 1})

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(res.os, "replace", boom)
    with pytest.raises(OSError):
        res.write_json(p, {"a": 2})
    assert json.loads(p.read_text()) == {"a": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["summary.json"]  # no temp file left behind


def test_json_is_plain(tmp_path: Path):
    p = tmp_path / "x.json"
    res.write_json(p, {"n": np.int64(3), "v": np.float32(0.5), "arr": np.arange(3), "bad": np.nan, "p": tmp_path})
    d = json.loads(p.read_text())
    assert d == {"n": 3, "v": 0.5, "arr": [0, 1, 2], "bad": None, "p": str(tmp_path)}


def test_manifest_records_versions_and_seed():
    m = res.manifest(["mslam", "run", "x"], 7, {"total_s": 1.0})
    assert m["seed"] == 7 and m["command"][1] == "run"
    assert "torch" in m["versions"] and "numpy" in m["versions"]


def test_run_dir_layout(tmp_path: Path):
    d = res.run_dir(tmp_path, "tum_fr1_xyz", "replay+ewc", 2)
    assert d == tmp_path / "tum_fr1_xyz" / "replay+ewc" / "seed2"
    assert not res.is_complete(d)


def test_atomic_writes_have_the_usual_permissions(tmp_path):
    """Result files are readable like any other output (mkstemp alone would leave them 0600)."""
    import stat

    from mutualslam_cli import atomic

    path = tmp_path / "x.txt"
    atomic.atomic_write_text(path, "hello")
    assert path.read_text() == "hello"
    plain = tmp_path / "plain.txt"
    with open(plain, "w") as f:  # what open() gives under this process's umask
        f.write("x")
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o666 & ~atomic._UMASK
    assert not list(tmp_path.glob(".x.txt.*"))  # no temporary file left behind

"""The schema of ``summary.json``: the writer refuses what it does not hold, readers read through it, old
files are read or refused by version, and every key the report, the book and the CLI read is in it."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
import yaml

import mutualslam_cli
from mutualslam_cli.config import load_config, to_dict
from mutualslam_cli.errors import SchemaError
from mutualslam_cli.results import schema
from mutualslam_cli.results.summary import SUMMARY_KEYS, RunSummary, Summary, flatten, read_summary

PACKAGE = Path(mutualslam_cli.__file__).parent
REPO = PACKAGE.parent
#: The modules that read summaries back: the report, the book, the CLI's tables, eval-depth.
READERS = [*sorted((PACKAGE / "report").glob("*.py")), *sorted((PACKAGE / "book").glob("*.py")),
           PACKAGE / "cli" / "run.py", PACKAGE / "cli" / "book.py", PACKAGE / "eval_depth.py"]
SECTIONS = ("depth.", "trajectory.", "vo.", "map.", "timing.", "ba.", "adaptation.", "loop.", "run.", "dense.",
            "sequence.", "external.")
FILE_ENDINGS = (".png", ".ply", ".json", ".csv", ".txt", ".yaml", ".pth", ".npz")


def unknown_keys(texts: list[str], config_keys: set[str]) -> list[str]:
    """The dotted strings among ``texts`` that look like summary keys (a section's prefix) but are neither in the
    schema nor a config key. A stem (``depth.pcd.lsq``, completed as ``f"{stem}.adapted"``) or a prefix ending in
    ``.`` needs some key under it."""
    out = []
    for t in texts:
        if not t.startswith(SECTIONS) or t.endswith(FILE_ENDINGS) or not t.replace(".", "").replace("_", "").isalnum():
            continue
        if t in config_keys or any(c.startswith(t) for c in config_keys if t.endswith(".")):
            continue
        if schema.field_of(t) is not None or schema.has_prefix(t if t.endswith(".") else t + "."):
            continue
        out.append(t)
    return out


def _literals(path: Path) -> list[str]:
    return [n.value for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Constant)
            and isinstance(n.value, str)]


def _config_keys() -> set[str]:
    return set(flatten(to_dict(load_config())))


def _book_keys(spec: dict) -> list[str]:
    """Every ``key:`` a book's tables and figures name (nested anywhere in the spec)."""
    out: list[str] = []

    def walk(x: object) -> None:
        if isinstance(x, dict):
            for k, v in x.items():
                if k in ("key", "keys", "y", "x") and isinstance(v, str):
                    out.append(v)
                elif k == "keys" and isinstance(v, list):
                    out.extend(str(s) for s in v)
                walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)

    walk(spec)
    return out


def test_every_key_a_reader_names_is_in_the_schema() -> None:
    config = _config_keys()
    bad = {str(p.relative_to(REPO)): unknown_keys(_literals(p), config) for p in READERS}
    assert not {k: v for k, v in bad.items() if v}


@pytest.mark.parametrize("book", sorted((REPO / "configs").glob("book*.yaml")), ids=lambda p: p.name)
def test_every_key_a_book_reads_is_in_the_schema(book: Path) -> None:
    keys = _book_keys(yaml.safe_load(book.read_text()))
    assert keys, "the book names no key: the walk above no longer finds them"
    assert not unknown_keys(keys, _config_keys())


def test_a_renamed_key_is_caught() -> None:
    assert unknown_keys(["depth.pcd.lsq.adapted", "depth.pcd.lsqq.adapted", "dense.gt_scale.", "vo.max_fts",
                         "depth.pcd.lsq", "depth.pcd_nonkf", "depth.pcd.lsqq", "map_vo.ply"],
                        {"vo.max_fts"}) == ["depth.pcd.lsqq.adapted", "depth.pcd.lsqq"]
    with pytest.raises(SchemaError, match="not in summary schema version 2"):
        Summary().set("depth.pcd.lsqq.adapted", 1.0)


def test_required_keys_are_declared_and_the_shipped_json_schema_is_current() -> None:
    assert all(schema.field_of(k) is not None for k in SUMMARY_KEYS)
    assert schema.SCHEMA_FILE.read_text() == schema.schema_text(), \
        "summary.schema.json is stale: python -m mutualslam_cli.results.schema"
    js = json.loads(schema.SCHEMA_FILE.read_text())
    assert js["properties"]["depth"]["properties"]["pcd"]["properties"]["lsq"]["properties"]["adapted"]["type"] == \
        ["number", "null"]
    assert js["properties"]["schema_version"] == {"const": schema.SCHEMA_VERSION}


def test_the_writer_checks_kinds_and_the_reader_types_values(tmp_path: Path) -> None:
    s = Summary()
    with pytest.raises(SchemaError, match=r"vo\.keyframes = 2\.5 is not a integer"):
        s.set("vo.keyframes", 2.5)
    with pytest.raises(SchemaError, match="is not a flag"):
        s.set("vo.from_cache", 1)
    s.set("vo.keyframes", 12)
    s.set("depth.pcd.lsq.adapted", 61.5)
    s.set("vo.from_cache", True)
    s.absent("trajectory.ate_rmse_m.ba", "global BA not run")
    (tmp_path / "summary.json").write_text(json.dumps(s.to_dict()))
    r = read_summary(tmp_path)
    assert r.version == 2
    assert r.integer("vo.keyframes") == 12
    assert r.number("vo.keyframes") == 12.0
    assert r.number("depth.pcd.lsq.adapted") == 61.5
    assert r.integer("depth.pcd.lsq.adapted") is None
    assert r.flag("vo.from_cache") is True
    assert r.number("trajectory.ate_rmse_m.ba") is None
    assert r.notes["trajectory.ate_rmse_m.ba"] == "global BA not run"
    with pytest.raises(SchemaError, match=r"asked for 'vo\.keyframe'"):
        r.get("vo.keyframe")
    assert r.nested() == s.to_dict()


def test_old_files_are_read_and_unknown_versions_refused(tmp_path: Path) -> None:
    old = {"vo": {"keyframes": 3, "retired_key": 1.0}, "notes": {}}  # version 1: no schema_version
    (tmp_path / "summary.json").write_text(json.dumps(old))
    r = read_summary(tmp_path)
    assert r.version == 1
    assert r.integer("vo.keyframes") == 3
    assert r.flat()["vo.retired_key"] == 1.0
    assert r.nested() == old
    for data, match in (({**old, "schema_version": 3}, "schema version 3; this mslam reads versions 1–2"),
                        ({**old, "schema_version": 2}, r"vo.retired_key' is not in summary schema version 2"),
                        ({"vo": {"keyframes": "3"}, "schema_version": 2}, "is not a integer")):
        (tmp_path / "summary.json").write_text(json.dumps(data))
        with pytest.raises(SchemaError, match=match) as e:
            read_summary(tmp_path)
        assert str(tmp_path / "summary.json") in str(e.value)
    with pytest.raises(SchemaError, match="not an object of metrics"):
        RunSummary.parse([1, 2], "x.json")

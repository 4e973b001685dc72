"""The front end's journal and its cache: data-only .npz (never pickle), exact round trips, a replica that
is the front end bit for bit; bad cache entries are recomputed."""

from __future__ import annotations

import dataclasses
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.map.journal import JOURNAL_VERSION, journal_from_arrays, journal_to_arrays
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.state import MapState
from mutualslam_cli.stages.frontend import run_frontend
from mutualslam_cli.vo.journal_cache import CHECKPOINT_EVERY, cache_path, load_entry, vo_cache_key
from mutualslam_cli.vo.source import FrontEndSource


def _cfg(mode: str):
    return load_config(CONFIG_DIR / "smoke.yaml", [f"vo.mode={mode}", "vo.max_fts=300"])


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return load_sequence(make_tum_dir(tmp_path_factory.mktemp("vo_cache"), scene="room", n=30, width=320, height=240))


@pytest.fixture(scope="module")
def results(seq) -> dict[str, VOResult]:
    """Real front-end results of every mode (``gt`` carries the svo meta nested in its own)."""
    out = {mode: run_frontend(seq, _cfg(mode))[0] for mode in ("svo", "gt", "gt-depth")}
    assert len(out["svo"].keyframes) >= 2
    assert len(out["svo"].points) > 50
    return out


def assert_same(a, b, where: str = "vo") -> None:
    """Equal values and types, recursively: arrays by dtype, shape and content (NaN equal to NaN)."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype, f"{where}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        assert a.shape == b.shape, f"{where}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict), f"{where}: keys {list(a)} vs {list(b)}"
        assert list(a) == list(b), f"{where}: keys {list(a)} vs {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b), f"{where}: {a!r} vs {b!r}"
        assert len(a) == len(b), f"{where}: {a!r} vs {b!r}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float), where
        assert np.isnan(b), where
    else:  # numbers may come back as Python numbers instead of numpy scalars
        assert a == b, f"{where}: {a!r} vs {b!r}"
        assert isinstance(a, (bool, np.bool_)) == isinstance(b, (bool, np.bool_)), f"{where}: {a!r} vs {b!r}"
        assert isinstance(a, str) == isinstance(b, str), where


# ----------------------------------------------------------------------------- the journal


@pytest.mark.parametrize("mode", ["svo", "gt", "gt-depth"])
def test_journal_round_trip_and_replay_give_the_front_end_bit_for_bit(seq, results, mode):
    """Every event survives the arrays (no pickle) exactly; a replica fed the events is the result."""
    source = FrontEndSource(seq, _cfg(mode))
    source.run_all()
    events = source.pure
    assert {e.kind for e in events} >= {"keyframe", "points", "frame"}
    back = journal_from_arrays(journal_to_arrays(events))
    assert len(back) == len(events)
    assert all(a.same(b) for a, b in zip(events, back))
    replica = MapState(source.state.intr, len(seq))
    for e in back:
        replica.apply(e)
    no_meta = {"meta": {}}
    assert_same(dataclasses.replace(source.result(), **no_meta), dataclasses.replace(replica.snapshot(seq.frames),
                                                                                   **no_meta))
    assert_same(dataclasses.replace(results[mode], **no_meta, covisibility=source.result().covisibility),
                dataclasses.replace(source.result(), **no_meta))


@pytest.mark.parametrize("mode", ["svo", "gt"])
def test_entry_is_data_only(seq, tmp_path, mode):
    vo, _ = run_frontend(seq, _cfg(mode), cache_dir=tmp_path)
    path = cache_path(tmp_path, seq, _cfg(mode))
    with np.load(path, allow_pickle=False) as z:  # every member loads without pickle
        kinds = {k: z[k].dtype.kind for k in z.files}
    assert "O" not in kinds.values()
    assert kinds["header"] == "u"
    resumable = mode == "svo" and len(vo.keyframes) >= CHECKPOINT_EVERY  # our VO's resumption points
    assert any(k.startswith("ck") for k in kinds) == resumable
    assert not list(tmp_path.glob(".*.tmp"))  # the atomic writer left no temporary file
    entry = load_entry(path)
    assert entry is not None
    assert entry.complete
    assert entry.meta["mode"] == ("svo" if mode == "svo" else "gt")


def test_second_run_replays_the_journal(seq, results, tmp_path):
    vo, cached = run_frontend(seq, _cfg("svo"), cache_dir=tmp_path)
    assert not cached
    assert cache_path(tmp_path, seq, _cfg("svo")).name.endswith(".journal.npz")
    again, cached = run_frontend(seq, _cfg("svo"), cache_dir=tmp_path)
    assert cached
    assert_same(vo, again)  # the journal replayed is the front end's map, bit for bit
    no_meta = {"meta": {}}  # meta holds timings
    assert_same(dataclasses.replace(results["svo"], **no_meta), dataclasses.replace(again, **no_meta))  # deterministic


# ----------------------------------------------------------------------------- invalid entries


def _rewrite(path: Path, change) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _wrong_version(path: Path) -> None:
    def change(a):
        a["header"] = np.frombuffer(bytes(a["header"]).replace(
            f'"version": {JOURNAL_VERSION}'.encode(), b'"version": 999'), np.uint8)
    _rewrite(path, change)


def _object_array(path: Path) -> None:
    def change(a):
        a["ev.frame"] = np.array([object()] * len(a["ev.frame"]), dtype=object)
    _rewrite(path, change)


def _plain_npy(path: Path) -> None:
    with open(path, "wb") as f:  # a file object: np.save would append ".npy" to the name
        np.save(f, np.arange(3))


def _disagreeing(path: Path) -> None:
    def change(a):
        a["ev.frame"] = a["ev.frame"][:-1]
    _rewrite(path, change)


@pytest.mark.parametrize(("spoil", "why"), [
    (lambda p: p.write_bytes(b"not an archive at all"), "BadZipFile|pickled|not an|Failed"),
    (lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), ""),
    (_wrong_version, "version 999"),
    (_object_array, "pickle"),
    (_plain_npy, ""),
    (_disagreeing, "disagree"),
])
def test_invalid_entry_is_recomputed_and_replaced(seq, results, tmp_path, caplog, spoil, why):
    cfg = _cfg("svo")
    path = cache_path(tmp_path, seq, cfg)
    run_frontend(seq, cfg, cache_dir=tmp_path)
    spoil(path)
    with caplog.at_level(logging.WARNING, logger="mutualslam_cli.vo.journal_cache"):
        vo, cached = run_frontend(seq, cfg, cache_dir=tmp_path)
    assert not cached
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1, warned
    assert str(path) in warned[0], warned
    assert "recomputing" in warned[0], warned
    assert why == "" or any(w in warned[0] for w in why.split("|")), warned[0]
    assert load_entry(path) is not None  # overwritten with a valid entry
    again, cached = run_frontend(seq, cfg, cache_dir=tmp_path)
    assert cached
    assert_same(vo, again)


# ----------------------------------------------------------------------------- old pickles


class _Payload:
    """Unpickling this creates a marker file: what a hostile cache entry could do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_old_pkl_entry_is_never_unpickled(seq, results, tmp_path, monkeypatch):
    cfg = _cfg("svo")
    old = tmp_path / f"{seq.name}-svo-{vo_cache_key(seq, cfg)}.pkl"
    marker = tmp_path / "code-ran"
    old.write_bytes(pickle.dumps(_Payload(marker)))

    def refuse(*args, **kwargs):
        raise AssertionError("the VO cache called pickle")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    _, cached = run_frontend(seq, cfg, cache_dir=tmp_path)  # no journal yet: recomputed, the .pkl ignored
    assert not cached
    assert not marker.exists()
    assert cache_path(tmp_path, seq, cfg).is_file()
    assert old.is_file()
    _, cached = run_frontend(seq, cfg, cache_dir=tmp_path)  # then the journal is used
    assert cached
    assert not marker.exists()


def test_a_grid_prepares_the_journal_its_jobs_read(seq, tmp_path):
    # the front end's output follows OpenCV's thread count (a journal of 2 threads, resumed by a job of 1, failed
    # its check at the first frame run again): the key names the count, and a grid's prepared front end is
    # run with its jobs' count, so they find it
    from mutualslam_cli.ablate import prepare_frontends
    from mutualslam_cli.config import with_overrides
    from mutualslam_cli.stages.context import use_threads

    cfg = _cfg("svo")
    assert vo_cache_key(seq, with_overrides(cfg, threads=1)) != vo_cache_key(seq, with_overrides(cfg, threads=2))
    prepare_frontends(with_overrides(cfg, threads=0), [str(seq.root)], [0], str(tmp_path), threads=1)
    job_cfg = use_threads(with_overrides(cfg, threads=1))
    entry = load_entry(cache_path(tmp_path / "_cache" / "vo", seq, job_cfg))
    assert entry is not None
    assert entry.complete

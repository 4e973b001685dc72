"""The map has one writer (:class:`~mutualslam_cli.map.state.MapState`): no module outside ``mutualslam_cli.map``
calls the store's private mutators or assigns into the store's arrays, and the map state's writers journal
exactly what the store does."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from mutualslam_cli.map.journal import Journal
from mutualslam_cli.map.state import MapState
from mutualslam_cli.map.store import Map
from mutualslam_cli.types import Intrinsics

ROOT = Path(__file__).resolve().parents[2] / "mutualslam_cli"
#: The store's fields (what a reader may read and only the map state may change).
FIELDS = {"kf_frame", "kf_time", "kf_T_wc", "kf_segment", "kf_points", "host", "px_h", "xn_h", "rho", "sigma",
          "obs", "Xw", "_wc", "_cw"}


def _mutators() -> set[str]:
    return {n for n in vars(Map) if n.startswith("_") and not n.startswith("__") and callable(vars(Map)[n])
            and n != "_emit"}


def _writes(path: Path) -> list[str]:
    """``line: what`` for each call of a store mutator and each assignment into ``<x>.map.<field>``."""
    out, mutators = [], _mutators()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in mutators:
            out.append(f"{node.lineno}: calls {node.func.attr}")
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
            node, (ast.AugAssign, ast.AnnAssign)) else []
        for t in targets:
            while isinstance(t, ast.Subscript):
                t = t.value
            if (isinstance(t, ast.Attribute) and t.attr in FIELDS and isinstance(t.value, ast.Attribute)
                    and t.value.attr == "map"):
                out.append(f"{node.lineno}: assigns map.{t.attr}")
    return out


def test_only_the_map_package_writes_the_store():
    assert len(_mutators()) >= 10
    outside = [p for p in sorted(ROOT.rglob("*.py")) if p.relative_to(ROOT).parts[0] != "map"]
    bad = [f"{p.relative_to(ROOT)}:{w}" for p in outside for w in _writes(p)]
    assert not bad, "the map written outside mutualslam_cli.map:\n" + "\n".join(bad)


def test_the_map_states_writers_journal_and_replay_bit_for_bit():
    intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    st = MapState(intr, 10, Journal())
    T = np.eye(4)
    T[0, 3] = 0.1
    k0, k1 = st.add_keyframe(0, 0.0, np.eye(4), 0), st.add_keyframe(5, 0.5, T, 0)
    px = np.array([[100.0, 90.0], [200.0, 150.0]])
    pids = st.add_points(np.array([k0, k0]), px, (px - [160, 120]) / 300, np.array([0.5, 0.25]), np.full(2, 0.01),
                         [{k0: px[0]}, {k0: px[1]}])
    st.observe(k1, pids, px + 1)
    st.set_depths(pids[:1], np.array([0.4]))
    st.refresh(pids[:1])
    st.remove_observations(pids[1:], np.array([k1]))
    st.remove_points(pids[1:])
    replica = MapState(intr, 10)
    for e in st.journal.events:
        replica.apply(e)
    assert [e.kind for e in st.journal.events] == ["keyframe", "keyframe", "points", "observe", "depth", "refresh",
                                                    "unobserve", "remove"]
    np.testing.assert_array_equal(replica.map.Xw, st.map.Xw)
    assert replica.map.obs[pids[0]].keys() == st.map.obs[pids[0]].keys()
    assert not replica.map.obs[pids[1]]

"""Merging a segment into the map before it (:mod:`mutualslam_cli.backend.merge`): a segment in a unit of its own
moves whole by the measured Sim(3); one a bridge already joined is corrected as a loop is; a segment merges once."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mutualslam_cli.backend.loop_closer import place_detector
from mutualslam_cli.backend.loop_detector import LoopClosure
from mutualslam_cli.backend.merge import SegmentMerger, merge_similarity
from mutualslam_cli.config import RunConfig
from mutualslam_cli.geometry import exp_so3, se3_inv
from mutualslam_cli.map.sim3 import Sim3
from mutualslam_cli.map.state import MapState
from mutualslam_cli.types import Intrinsics

INTR = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)


def _T_wc(yaw: float, centre) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([[0.0, yaw, 0.1]]))[0]
    T[:3, 3] = centre
    return T


def _state() -> MapState:
    """Segment 0: keyframes 0–2; segment 1 (after a loss): keyframes 3–4, in its own frame and unit."""
    st = MapState(INTR, 50)
    kfs = [(0, [0, 0, 0]), (0, [0.1, 0, 0]), (0, [0.2, 0, 0]), (1, [0, 0, 0]), (1, [0.05, 0, 0])]
    for k, (seg, c) in enumerate(kfs):
        if k in (0, 3):
            st.start_segment(seg, 10 * k, "homography")
        st.add_keyframe(10 * k, float(k), _T_wc(0.1 * k, c), seg)
    st.add_points(np.array([3, 4]), np.array([[100.0, 100.0], [200.0, 150.0]]), np.array([[0.1, 0.0], [-0.2, 0.1]]),
                  np.array([0.5, 0.25]), np.array([0.01, 0.01]), [{3: np.zeros(2)}, {4: np.zeros(2)}])
    return st


class Source:
    def __init__(self, state: MapState):
        self.state, self.settled, self.refined = state, 0, []

    def settle(self):
        self.settled += 1

    def transform_segment(self, segment, S, onto):
        self.state.transform_segment(segment, S, onto)

    def refine(self, r):
        self.refined.append(r)


def _merger(state: MapState, loop: LoopClosure | None, closer=None) -> SegmentMerger:
    seq = SimpleNamespace(intrinsics=INTR, load_gray=lambda f: np.zeros((240, 320), np.uint8))
    cfg, source = RunConfig(), Source(state)
    mg = SegmentMerger(seq, cfg.seed, source, place_detector(seq, cfg.vo, cfg.loop, source), closer)
    mg.detector.add = lambda kf, gray: mg.detector.index.images.add(kf, gray)
    asked = []

    def query(state, kf, gray, depth, seed=0, pool=None, newest=0):
        asked.append((kf, list(pool)))
        return loop if loop is not None and kf == loop.query else None

    mg.detector.query = query
    mg.asked = asked
    return mg


def test_the_similarity_puts_the_query_keyframe_on_the_verified_pose():
    T_new = se3_inv(_T_wc(0.3, [0.4, -0.1, 0.2]))
    T_o = se3_inv(_T_wc(-0.5, [2.0, 1.0, -1.0]))
    S = merge_similarity(T_new, LoopClosure(4, 1, T_o, 2.5, 100, 0.1, 50, 50))
    R, t, s = S.R, S.t, S.s
    T_wc = se3_inv(T_new)
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = R @ T_wc[:3, :3], s * R @ T_wc[:3, 3] + t
    np.testing.assert_allclose(moved, se3_inv(T_o), atol=1e-12)


def test_a_segment_of_its_own_moves_whole_onto_the_old_map_once():
    state = _state()
    T_o = se3_inv(_T_wc(0.7, [0.3, 0.2, 0.1]))
    mg = _merger(state, LoopClosure(4, 1, T_o, 2.0, 100, 0.1, 50, 50))
    X0 = state.map.Xw[[0, 1]].copy()
    depth_of = lambda kf: np.ones((8, 8))  # noqa: E731
    for kf in range(5):
        mg.after_keyframe(kf, depth_of, lambda ids: {})
    assert [a[0] for a in mg.asked] == [3, 4]  # segment 0 is the map: only the new segment's keyframes ask
    assert mg.asked[0][1] == [0, 1, 2]  # … and only about the keyframes before the segment
    np.testing.assert_allclose(state.pose(4), se3_inv(T_o), atol=1e-9)
    assert state.unit(1) == 0
    assert mg.merges[0].how == "similarity"
    # the hosted points moved with their keyframes, their distances from them ×2
    assert np.linalg.norm(state.map.Xw[1] - state.pose(4)[:3, 3]) == pytest.approx(
        2.0 * np.linalg.norm(X0[1] - _T_wc(0.4, [0.05, 0, 0])[:3, 3]))
    mg.after_keyframe(4, depth_of, lambda ids: {})
    assert len(mg.asked) == 2
    assert len(mg.merges) == 1


def test_after_a_merge_every_reader_sees_one_unit():
    """One answer to "which unit": the merged segment is in the old unit in the map state, in its snapshot (which the
    global BA, the scale-drift windows and the map's e_si read) and in the point units of the map's metrics."""
    from mutualslam_cli.metrics.slam import point_units
    from mutualslam_cli.types import FrameRef

    state = _state()
    mg = _merger(state, LoopClosure(4, 1, se3_inv(_T_wc(0.7, [0.3, 0.2, 0.1])), 2.0, 100, 0.1, 50, 50))
    before = state.snapshot([FrameRef(i, float(i), Path(f"{i}.png"), None) for i in range(50)])
    assert before.unit_of_segment() == {0: 0, 1: 1}
    for kf in range(5):
        mg.after_keyframe(kf, lambda kf: np.ones((8, 8)), lambda ids: {})
    vo = state.snapshot([FrameRef(i, float(i), Path(f"{i}.png"), None) for i in range(50)])
    assert state.unit(1) == 0
    assert vo.unit_of_segment() == {0: 0, 1: 0}
    assert set(point_units(vo, vo.unit_of_segment()).tolist()) == {0}


def test_a_bridged_segment_is_corrected_as_a_loop():
    state = _state()
    state.transform_segment(1, Sim3(np.eye(3), np.array([0.3, 0, 0]), 1.0), 0)  # a bridge joined it to segment 0
    loop = LoopClosure(4, 1, se3_inv(_T_wc(0.7, [0.3, 0.2, 0.1])), 1.2, 100, 0.1, 50, 50)
    calls = []
    closer = SimpleNamespace(close=lambda lp, d, v: calls.append(lp.query) or {"ba_nearby_targets": 3})
    mg = _merger(state, loop, closer)
    before = state.pose(3).copy()
    for kf in range(5):
        mg.after_keyframe(kf, lambda kf: np.ones((8, 8)), lambda ids: {})
    assert calls == [4]
    assert mg.merges[0].how == "pose graph + BA"
    np.testing.assert_array_equal(state.pose(3), before)  # not moved rigidly: the loop's pose graph does it

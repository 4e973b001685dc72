"""Relocalisation against a map (mutualslam_cli.vo.relocalise) and its use by the front end."""

from __future__ import annotations

import numpy as np
import pytest
from synth import make_sequence

from mutualslam_cli.geometry import se3_inv, to_normalized
from mutualslam_cli.map.state import MapState
from mutualslam_cli.map.store import Map
from mutualslam_cli.vo.features import detect_grid
from mutualslam_cli.vo.recovery import OLD_INLIER_PX, OLD_WITNESS_RATIO
from mutualslam_cli.vo.relocalise import RelocIndex, RelocSettings

W, H = 320, 240
THR = 2.0 / 250.0  # 2 px at the synthetic camera's focal length (~250 px at 320 px wide)


@pytest.fixture(scope="module")
def room():
    return make_sequence("room", n=60, width=W, height=H, seed=3)


def _gray(rgb: np.ndarray) -> np.ndarray:
    return (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]).astype(np.uint8)


def _map(seq, kf_frames: list[int]) -> tuple[Map, RelocIndex]:
    """A metric map with GT poses: keyframes at ``kf_frames``, map points from GT depth at grid corners."""
    K = seq.intrinsics.K()
    st, index = MapState(seq.intrinsics, len(seq)), RelocIndex(seq.intrinsics)
    for fi in kf_frames:
        k = st.add_keyframe(fi, float(seq.timestamps[fi]), seq.poses[fi], 0)
        gray = _gray(seq.rgb[fi])
        px = detect_grid(gray, 16, 300)
        z = seq.depth[fi][np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)]
        ok = z > 0
        px, z = px[ok], z[ok]
        st.add_points(np.full(len(z), k), px, to_normalized(px, K), 1.0 / z, np.zeros(len(z)), [{k: p} for p in px])
        index.add_keyframe(k, gray)
    return st.map, index


def _pose_error(T_cw: np.ndarray, T_wc_gt: np.ndarray) -> tuple[float, float]:
    """Position (map units = metres here) and rotation (degrees) error of an estimate."""
    D = T_cw @ T_wc_gt
    ang = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(se3_inv(T_cw)[:3, 3] - T_wc_gt[:3, 3])), float(ang)


@pytest.mark.parametrize("query", [27, 41])
def test_relocalisation_recovers_the_pose_of_an_unseen_frame(room, query):
    """A frame between keyframes (no motion prior, no previous frame) is found within 1 cm and 0.5°."""
    m, index = _map(room, [0, 10, 20, 30, 40, 50])
    r = index.query(_gray(room.rgb[query]), m, THR, seed=query)
    assert r is not None
    dt, dr = _pose_error(r.T_cw, room.poses[query])
    assert dt < 0.01, (dt, dr)
    assert dr < 0.5, (dt, dr)
    assert r.inliers >= index.settings.min_inliers
    assert len(r.pids) == r.inliers
    assert r.raw.shape == (r.inliers, 2)
    assert index.rejected == 0


def test_a_frame_of_another_place_is_not_relocalised(room):
    """No candidate of this room explains a frame of another scene: None, nothing accepted."""
    m, index = _map(room, [0, 10, 20, 30, 40, 50])
    other = make_sequence("far", n=2, width=W, height=H, seed=1)
    assert index.query(_gray(other.rgb[1]), m, THR, seed=0) is None


def test_a_planted_wrong_candidate_is_rejected(room):
    """The only candidate offered carries another keyframe's image under its map points: its matches
    give a pose that the verification refutes (or no pose at all), never an accepted relocalisation."""
    m, index = _map(room, [0, 30])
    index.images[1], index.features[1], index.thumbs[1] = index.images[0], index.features[0], index.thumbs[0]
    assert index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[1]) is None
    m2, honest = _map(room, [0, 30])
    r = honest.query(_gray(room.rgb[31]), m2, THR, seed=0, keyframes=[1])  # the same query, honest candidate
    assert r is not None
    assert _pose_error(r.T_cw, room.poses[31])[0] < 0.01


def test_a_wrong_candidate_no_other_keyframe_can_witness_is_refused(room):
    """A keyframe with no other keyframe in the map, carrying another frame's image under its points: its
    matches are all consistent with one wrong pose (14 cm / 6.7° off before), which only another keyframe's
    own image could refute — with none, the pose is refused, and counted."""
    m, index = _map(room, [30])
    index.add_keyframe(0, _gray(room.rgb[0]))  # its image and features now those of frame 0
    assert index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[0]) is None
    assert index.rejected == 1
    m, index = _map(room, [30, 34])  # a witness (honest images) refutes the same planted pose
    index.add_keyframe(0, _gray(room.rgb[0]))
    assert index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[0]) is None
    assert index.rejected == 1
    r = _map(room, [30, 34])[1].query(_gray(room.rgb[31]), _map(room, [30, 34])[0], THR, seed=0, keyframes=[0])
    assert r is not None
    assert _pose_error(r.T_cw, room.poses[31])[0] < 0.01


def test_the_halves_are_halves_of_the_inliers(room, monkeypatch):
    """Outlying matches do not take part in the halves' test: each half's pose is fitted to inliers only."""
    import mutualslam_cli.vo.relocalise as rl

    m, index = _map(room, [20, 30, 40])
    sizes = []
    fit = rl.estimate_pose

    def spy(X, xn, *a, **k):
        sizes.append(len(X))
        return fit(X, xn, *a, **k)

    monkeypatch.setattr(rl, "estimate_pose", spy)
    r = index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[1])
    assert r is not None
    first, halves = sizes[0], sizes[1:3]  # the PnP on every match, then one pose per half
    assert sum(halves) == r.inliers <= first
    assert abs(halves[0] - halves[1]) <= 1


def test_images_decoded_again_relocalise_as_held_ones_and_are_not_kept(room):
    """A long sequence keeps no keyframe image in the index: each is decoded again when a query needs it (the
    same pixels), and the relocalisation is the one the held images give."""
    m, held = _map(room, [0, 30])
    frames = {k: fi for k, fi in enumerate([0, 30])}
    decoded = []
    lazy = RelocIndex(room.intrinsics, load=lambda k: decoded.append(k) or _gray(room.rgb[frames[k]]))
    for k in (0, 1):
        lazy.add_keyframe(k, _gray(room.rgb[frames[k]]))
    assert all(v is None for v in lazy.images._held.values())  # ids only
    a = held.query(_gray(room.rgb[31]), m, THR, seed=0)
    b = lazy.query(_gray(room.rgb[31]), m, THR, seed=0)
    assert a is not None
    assert b is not None
    assert decoded
    np.testing.assert_array_equal(a.T_cw, b.T_cw)
    np.testing.assert_array_equal(a.pids, b.pids)
    with pytest.raises(TypeError):
        lazy.images[0] = _gray(room.rgb[1])


def _old_map_settings() -> RelocSettings:
    """The front end's second, old-map query (vo/recovery.py) at this test's 2 px threshold."""
    return RelocSettings(inlier_factor=OLD_INLIER_PX / 2.0, witness_ratio=OLD_WITNESS_RATIO)


def test_the_old_map_query_still_refuses_wrong_places(room):
    """The old-map query's looser thresholds (the loop closure's) refuse what the tight ones refuse: a frame of
    another scene, a planted wrong candidate with a witness, a wrong candidate no other keyframe can witness."""
    old = _old_map_settings()
    m, index = _map(room, [0, 10, 20, 30, 40, 50])
    other = make_sequence("far", n=2, width=W, height=H, seed=1)
    assert index.query(_gray(other.rgb[1]), m, THR, seed=0, newest=0, settings=old) is None
    m, index = _map(room, [0, 30])
    index.images[1], index.features[1], index.thumbs[1] = index.images[0], index.features[0], index.thumbs[0]
    assert index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[1], settings=old) is None
    m, index = _map(room, [30])
    index.add_keyframe(0, _gray(room.rgb[0]))
    assert index.query(_gray(room.rgb[31]), m, THR, seed=0, keyframes=[0], settings=old) is None
    assert index.rejected == 1


def test_the_old_map_query_finds_a_frame_by_appearance_alone(room):
    """With no recency (``newest=0``) a frame is found among every keyframe by its thumbnail, at the old-map
    thresholds, within 1 cm and 0.5°."""
    m, index = _map(room, [0, 10, 20, 30, 40, 50])
    r = index.query(_gray(room.rgb[12]), m, THR, seed=0, newest=0, settings=_old_map_settings())
    assert r is not None
    assert m.kf_frame[r.keyframe] in (10, 20)
    dt, dr = _pose_error(r.T_cw, room.poses[12])
    assert dt < 0.01
    assert dr < 0.5

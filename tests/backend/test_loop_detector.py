"""Loop closure's detection and verification (mutualslam_cli.backend.loop_detector) on a rendered room the camera
circles: frame 1273 sees again what frames 45-75 saw, 13 cm and 2.3 degrees from frame 60."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.backend.loop_detector import DEPTH_SPREAD_FACTOR, LoopDetector, depth_agrees
from mutualslam_cli.config import LoopConfig
from mutualslam_cli.datasets.synthetic.scenes import camera_pose
from mutualslam_cli.datasets.synthetic.sequences import FPS, _setup, synthetic_intrinsics
from mutualslam_cli.geometry import se3_inv, to_normalized
from mutualslam_cli.map.state import MapState
from mutualslam_cli.vo.features import detect_grid

W, H = 320, 240
THR = 2.0 / 250.0


@pytest.fixture(scope="module")
def frames():
    """``frame → (grey, depth, T_wc)`` of the frames the tests use (rendered one by one)."""
    sdef, renderer = _setup("room", W, H, 0, "target")
    out = {}
    for f in (30, 45, 60, 75, 90, 300, 315, 330, 1262, 1266, 1270, 1273, 1276):
        T = camera_pose(sdef.path, f / FPS)
        rgb, depth = renderer.render(T)
        grey = (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]).astype(np.uint8)
        out[f] = (grey, depth, T)
    return out


def _map(frames, old: list[int], query: int, unit: float, offset: np.ndarray, drifted: tuple = ()) -> MapState:
    """Keyframes of ``old`` frames with GT poses and points (metric), then the ``query`` frame placed ``offset``
    (a drift) from its true pose, its own points in a unit ``unit`` times the old one's; frames in ``drifted`` (of
    ``old``) are placed and scaled like the query (the new map, made since the old visit)."""
    intr = synthetic_intrinsics(W, H)
    st = MapState(intr, 2000)
    K = intr.K()
    placed = [(f, unit, offset @ frames[f][2]) if f in drifted else (f, 1.0, frames[f][2]) for f in old]
    for f, scale, T in placed + [(query, unit, offset @ frames[query][2])]:
        k = st.add_keyframe(f, f / FPS, T, 0)
        grey, depth = frames[f][0], frames[f][1]
        px = detect_grid(grey, 16, 300).astype(np.float64)
        z = depth[np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)] * scale
        st.add_points(np.full(len(z), k), px, to_normalized(px, K), 1.0 / z, np.zeros(len(z)),
                          [{k: p} for p in px])
    return st


def _detector(st: MapState, frames, settings: LoopConfig) -> LoopDetector:
    d = LoopDetector(synthetic_intrinsics(W, H), THR, settings)
    for k, f in enumerate(st.map.kf_frame):
        d.add(k, frames[f][0])
    return d


def test_a_place_seen_before_is_found_with_its_pose_and_scale(frames):
    drift = np.eye(4)
    drift[:3, 3] = [0.2, -0.05, 0.1]  # where the odometry put the new keyframe: 23 cm off
    st = _map(frames, [30, 45, 60, 75, 90], 1273, unit=1.25, offset=drift)
    q = st.n_keyframes - 1
    d = _detector(st, frames, LoopConfig(min_gap=1))
    loop = d.query(st, q, frames[1273][0], frames[1273][1])  # an exact "network": GT depth
    assert loop is not None
    assert st.map.kf_frame[loop.match] in (45, 60, 75)
    pos_err = np.linalg.norm(se3_inv(loop.T_cw)[:3, 3] - frames[1273][2][:3, 3])
    assert pos_err < 0.02  # the loop pose is the true pose in the old (metric) map
    assert loop.scale == pytest.approx(1 / 1.25, rel=0.03)  # old units per unit of the drifted map
    assert loop.spread < 0.05
    assert loop.inliers >= 40


def test_a_look_alike_place_is_rejected(frames):
    """Keyframe 0 carries the image of a frame next to the query (a place that looks the same) under the points
    of another part of the room: appearance picks it first, geometry and the witnesses refuse it."""
    st = _map(frames, [300, 315, 330], 1273, unit=1.0, offset=np.eye(4))
    q = st.n_keyframes - 1
    d = _detector(st, frames, LoopConfig(min_gap=1))
    d.index.add_keyframe(0, frames[1270][0])  # the look-alike: another place's points, this place's image
    assert d.index.candidates(frames[1273][0], [0, 1, 2], newest=0)[0] == 0
    assert d.query(st, q, frames[1273][0], frames[1273][1]) is None
    assert sum(d.rejected.values()) >= 1
    assert d.tried >= 1


def test_the_loop_scale_pairs_nearby_points_so_a_biased_network_cancels():
    from mutualslam_cli.backend.loop_detector import _local_scale

    rng = np.random.default_rng(0)
    size = (320, 240)
    truth = rng.uniform(1.0, 4.0, (240, 320))  # metres at each pixel
    # the network's depth is off by up to 60 % across the image (a wall it puts too far on the right)
    depth = truth * (1.0 + 0.6 * np.arange(320)[None, :] / 320)
    # old points (old unit = metres) mostly on the left, the new keyframe's own points (unit 2x) mostly on the right,
    # some of each everywhere
    def points(n, left):
        x = np.concatenate([rng.uniform(0, 160, int(0.8 * n)), rng.uniform(0, 320, n - int(0.8 * n))])
        x = x if left else 319 - x
        uv = np.stack([x, rng.uniform(0, 239, n)], 1)
        return uv, truth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    px_old, z_old = points(150, True)
    uv_new, z_m = points(150, False)
    z_new = 2.0 * z_m  # the drifted unit: old units per new unit = 0.5
    s, err = _local_scale(px_old, z_old, uv_new, z_new, depth, size)
    assert abs(s / 0.5 - 1) < 0.03
    assert err < 0.02
    # no old point with a new one near: not measurable
    assert _local_scale(px_old[px_old[:, 0] < 100], z_old[px_old[:, 0] < 100], uv_new[uv_new[:, 0] > 250],
                        z_new[uv_new[:, 0] > 250], depth, size) is None
    # the medians over each set, the rule before: the network's bias does not cancel
    from mutualslam_cli.pixels import lookup_nearest
    glob = (np.median(z_old / lookup_nearest(depth, px_old, size))
            / np.median(z_new / lookup_nearest(depth, uv_new, size)))
    assert abs(glob / 0.5 - 1) > 0.1


def test_each_query_records_its_candidates_and_what_became_of_them(frames):
    """What loop recall reads (LoopDetector.queries): the pool, the candidates by appearance, each verified one's
    outcome and the query's; recording changes no decision."""
    from mutualslam_cli.vo.relocalise import NO_MATCH, PASSED, REFUTED

    drift = np.eye(4)
    drift[:3, 3] = [0.2, -0.05, 0.1]
    st = _map(frames, [30, 45, 60, 75, 90], 1273, unit=1.25, offset=drift)
    q = st.n_keyframes - 1
    d = _detector(st, frames, LoopConfig(min_gap=1, n_candidates=3))
    loop = d.query(st, q, frames[1273][0], frames[1273][1])
    rec = d.queries[-1]
    assert rec["kf"] == q
    assert rec["pool"].tolist() == [0, 1, 2, 3, 4]
    assert len(rec["candidates"]) == 3
    assert set(rec["candidates"]) <= set(range(5))
    tried = list(rec["geometry"])
    assert tried == rec["candidates"][: len(tried)]  # verified in the order proposed, until one passed
    assert rec["geometry"][tried[-1]] == PASSED
    assert all(rec["geometry"][k] in (REFUTED, NO_MATCH) for k in tried[:-1])
    assert rec["verified"] == loop.match == tried[-1]
    assert rec["outcome"] == "loop"
    assert d.already_closed(st, loop) is False
    assert d.queries[-1]["outcome"] == "loop"
    # the look-alike: refused by geometry, recorded so
    st2 = _map(frames, [300, 315, 330], 1273, unit=1.0, offset=np.eye(4))
    d2 = _detector(st2, frames, LoopConfig(min_gap=1))
    d2.index.add_keyframe(0, frames[1270][0])
    assert d2.query(st2, st2.n_keyframes - 1, frames[1273][0], frames[1273][1]) is None
    rec2 = d2.queries[-1]
    assert rec2["candidates"][0] == 0
    assert rec2["verified"] is None
    assert rec2["geometry"][0] in (REFUTED, NO_MATCH)
    assert PASSED not in rec2["geometry"].values()
    assert rec2["outcome"].startswith("geometry")


def test_a_noisy_network_does_not_refuse_a_true_loop(frames):
    """A network 35 % off per pixel (a pre-trained one on real images) spreads the old points' depth ratios past
    ``max_depth_spread``; the keyframe's own points spread as much, so the loop is not refused for it."""
    drift = np.eye(4)
    drift[:3, 3] = [0.2, -0.05, 0.1]
    st = _map(frames, [30, 45, 60, 75, 90], 1273, unit=1.25, offset=drift)
    q = st.n_keyframes - 1
    noisy = frames[1273][1] * np.exp(np.random.default_rng(0).normal(0, 0.35, frames[1273][1].shape))
    d = _detector(st, frames, LoopConfig(min_gap=1))
    loop = d.query(st, q, frames[1273][0], noisy)
    assert loop is not None
    assert loop.spread > LoopConfig().max_depth_spread
    assert d.queries[-1]["spread_new"] * DEPTH_SPREAD_FACTOR >= loop.spread


def test_depth_agreement_is_against_the_networks_own_noise():
    assert depth_agrees(0.2, 0.0, 0.25)
    assert depth_agrees(0.4, 0.3, 0.25)
    assert not depth_agrees(0.5, 0.3, 0.25)  # 1.67 × the network's own spread: the pose's depths do not follow
    assert not depth_agrees(0.3, 0.1, 0.25)


def test_a_true_loop_is_witnessed_by_the_old_map_not_by_the_drifted_new_one(frames):
    """The keyframes made since the old visit carry the drift the loop corrects: under the true loop pose their points
    are a drift away from where their images put them. Taken as witnesses (the old rule: the candidate's segment)
    they refute every true revisit; the old side of the map (the pool) confirms it. Its scale comes from the two maps'
    own points on one pixel (3D–3D pairs), not from the network."""
    drift = np.eye(4)
    drift[:3, 3] = [0.2, -0.05, 0.1]
    new = [1262, 1266, 1270, 1276]  # the query's neighbours, made in the drifted map
    st = _map(frames, [30, 45, 60, 75, 90, *new], 1273, unit=1.25, offset=drift, drifted=new)
    q = st.n_keyframes - 1
    pool = [0, 1, 2, 3, 4]  # the old visit: keyframes 5–8 are within min_gap of the query
    d = _detector(st, frames, LoopConfig(min_gap=5))
    loop = d.query(st, q, frames[1273][0], np.full_like(frames[1273][1], 5.0))  # a useless "network": flat
    assert loop is not None
    assert st.map.kf_frame[loop.match] in (45, 60, 75)
    T_true = se3_inv(frames[1273][2])
    s = d.index.settings
    assert set(d.index._witnesses(T_true, loop.match, st.map, (H, W), s, pool)) <= set(pool) - {loop.match}
    assert set(d.index._witnesses(T_true, loop.match, st.map, (H, W), s)) & {5, 6, 7, 8}  # the old rule took new ones
    assert np.linalg.norm(se3_inv(loop.T_cw)[:3, 3] - frames[1273][2][:3, 3]) < 0.02
    assert d.queries[-1]["scale_from"] == "map"
    assert loop.scale == pytest.approx(1 / 1.25, rel=0.03)


def test_the_maps_own_scale_pairs_points_on_one_pixel():
    from mutualslam_cli.backend.loop_detector import MIN_SAME_POINTS, paired_scale

    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 300, (60, 2))
    z = rng.uniform(1.0, 4.0, 60)
    s, err = paired_scale(uv + rng.normal(0, 0.5, uv.shape), 0.8 * z, uv, z)  # old units per new: 0.8
    assert s == pytest.approx(0.8, rel=1e-6)
    assert err < 1e-6
    wrong = z.copy()
    wrong[:15] *= 3.0  # a quarter of the pairs are other points: the median holds
    assert paired_scale(uv, 0.8 * wrong, uv, z)[0] == pytest.approx(0.8, rel=1e-6)
    assert paired_scale(uv[:MIN_SAME_POINTS - 1], z[:MIN_SAME_POINTS - 1], uv, z) is None
    assert paired_scale(uv + 10.0, z, uv, z) is None  # no old point on a new one's pixel

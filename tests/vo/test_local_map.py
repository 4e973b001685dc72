"""Map reuse (:mod:`mutualslam_cli.vo.local_map`): which old points a frame looks for, and from which keyframe."""

from __future__ import annotations

import numpy as np

from mutualslam_cli.geometry import exp_so3, se3_inv
from mutualslam_cli.map.state import MapState
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.keyframe_images import KeyframeImages
from mutualslam_cli.vo.local_map import MAX_SOURCES, local_map

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
SIZE = (320, 240)
INTR = Intrinsics(300.0, 300.0, 160.0, 120.0, *SIZE)


def _T_wc(centre, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([[0.0, np.radians(yaw_deg), 0.0]]))[0]
    T[:3, 3] = centre
    return T


def _add_point(st: MapState, X: np.ndarray, kfs: list[int]) -> int:
    """A point at world ``X`` hosted by ``kfs[0]`` and observed by every keyframe of ``kfs``."""
    m = st.map
    T_cw = se3_inv(m.kf_T_wc[kfs[0]])
    Xc = T_cw[:3, :3] @ X + T_cw[:3, 3]
    xn = Xc[:2] / Xc[2]
    obs = {}
    for k in kfs:
        Tk = se3_inv(m.kf_T_wc[k])
        Xk = Tk[:3, :3] @ X + Tk[:3, 3]
        obs[k] = (Xk[:2] / Xk[2]) * 300.0 + np.array([160.0, 120.0])
    return int(st.add_points(np.array([kfs[0]]), np.array([obs[kfs[0]]]), xn[None], np.array([1 / Xc[2]]),
                             np.array([0.01]), [obs])[0])


def _scene() -> tuple[MapState, dict[str, int]]:
    st = MapState(INTR, 200)
    st.add_keyframe(0, 0.0, _T_wc([0, 0, 0]), 0)            # kf 0: old, same viewpoint as the query
    st.add_keyframe(10, 1.0, _T_wc([1.8, 0, 1.2], -60.0), 0)  # kf 1: old, a very different viewpoint
    for j in range(2, 7):                                   # kf 2–6: the newest, far to the side
        st.add_keyframe(100 + j, 5.0 + j, _T_wc([3.0 + 0.1 * j, 0, 0]), 0)
    p = {"old": _add_point(st, np.array([0.1, 0.05, 2.0]), [0]),
         "oblique": _add_point(st, np.array([-0.2, 0.0, 2.0]), [1]),
         "both": _add_point(st, np.array([0.3, -0.1, 2.5]), [1, 0]),
         "behind": _add_point(st, np.array([0.0, 0.0, -2.0]), [0]),
         "recent": _add_point(st, np.array([3.4, 0.0, 2.0]), [5, 6])}
    return st, p


def _query(m, tracked=(), occupied=None, kfs=None):
    occupied = np.zeros((0, 2)) if occupied is None else occupied
    T_cw = se3_inv(_T_wc([0.02, 0, 0]))
    kfs = np.arange(len(m.kf_frame)) if kfs is None else np.asarray(kfs)
    return local_map(m, T_cw, K, SIZE, kfs, [2, 3, 4, 5, 6], {4, 5, 6}, np.asarray(tracked, np.int64),
                     occupied, lambda px: px, 20)


def test_old_points_in_view_are_looked_for_from_the_closest_viewpoint():
    st, p = _scene()
    m = st.map
    lm = _query(m)
    got = dict(zip(lm.pids.tolist(), lm.source.tolist()))
    assert got[p["old"]] == 0
    assert got[p["both"]] == 0
    assert p["oblique"] not in got  # seen only from ~60° away: a patch KLT cannot match
    assert p["behind"] not in got
    assert p["recent"] not in got
    assert lm.old[lm.pids == p["old"]].all()


def test_tracked_points_other_units_and_taken_cells_are_skipped():
    st, p = _scene()
    m = st.map
    assert p["old"] not in _query(m, tracked=[p["old"]]).pids
    assert len(_query(m, kfs=[2, 3, 4, 5, 6]).pids) == 0  # the old keyframes in another map unit
    px = (np.array([0.1 - 0.02, 0.05]) / 2.0) * 300 + np.array([160, 120])  # where "old" projects
    assert p["old"] not in _query(m, occupied=px[None]).pids  # a track holds its cell: no new point there


def test_at_most_max_sources_old_keyframes_are_decoded():
    st = MapState(INTR, 200)
    m = st.map
    n = MAX_SOURCES + 3
    for j in range(n):
        st.add_keyframe(j, float(j), _T_wc([0.01 * j, 0, 0]), 0)
    for j in range(n):  # each old keyframe the closest view of its own points (1 + j of them)
        for i in range(1 + j):
            _add_point(st, np.array([-0.6 + 0.15 * i, -0.3 + 0.1 * j, 2.0]), [j])
    T_cw = se3_inv(_T_wc([0.01 * (n - 1), 0, 0]))
    lm = local_map(m, T_cw, K, SIZE, np.arange(n), [], set(), np.zeros(0, np.int64), np.zeros((0, 2)),
                   lambda px: px, 10)
    assert set(lm.source.tolist()) == set(range(n - MAX_SOURCES, n))  # the ones holding the most points


def test_keyframe_images_are_decoded_once_and_kept_few():
    loads = []
    imgs = KeyframeImages(lambda f: loads.append(f) or np.full((2, 2), f, np.uint8), size=2)
    assert imgs.get(3)[0, 0] == 3
    assert imgs.get(3)[0, 0] == 3
    assert loads == [3]
    imgs.get(4), imgs.get(5), imgs.get(3)
    assert loads == [3, 4, 5, 3]  # 3 was dropped when 5 came (two kept)


# ----------------------------------------------------------------------------- warped KLT and fusion (rendered room)


def _render_map():
    """Frame 60 of a rendered room as a keyframe with GT points, and the grey images and poses of later frames."""
    from mutualslam_cli.datasets.synthetic.scenes import camera_pose
    from mutualslam_cli.datasets.synthetic.sequences import FPS, _setup, synthetic_intrinsics
    from mutualslam_cli.geometry import to_normalized
    from mutualslam_cli.vo.features import detect_grid

    w, h = 320, 240
    sdef, renderer = _setup("room", w, h, 0, "target")
    frames = {}
    for f in (60, 120):
        T = camera_pose(sdef.path, f / FPS)
        rgb, depth = renderer.render(T)
        frames[f] = ((0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]).astype(np.uint8), depth, T)
    intr = synthetic_intrinsics(w, h)
    st = MapState(intr, 200)
    m = st.map
    g, d, T = frames[60]
    k = st.add_keyframe(60, 60 / FPS, T, 0)
    px = detect_grid(g, 16, 300).astype(np.float64)
    z = d[np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)]
    pids = st.add_points(np.full(len(z), k), px, to_normalized(px, intr.K()), 1.0 / z, np.zeros(len(z)),
                         [{k: p} for p in px])
    return m, pids, frames, intr


def test_warped_klt_finds_an_old_point_from_another_viewpoint_where_plain_klt_drifts():
    """Frame 120 sees frame 60's points from 2 s further along the room's path: the patch warped by the relative pose
    (SVO 2.0) lands within a fraction of a pixel of the true projection, plain KLT several times farther."""
    from mutualslam_cli.vo.reproject import affine_warps, warped_klt
    from mutualslam_cli.vo.tracking import klt_track

    m, pids, frames, intr = _render_map()
    K = intr.K()
    gq, _, Tq = frames[120]
    T_cw = se3_inv(Tq)
    pc = m.Xw[pids] @ T_cw[:3, :3].T + T_cw[:3, 3]
    proj = pc[:, :2] / pc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    inside = (pc[:, 2] > 0) & (proj[:, 0] > 10) & (proj[:, 0] < 310) & (proj[:, 1] > 10) & (proj[:, 1] < 230)
    P, src = pids[inside], np.zeros(int(inside.sum()), np.int64)
    src_raw, pred, A = affine_warps(m, P, src, T_cw, intr)
    raw, ok = warped_klt(lambda kf: frames[60][0], gq, src, src_raw, pred.astype(np.float32), A, 17, 3, 1.0)
    raw2, ok2 = klt_track(frames[60][0], gq, src_raw.astype(np.float32), 17, 3, 1.0, pred=pred.astype(np.float32),
                          retry=False)
    err = np.linalg.norm(raw[ok] - proj[inside][ok], axis=1)
    err2 = np.linalg.norm(raw2[ok2] - proj[inside][ok2], axis=1)
    assert len(P) > 40
    assert ok.mean() > 0.8
    assert np.median(err) < 0.3
    assert np.median(err2) > 2.5 * np.median(err)


def test_a_young_point_that_is_an_old_one_seen_again_is_fused_into_it():
    """A young point at an old point's corner (a revisit that made the corner again) is a candidate duplicate of it;
    fusing moves its observations to the old point and takes it out of the map, journaled as observations and a
    removal."""
    from mutualslam_cli.map.journal import Journal
    from mutualslam_cli.vo.local_map import duplicates

    st, p = _scene()
    m = st.map
    st.journal = Journal()
    X_old = m.Xw[p["old"]].copy()
    young = _add_point(st, X_old + [0.001, 0.0, 0.0], [5, 6])  # the same corner, made again by keyframes 5–6
    far = _add_point(st, X_old * [1.0, 1.0, 1.5], [5, 6])  # on the same ray, 50 % deeper: another point
    T_cw = se3_inv(_T_wc([0.02, 0, 0]))
    pc = lambda i: m.Xw[i] @ T_cw[:3, :3].T + T_cw[:3, 3]  # noqa: E731
    raw = np.array([pc(i)[:2] / pc(i)[2] * 300.0 + [160.0, 120.0] for i in (young, far)])
    y, o = duplicates(m, T_cw, K, np.arange(len(m.kf_frame)), 2, np.array([young, far]), raw, lambda px: px)
    assert y.tolist() == [young]
    assert o.tolist() == [p["old"]]
    st.fuse_points(y, o)
    assert set(m.obs[p["old"]]) == {0, 5, 6}
    assert not m.obs[young]
    assert np.isnan(m.Xw[young]).all()
    assert p["old"] in m.kf_points[5]
    assert young not in m.kf_points[5]
    assert [e.kind for e in m.journal.events[-3:]] == ["observe", "observe", "remove"]

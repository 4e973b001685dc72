"""Map reuse (:mod:`mutualslam_cli.vo.local_map`): which old points a frame looks for, and from which keyframe."""

from __future__ import annotations

import numpy as np

from mutualslam_cli.geometry import exp_so3, se3_inv
from mutualslam_cli.vo.local_map import MAX_SOURCES, KeyframeImages, local_map
from mutualslam_cli.vo.state import Map

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
SIZE = (320, 240)


def _T_wc(centre, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([[0.0, np.radians(yaw_deg), 0.0]]))[0]
    T[:3, 3] = centre
    return T


def _add_point(m: Map, X: np.ndarray, kfs: list[int]) -> int:
    """A point at world ``X`` hosted by ``kfs[0]`` and observed by every keyframe of ``kfs``."""
    T_cw = se3_inv(m.kf_T_wc[kfs[0]])
    Xc = T_cw[:3, :3] @ X + T_cw[:3, 3]
    xn = Xc[:2] / Xc[2]
    obs = {}
    for k in kfs:
        Tk = se3_inv(m.kf_T_wc[k])
        Xk = Tk[:3, :3] @ X + Tk[:3, 3]
        obs[k] = (Xk[:2] / Xk[2]) * 300.0 + np.array([160.0, 120.0])
    return int(m.add_points(np.array([kfs[0]]), np.array([obs[kfs[0]]]), xn[None], np.array([1 / Xc[2]]),
                            np.array([0.01]), [obs])[0])


def _scene() -> tuple[Map, dict[str, int]]:
    m = Map()
    m.add_keyframe(0, 0.0, _T_wc([0, 0, 0]), 0)            # kf 0: old, same viewpoint as the query
    m.add_keyframe(10, 1.0, _T_wc([1.8, 0, 1.2], -60.0), 0)  # kf 1: old, a very different viewpoint
    for j in range(2, 7):                                  # kf 2–6: the newest, far to the side
        m.add_keyframe(100 + j, 5.0 + j, _T_wc([3.0 + 0.1 * j, 0, 0]), 0)
    p = {"old": _add_point(m, np.array([0.1, 0.05, 2.0]), [0]),
         "oblique": _add_point(m, np.array([-0.2, 0.0, 2.0]), [1]),
         "both": _add_point(m, np.array([0.3, -0.1, 2.5]), [1, 0]),
         "behind": _add_point(m, np.array([0.0, 0.0, -2.0]), [0]),
         "recent": _add_point(m, np.array([3.4, 0.0, 2.0]), [5, 6])}
    return m, p


def _query(m: Map, tracked=(), occupied=None, kfs=None):
    occupied = np.zeros((0, 2)) if occupied is None else occupied
    T_cw = se3_inv(_T_wc([0.02, 0, 0]))
    kfs = np.arange(len(m.kf_frame)) if kfs is None else np.asarray(kfs)
    return local_map(m, T_cw, K, SIZE, kfs, [2, 3, 4, 5, 6], {4, 5, 6}, np.asarray(tracked, np.int64),
                     occupied, lambda px: px, 20)


def test_old_points_in_view_are_looked_for_from_the_closest_viewpoint():
    m, p = _scene()
    lm = _query(m)
    got = dict(zip(lm.pids.tolist(), lm.source.tolist()))
    assert got[p["old"]] == 0 and got[p["both"]] == 0  # kf 0 saw them from where the frame is; kf 1 from ~60° away
    assert p["oblique"] not in got  # seen only from ~60° away: a patch KLT cannot match
    assert p["behind"] not in got and p["recent"] not in got  # behind the camera / outside the image
    assert lm.old[lm.pids == p["old"]].all()


def test_tracked_points_other_units_and_taken_cells_are_skipped():
    m, p = _scene()
    assert p["old"] not in _query(m, tracked=[p["old"]]).pids
    assert len(_query(m, kfs=[2, 3, 4, 5, 6]).pids) == 0  # the old keyframes in another map unit
    px = (np.array([0.1 - 0.02, 0.05]) / 2.0) * 300 + np.array([160, 120])  # where "old" projects
    assert p["old"] not in _query(m, occupied=px[None]).pids  # a track holds its cell: no new point there


def test_at_most_max_sources_old_keyframes_are_decoded():
    m = Map()
    n = MAX_SOURCES + 3
    for j in range(n):
        m.add_keyframe(j, float(j), _T_wc([0.01 * j, 0, 0]), 0)
    for j in range(n):  # each old keyframe the closest view of its own points (1 + j of them)
        for i in range(1 + j):
            _add_point(m, np.array([-0.6 + 0.15 * i, -0.3 + 0.1 * j, 2.0]), [j])
    T_cw = se3_inv(_T_wc([0.01 * (n - 1), 0, 0]))
    lm = local_map(m, T_cw, K, SIZE, np.arange(n), [], set(), np.zeros(0, np.int64), np.zeros((0, 2)),
                   lambda px: px, 10)
    assert set(lm.source.tolist()) == set(range(n - MAX_SOURCES, n))  # the ones holding the most points


def test_keyframe_images_are_decoded_once_and_kept_few():
    loads = []
    imgs = KeyframeImages(lambda f: loads.append(f) or np.full((2, 2), f, np.uint8), size=2)
    assert imgs.get(3)[0, 0] == 3 and imgs.get(3)[0, 0] == 3 and loads == [3]
    imgs.get(4), imgs.get(5), imgs.get(3)
    assert loads == [3, 4, 5, 3]  # 3 was dropped when 5 came (two kept)

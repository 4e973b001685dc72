"""Sim(3) pose graph over keyframes: a loop's correction spread over the keyframes it closes
(:mod:`~mutualslam_cli.backend.loop_detector`).

Each keyframe ``k`` of the loop's map unit from the loop's old end on is a node ``M_k = [s_k R_k | t_k]``
(camera to world, ``s_k`` the unit of its own map: 1 before). Edges hold what the odometry measured:
between consecutive keyframes and between keyframes that share ≥ ``min_shared`` map points (within
``window`` keyframes), the relative Sim(3) ``M_i⁻¹ M_j`` of the current map — weak across a bridge, whose
placement was an estimate (:data:`BRIDGE_SIGMAS`: above all its scale); the loop edge holds what the
loop measured, the new keyframe in the old keyframe's frame and unit (``[s R_loop | t_loop]``), its scale as
sure as the loop's own standard error says. The old end
is fixed; Levenberg–Marquardt finds the poses that strain the edges least. The result is a
:class:`~mutualslam_cli.map.refinement.MapRefinement`: keyframe poses ``[R_k | t_k]``, each keyframe's unit grown
by ``s_k`` (the points it hosts: inverse depth ÷ ``s_k``; its frames: translation × ``s_k``).

Why GTSAM: a Sim(3) graph needs the group's Jacobians (7 degrees of freedom with the scale), a sparse
solver and robust edges; GTSAM (BSD licence, maintained, wheels on PyPI) has them, tested
(``Similarity3``, ``BetweenFactorSimilarity3``, sparse LM). Hand-written, it would be this module several
times over, and tested far less.
"""

from __future__ import annotations

import itertools

import gtsam
import numpy as np

from mutualslam_cli.backend.loop_detector import LoopClosure
from mutualslam_cli.map.refinement import MapRefinement
from mutualslam_cli.map.state import MapState

#: Standard deviations of an odometry edge, per tangent coordinate (rotation ×3 rad, translation ×3 map units, log
#: scale): a monocular odometry drifts in scale more than in rotation and place.
EDGE_SIGMAS = (0.01,) * 6 + (0.03,)
#: ... of the loop edge's rotation and translation; its log scale's is the loop's own standard error (at least this).
LOOP_SIGMA = 0.01
#: ... and of the edge across a bridge, per tangent coordinate (rotation ×3 rad, translation ×3 map units, log
#: scale): its rotation came from the images and its translation spans a gap of a few frames, but its scale is an
#: estimate from the network's depth (:mod:`~mutualslam_cli.backend.bridges`), so the loop's correction goes to the
#: bridges' scales first — and only there, not into rotations and places the bridge did measure.
BRIDGE_SIGMAS = (0.05,) * 3 + (0.1,) * 3 + (0.3,)


def _sim3(M: np.ndarray) -> gtsam.Similarity3:
    """``[s R | t]`` (``p_w = s R p_c + t``) as a GTSAM ``Similarity3`` (``p ↦ s (R p + t)``)."""
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    return gtsam.Similarity3(gtsam.Rot3(M[:3, :3] / s), M[:3, 3] / s, s)


def _matrix(S: gtsam.Similarity3) -> np.ndarray:
    """The inverse of :func:`_sim3`: ``[s R | t]``."""
    s = float(S.scale())
    M = np.eye(4)
    M[:3, :3] = s * S.rotation().matrix()
    M[:3, 3] = s * np.asarray(S.translation())
    return M


def close_loop(state: MapState, loop: LoopClosure, min_shared: int = 20, window: int = 10) -> MapRefinement:
    """The refinement that closes ``loop`` in ``state``'s map (module docstring)."""
    unit = state.unit_of(loop.query)
    kfs = [k for k in range(loop.match, state.n_keyframes) if state.unit_of(k) == unit]
    M0 = {k: state.pose(k) for k in kfs}
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    edge = gtsam.noiseModel.Diagonal.Sigmas(np.array(EDGE_SIGMAS))
    for k in kfs:
        values.insert(k, _sim3(M0[k]))
    graph.add(gtsam.NonlinearEqualitySimilarity3(loop.match, _sim3(M0[loop.match])))
    pairs = set(itertools.pairwise(kfs))
    for a_i, a in enumerate(kfs):
        for b in kfs[a_i + 1:a_i + 1 + window]:
            if state.n_shared(a, b) >= min_shared:
                pairs.add((a, b))
    bridge = gtsam.noiseModel.Diagonal.Sigmas(np.array(BRIDGE_SIGMAS))
    for a, b in sorted(pairs):
        graph.add(gtsam.BetweenFactorSimilarity3(a, b, _sim3(np.linalg.inv(M0[a]) @ M0[b]),
                                                 edge if state.segment(a) == state.segment(b) else bridge))
    T_loop = np.linalg.inv(loop.T_cw)
    M_loop = T_loop.copy()
    M_loop[:3, :3] *= loop.scale
    ls = max(LOOP_SIGMA, loop.scale_error)  # the scale from the network's depth ratios: as sure as they are
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.array([LOOP_SIGMA] * 6 + [ls])))
    graph.add(gtsam.BetweenFactorSimilarity3(loop.match, loop.query, _sim3(np.linalg.inv(M0[loop.match]) @ M_loop),
                                             robust))
    out = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    poses, scales = [], []
    for k in kfs:
        M = _matrix(out.atSimilarity3(k))
        s = float(np.cbrt(np.linalg.det(M[:3, :3])))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = M[:3, :3] / s, M[:3, 3]
        poses.append(T)
        scales.append(s)
    scale_of = dict(zip(kfs, scales))
    pids = state.hosted_points(scale_of)
    rho = np.array([state.inv_depth(p) / scale_of[state.host_of(p)] for p in pids.tolist()])
    px = np.array([state.host_pixel(p) for p in pids.tolist()]).reshape(-1, 2)
    return MapRefinement(np.array(kfs, np.int64), np.array(poses).reshape(-1, 4, 4), pids, rho, px,
                         np.zeros(0, np.int64), np.array(scales))

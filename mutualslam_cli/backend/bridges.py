"""Joining a re-initialised tracking segment to the map before it: scale-consistent re-initialisation.

When relocalisation fails, the front end starts a new segment with its own origin and its own
unit (median depth 1 at its initialisation). A depth predictor carries the unit across the gap:
its ratio to the map on the last keyframe before the gap that sees enough of the map (of the last
:data:`MAX_BACK`), ``r_prev = median(z_map / z_pred)`` over that keyframe's map points, and on the new
segment's first keyframe, ``r_new``, give the new
segment's scale in the old unit, ``s = r_prev / r_new``. The predictor's own unit cancels, so any
depth network serves; the adapted one, trained on this map's sparse depths, has ``r_prev ≈ 1``
(CNN-SVO seeds its depth filter from a CNN in the same spirit).

The new segment's first keyframe is placed at the last tracked pose before the gap, turned by the
rotation between that frame's image and the keyframe's when the two give one (ORB matches, a
homography by RANSAC on normalised coordinates, the rotation fitted to the inliers' bearings:
over a few frames the camera turns far more than it moves); the translation over the gap is not
observed and taken as zero. The segment keeps its id: its placement is an estimate (a *bridge*),
so it shares no observation with the map before it, and everything that solves per connected part
(the global BA) keeps treating it on its own — in the one unit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from mutualslam_cli.geometry import to_normalized
from mutualslam_cli.map.result import MapPoints, VOResult
from mutualslam_cli.map.sim3 import Sim3
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.types import Intrinsics, Trajectory
from mutualslam_cli.vo.camera import undistort_points
from mutualslam_cli.vo.features import orb_features, orb_matches

#: Map points with a depth prediction a keyframe needs for its scale ratio.
MIN_RATIO_POINTS = 10
#: Keyframes before a gap (newest first) tried for the old unit's ratio.
MAX_BACK = 3
#: Largest relative standard error of a bridge's scale (both sides' medians): beyond it the segment stays apart.
MAX_SCALE_ERROR = 0.1
#: Homography inliers (normalised coordinates, this many pixels at the focal length) for a rotation.
ROTATION_PX, MIN_ROTATION_MATCHES = 3.0, 30
#: Median angle between the rotated bearings of the inliers (degrees) above which the rotation is not used.
MAX_ROTATION_RESIDUAL_DEG = 1.0


@dataclass
class Bridge:
    """How a segment was joined (``summary.json``'s ``vo.bridges`` counts them; the list goes to the manifest).

    Attributes:
        segment: the segment moved; onto: the segment before the gap.
        frame: the segment's first keyframe's frame, at ``timestamp`` (s); last_frame: the last
            tracked frame before it.
        scale: ``s``, old units per new unit; ratio_prev, ratio_new: ``median(z_map / z_pred)`` on
            either side, from n_prev and n_new points.
        rotation_deg: the rotation applied across the gap; rotation_from: ``images`` or ``none``.
        R, t: the similarity ``x ↦ s·R·x + t`` that moves the segment (lists, so the record is JSON).
        refused: why the segment was not joined ("" when it was): no ratio on a side, or ratios so spread
            that the scale is uncertain by more than :data:`MAX_SCALE_ERROR`; it then stays apart.
    """

    segment: int
    onto: int
    frame: int
    timestamp: float
    last_frame: int
    scale: float
    ratio_prev: float
    ratio_new: float
    n_prev: int
    n_new: int
    rotation_deg: float
    rotation_from: str
    R: list[list[float]] | None = None
    t: list[float] | None = None
    refused: str = ""

    def sim3(self) -> Sim3:
        """The move ``x ↦ s·R·x + t`` applied to the segment (:class:`~mutualslam_cli.map.sim3.Sim3`: ``R``
        ``(3, 3)``, ``t`` ``(3,)`` float arrays, ``s`` its ``scale``)."""
        return Sim3(np.array(self.R, float), np.array(self.t, float), self.scale)


def depth_ratio(vo: VOResult, kf_id: int, depth: np.ndarray,
                points_w: np.ndarray | None = None) -> tuple[float, int, float]:
    """``median(z_map / z_pred)`` over the map points keyframe ``kf_id`` observes, with ``depth``
    ``(h, w)`` the predictor's map of that keyframe.

    Returns:
        ``(ratio, n, relative standard error of the ratio)``: the error of a median, ``1.253 · σ / √n``
        with σ the ratios' spread (1.4826 × their median absolute deviation, relative to the median);
        ratio and error NaN with fewer than :data:`MIN_RATIO_POINTS` points that have a positive prediction.
    """
    uv, z = vo.sparse_depth(kf_id, points_w)
    d = lookup_nearest(np.asarray(depth, float), uv, (vo.intrinsics.width, vo.intrinsics.height))
    ok = np.isfinite(d) & (d > 0)
    n = int(ok.sum())
    if n < MIN_RATIO_POINTS:
        return float("nan"), n, float("nan")
    r = z[ok] / d[ok]
    med = float(np.median(r))
    spread = 1.4826 * float(np.median(np.abs(r - med))) / med
    return med, n, 1.2533 * spread / np.sqrt(n)


def rotation_between(gray_a: np.ndarray, gray_b: np.ndarray, vo: VOResult, intr_raw: Intrinsics) -> np.ndarray | None:
    """Rotation ``R`` with ``bearing_a ≈ R · bearing_b`` of two raw grey images, when their ORB matches
    agree on one (``None`` otherwise). ``intr_raw``: the camera of the raw images (with distortion)."""
    (pa, da), (pb, db) = orb_features(gray_a), orb_features(gray_b)
    i, j = orb_matches(da, db)
    if len(i) < MIN_ROTATION_MATCHES:
        return None
    K = vo.intrinsics.K()
    xa = to_normalized(undistort_points(pa[i], intr_raw), K)
    xb = to_normalized(undistort_points(pb[j], intr_raw), K)
    f = abs(K[0, 0])
    cv2.setRNGSeed(0)
    H, mask = cv2.findHomography(xb, xa, cv2.RANSAC, ROTATION_PX / f, maxIters=1000, confidence=0.999)
    if H is None or int(mask.sum()) < MIN_ROTATION_MATCHES:
        return None
    inl = mask.ravel().astype(bool)
    ba = np.c_[xa[inl], np.ones(inl.sum())]
    bb = np.c_[xb[inl], np.ones(inl.sum())]
    ba /= np.linalg.norm(ba, axis=1, keepdims=True)
    bb /= np.linalg.norm(bb, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(ba.T @ bb)  # Wahba's problem (Kabsch): argmin Σ ‖b_a − R b_b‖²
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    resid = np.degrees(np.arccos(np.clip(np.sum(ba * (bb @ R.T), axis=1), -1.0, 1.0)))
    return R if float(np.median(resid)) < MAX_ROTATION_RESIDUAL_DEG else None


def plan_bridge(vo: VOResult, first_kf: int, depth_of: Callable[[int], np.ndarray],
                gray_of_frame: Callable[[int], np.ndarray], intr_raw: Intrinsics, points_w: np.ndarray | None = None,
                ) -> Bridge | None:
    """How to join the segment that starts at keyframe ``first_kf`` to the map before it (module docstring).

    Args:
        vo: the map (its segments before ``first_kf`` already in their final unit).
        first_kf: the first keyframe of a segment that is not the first.
        depth_of: ``kf_id → (h, w)`` predicted depth of a keyframe (any unit, positive).
        gray_of_frame: ``frame index → (H, W)`` uint8 raw grey image.
        intr_raw: the camera of the raw images (distortion included).
        points_w: ``vo.points_world()`` when already computed.

    Returns:
        The :class:`Bridge` (its similarity moves the segment's keyframes, points and frames; ``refused``
        says why when the segment stays apart), ``None`` for the first segment.
    """
    kfs = vo.keyframes
    seg = kfs[first_kf].segment
    before = [k for k in kfs[:first_kf] if k.segment != seg]
    if not before:
        return None
    pw = vo.points_world() if points_w is None else points_w
    # the old unit's ratio on the newest keyframe before the gap that sees enough of its map: the very last
    # one may have been made on the failing frames (a blurred or black image) with hardly any point
    onto = before[-1].segment
    cands = [k for k in before if k.segment == onto][-MAX_BACK:][::-1]
    prev, r_prev, n_prev, e_prev = cands[0], float("nan"), 0, float("nan")
    for k in cands:
        if len(vo.points.observed_in(k.id)) >= MIN_RATIO_POINTS:
            prev = k
            r_prev, n_prev, e_prev = depth_ratio(vo, k.id, depth_of(k.id), pw)
            break
    r_new, n_new, e_new = depth_ratio(vo, first_kf, depth_of(first_kf), pw)
    first = kfs[first_kf]
    refused = ""
    if not (np.isfinite(r_prev) and np.isfinite(r_new) and r_new > 0):
        refused = f"fewer than {MIN_RATIO_POINTS} map points with a predicted depth on a side of the gap"
    elif np.hypot(e_prev, e_new) > MAX_SCALE_ERROR:
        refused = (f"the depth ratios spread too wide: the scale {r_prev / r_new:.3g} is uncertain by "
                   f"{100 * np.hypot(e_prev, e_new):.0f} % (> {100 * MAX_SCALE_ERROR:.0f} %; {n_prev} and "
                   f"{n_new} points)")
    if refused:
        return Bridge(int(seg), int(prev.segment), int(first.frame_index), float(first.timestamp), -1, float("nan"),
                      r_prev, r_new, n_prev, n_new, 0.0, "none", refused=refused)
    s = r_prev / r_new
    # the last tracked frame before the gap and its pose (in the old map's frame)
    tracked = np.flatnonzero(vo.frame_segment >= 0)
    pos = {int(f): n for n, f in enumerate(tracked)}
    first_frame = kfs[first_kf].frame_index
    last = int(max((f for f in tracked if f < first_frame and vo.frame_segment[f] == prev.segment),
                   default=prev.frame_index))
    T_last = vo.traj_all.poses[pos[last]] if last in pos else prev.pose
    R_rel = rotation_between(gray_of_frame(int(last)), gray_of_frame(first_frame), vo, intr_raw)
    P = T_last.copy()
    if R_rel is not None:
        P[:3, :3] = T_last[:3, :3] @ R_rel
    T0 = kfs[first_kf].pose
    S = Sim3.onto(T0, P, s)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R_rel) - 1) / 2, -1, 1)))) if R_rel is not None else 0.0
    return Bridge(int(seg), int(prev.segment), int(first_frame), float(kfs[first_kf].timestamp), int(last),
                  float(s), r_prev, r_new, n_prev, n_new, angle, "images" if R_rel is not None else "none",
                  S.R.tolist(), S.t.tolist())


def bridge_segment(vo: VOResult, first_kf: int, depth_of: Callable[[int], np.ndarray],
                   gray_of_frame: Callable[[int], np.ndarray], intr_raw: Intrinsics, points_w: np.ndarray | None = None,
                   ) -> tuple[VOResult, Bridge] | None:
    """:func:`plan_bridge` and the move it plans applied to ``vo`` (:func:`move_segment`): ``(vo', bridge)``,
    or ``None`` when the segment stays apart."""
    b = plan_bridge(vo, first_kf, depth_of, gray_of_frame, intr_raw, points_w)
    if b is None or b.refused:
        return None
    return move_segment(vo, b.segment, b.sim3(), onto=b.onto), b


def bridged(vo: VOResult, bridges: list[Bridge]) -> VOResult:
    """``vo`` (each segment in its own unit) with the bridges a run made applied in order: the front end joined,
    and nothing else (refused ones skipped)."""
    for b in (b for b in bridges if not b.refused):
        vo = move_segment(vo, int(b.segment), b.sim3(), onto=int(b.onto))
    return vo


def move_segment(vo: VOResult, seg: int, S: Sim3, onto: int | None = None) -> VOResult:
    """``vo`` with segment ``seg`` moved by the similarity ``S`` (``x ↦ s·R·x + t``): keyframe and frame poses
    ``T_wc ↦ [R·R_wc | s·R·t_wc + t]``, inverse depths ÷ ``s`` (points follow their hosts); with ``onto``, into
    that segment's map unit (:attr:`VOResult.units`)."""
    S = S.as_float64()
    s = S.s
    kfs = [replace(k, pose=S.apply_pose(k.pose)) if k.segment == seg else k for k in vo.keyframes]
    in_seg = np.array([k.segment == seg for k in vo.keyframes])
    pts = vo.points
    hosted = in_seg[pts.host] if len(pts.host) else np.zeros(0, bool)
    points = MapPoints(pts.ids, pts.host, pts.pixel, np.where(hosted, pts.inv_depth / s, pts.inv_depth),
                       np.where(hosted, pts.sigma / s, pts.sigma), pts.observations, pts.obs_pixels)
    tracked = vo.frame_segment[vo.frame_segment >= 0]
    poses = vo.traj_all.poses.copy()
    sel = tracked == seg
    if sel.any():
        poses[sel] = S.apply_poses(poses[sel])
    units = vo.units if onto is None else {k: u for k, u in vo.joined(seg, onto).items() if k != u}
    return replace(vo, keyframes=kfs, points=points, traj_all=Trajectory(vo.traj_all.timestamps, poses), units=units)

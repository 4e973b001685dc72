"""Loop recall of a run with ``loop.enabled`` and GT poses (:mod:`~mutualslam_cli.metrics.loop_recall`): the keys
``loop.recall.{revisits,found,verified,closed,refused}`` (the refusals' reasons in ``notes``) and
``loop_recall.csv``, one row per keyframe with a true revisit partner.

Evaluated after the run from what the loop closer recorded (:attr:`LoopDetector.queries`, the loops closed, the
keyframes it did not query): GT never reaches a decision of the run.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.backend.loop_closer import LoopCloser
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.loop_recall import MAX_ANGLE_DEG, MAX_DIST_M, RecallRow, classify, counts, true_revisits
from mutualslam_cli.metrics.trajectory import associate_indices
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.context import RunContext

log = logging.getLogger(__name__)

#: The ``loop.recall.*`` counts.
RECALL = ("revisits", "found", "verified", "closed", "refused")
#: The summary keys of loop recall.
RECALL_KEYS = tuple(f"loop.recall.{k}" for k in RECALL)
#: The keys of the closed loops' poses against GT (:func:`summarise_loop_poses`).
POSE_KEYS = ("loop.closed_right", "loop.closed_rot_err_deg_max")
#: ``loop_recall.csv``'s columns.
COLUMNS = ("kf", "frame", "timestamp", "partner", "partner_frame", "dist_m", "angle_deg", "n_partners", "found",
           "verified", "closed", "reason", "candidates", "verified_kf", "closed_kf")


def keyframe_gt(seq: Sequence, vo: VOResult, max_dt: float) -> np.ndarray:
    """``(K, 4, 4)`` GT ``T_wc`` of ``vo``'s keyframes, associated by timestamp as the ATE does
    (:func:`~mutualslam_cli.metrics.trajectory.associate_indices`); NaN rows for keyframes without GT."""
    out = np.full((len(vo.keyframes), 4, 4), np.nan)
    if seq.gt is None or not vo.keyframes:
        return out
    i_ref, i_kf = associate_indices(seq.gt.timestamps, np.array([k.timestamp for k in vo.keyframes]), max_dt)
    out[i_kf] = seq.gt.poses[i_ref]
    return out


#: A closed loop is *right* when its relative pose (query keyframe in the match's camera) is within these of GT's:
#: rotation (degrees) and the translation's direction (degrees; a monocular map has no metric length to compare).
RIGHT_ROT_DEG, RIGHT_DIR_DEG = 5.0, 20.0


def loop_pose_errors(T_query_cw: np.ndarray, T_match_cw: np.ndarray, gt_query_wc: np.ndarray,
                     gt_match_wc: np.ndarray) -> tuple[float, float]:
    """``(rotation, translation-direction)`` error in degrees of a loop's relative pose ``T_query_cw @ inv(T_match_cw)``
    (match camera → query camera) against GT's; a translation shorter than 1 mm in GT gives 0 for its direction."""
    rel = T_query_cw @ np.linalg.inv(T_match_cw)
    g = np.linalg.inv(gt_query_wc) @ gt_match_wc
    cos = (np.trace(rel[:3, :3] @ g[:3, :3].T) - 1.0) / 2.0
    rot = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    a, b = rel[:3, 3], g[:3, 3]
    if np.linalg.norm(b) < 1e-3 or np.linalg.norm(a) < 1e-12:
        return rot, 0.0
    return rot, float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def summarise_loop_poses(summary: Summary, closer: LoopCloser, poses: np.ndarray, ids: np.ndarray) -> None:
    """``loop.closed_right`` (closed loops whose relative pose agrees with GT, :data:`RIGHT_ROT_DEG`,
    :data:`RIGHT_DIR_DEG`) and ``loop.closed_rot_err_deg_max``: whether what was closed was so, whatever the revisit
    rule (a loop onto a keyframe 60 cm away that sees the same counter is a true loop, not a true revisit)."""
    row = {int(k): i for i, k in enumerate(ids.tolist())}
    errs = []
    for lp in closer.loops:
        loop = getattr(lp, "loop", None)
        if loop is None or loop.T_match_cw is None:
            continue
        q, m = row.get(loop.query), row.get(loop.match)
        if q is None or m is None or not (np.isfinite(poses[q]).all() and np.isfinite(poses[m]).all()):
            continue
        errs.append(loop_pose_errors(loop.T_cw, loop.T_match_cw, poses[q], poses[m]))
    if not closer.loops:
        summary.absent("loop.closed_right", "no loop closed")
        summary.absent("loop.closed_rot_err_deg_max", "no loop closed")
        return
    if not errs:
        summary.absent("loop.closed_right", "no closed loop has its pose recorded and GT at both ends")
        summary.absent("loop.closed_rot_err_deg_max", "no closed loop has its pose recorded and GT at both ends")
        return
    right = sum(r <= RIGHT_ROT_DEG and d <= RIGHT_DIR_DEG for r, d in errs)
    summary.set("loop.closed_right", right)
    summary.set("loop.closed_rot_err_deg_max", max(r for r, _ in errs))
    summary.notes["loop.closed_right"] = (f"{right} of {len(errs)} closed loops within {RIGHT_ROT_DEG:g}° and "
                                          f"{RIGHT_DIR_DEG:g}° (translation direction) of GT's relative pose")


#: The keys of the accepted relocalisations against GT (:func:`summarise_relocalisations`).
RELOC_KEYS = ("vo.relocalisations_right", "vo.relocalisations_wrong")


def summarise_relocalisations(summary: Summary, seq: Sequence, vo: VOResult, max_dt: float) -> None:
    """``vo.relocalisations_{right,wrong}``: each accepted relocalisation's frame (a keyframe) against the keyframe
    it was found on, their relative pose in the final front-end map against GT's (:func:`loop_pose_errors`, the
    loop rule: within :data:`RIGHT_ROT_DEG` in rotation and :data:`RIGHT_DIR_DEG` in translation direction)."""
    relocs = vo.meta.get("relocalisations", [])
    if seq.gt is None or len(seq.gt) == 0:
        for k in RELOC_KEYS:
            summary.absent(k, "sequence has no GT poses")
        return
    gt = keyframe_gt(seq, vo, max_dt)
    row = {k.frame_index: j for j, k in enumerate(vo.keyframes)}
    ids = {k.id: j for j, k in enumerate(vo.keyframes)}
    right = wrong = 0
    for r in relocs:
        q, m = row.get(int(r["frame"])), ids.get(int(r["keyframe"]))
        if q is None or m is None or not (np.isfinite(gt[q]).all() and np.isfinite(gt[m]).all()):
            continue
        rot, d = loop_pose_errors(np.linalg.inv(vo.keyframes[q].pose), np.linalg.inv(vo.keyframes[m].pose),
                                  gt[q], gt[m])
        ok = rot <= RIGHT_ROT_DEG and d <= RIGHT_DIR_DEG
        right, wrong = right + ok, wrong + (not ok)
    summary.set("vo.relocalisations_right", right)
    summary.set("vo.relocalisations_wrong", wrong)
    summary.notes["vo.relocalisations_wrong"] = (
        f"of {len(relocs)} accepted, {right + wrong} with GT at both ends: wrong when the relative pose to the "
        f"keyframe found is off GT's by more than {RIGHT_ROT_DEG:g}° or {RIGHT_DIR_DEG:g}° (translation direction)")


def run_stage(run: RunContext, closer: LoopCloser, vo: VOResult) -> list[RecallRow] | None:
    """Loop recall of ``closer`` (:class:`~mutualslam_cli.backend.loop_closer.LoopCloser`) over the keyframes of
    ``vo`` (the run's live map, whose keyframe ids the closer used): keys and ``loop_recall.csv``.

    Returns:
        The rows, or ``None`` without GT poses (the keys null with the reason).
    """
    seq, cfg, summary = run.seq, run.cfg, run.summary
    if seq.gt is None or len(seq.gt) == 0:
        for k in (*RECALL_KEYS, *POSE_KEYS):
            summary.absent(k, "sequence has no GT poses")
        return None
    poses = keyframe_gt(seq, vo, cfg.eval.ate_max_dt)
    ids = np.array([k.id for k in vo.keyframes], np.int64)
    revisits = true_revisits(poses, ids, cfg.loop.min_gap)
    queries = {int(q["kf"]): q for q in closer.detector.queries}
    closed = {lp.query: lp.match for lp in closer.loops}
    rows = classify(revisits, queries, closed, closer.skipped, cfg.loop.n_candidates)
    c = counts(rows)
    for k in RECALL_KEYS:
        summary.set(k, c[k.rsplit(".", 1)[1]])
    summary.notes["loop.recall.revisits"] = (
        f"keyframes with an older one ≥ {cfg.loop.min_gap} keyframes before within {MAX_DIST_M * 100:.0f} cm and "
        f"{MAX_ANGLE_DEG:.0f}° (GT), of {int(np.isfinite(poses[:, 0, 0]).sum())} keyframes with GT")
    if c["reasons"]:
        summary.notes["loop.recall.refused"] = "; ".join(f"{why}: {n}" for why, n in c["reasons"].items())
    summarise_loop_poses(summary, closer, poses, ids)
    elsewhere = [q for q, m in closed.items() if m not in {p.kf for p in revisits.get(q, [])}]
    if elsewhere:
        summary.notes["loop.recall.closed"] = (f"{len(elsewhere)} of {len(closed)} loops closed onto a keyframe that "
                                               f"is no true partner (GT beyond {MAX_DIST_M * 100:.0f} cm or "
                                               f"{MAX_ANGLE_DEG:.0f}°): query keyframes {elsewhere}")
    frame = {k.id: k.frame_index for k in vo.keyframes}
    stamp = {k.id: k.timestamp for k in vo.keyframes}
    table = pd.DataFrame([{**r.record(), "frame": frame[r.kf], "timestamp": stamp[r.kf],
                           "partner_frame": frame[r.partner]} for r in rows], columns=list(COLUMNS))
    atomic_write_text(run.folder / "loop_recall.csv", table.to_csv(index=False))
    log.info("loop recall: %d true revisits, %d found, %d verified, %d closed", c["revisits"], c["found"],
             c["verified"], c["closed"])
    return rows

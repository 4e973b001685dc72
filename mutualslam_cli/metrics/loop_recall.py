"""Loop recall against GT: of the keyframes that truly revisit an older place, how many the loop detector found,
verified and closed — and, for the others, why not.

A *true revisit* is a pair of keyframes ``(i, j)``, ``j − i ≥ min_gap`` (the detector's own gap, so that it could
have proposed ``i``), whose GT poses are within :data:`MAX_DIST_M` of each other and whose relative rotation
``R_i^T R_j`` turns by at most :data:`MAX_ANGLE_DEG`. Place-recognition evaluations score a detector's recall
against such ground-truth loops — pairs of images whose GT poses are close (Gálvez-López and Tardós, "Bags of
Binary Words for Fast Place Recognition in Image Sequences", IEEE T-RO 28(5), 2012; Lowry et al., "Visual Place
Recognition: A Survey", IEEE T-RO 32(1), 2016); for a camera the viewing direction must agree too, and
30 cm / 30° is our bound for a hand-held indoor camera (a place it could match by appearance and geometry).
For each query keyframe ``j`` with at least one true partner:

- ``found``: one of its true partners was among the candidates the detector proposed (the best ``n_candidates``
  by appearance, :attr:`~mutualslam_cli.backend.loop_detector.LoopDetector.queries`);
- ``verified``: the candidate that passed geometric verification is a true partner;
- ``closed``: a loop closed from ``j`` onto a true partner.

Each stage implies the one before. GT enters here only, after the run: no decision of the run reads it.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, TypedDict

import numpy as np

from mutualslam_cli.types import Scalar

#: GT distance (m) and rotation angle (degrees) within which two keyframes see the same place.
MAX_DIST_M, MAX_ANGLE_DEG = 0.30, 30.0


class _QueryRecord(TypedDict):
    kf: int
    pool: np.ndarray
    candidates: list[int]
    geometry: dict[int, str]
    verified: int | None
    outcome: str


class LoopQuery(_QueryRecord, total=False):
    """One record of :attr:`~mutualslam_cli.backend.loop_detector.LoopDetector.queries` (its docstring says what
    each key holds), defined here as loop recall reads it; the keys below only once the query got that far:
    ``spread_old``, ``spread_new`` the depth spreads of the old and new points, ``scale_from`` ``"map"`` or
    ``"network"``."""

    spread_old: float
    spread_new: float
    scale_from: str


@dataclass
class Partner:
    """One true revisit partner ``i`` of a query keyframe: GT distance (m) and rotation angle (degrees)."""

    kf: int
    dist_m: float
    angle_deg: float


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (degrees) of the relative rotation ``Ra^T Rb`` (axis-angle magnitude, ``arccos((tr − 1) / 2)``).

    Args:
        Ra, Rb: ``(..., 3, 3)`` rotations (broadcast).
    """
    tr = np.einsum("...ji,...ji->...", Ra, Rb)  # trace(Ra^T Rb)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def true_revisits(poses: np.ndarray, ids: np.ndarray, min_gap: int, max_dist: float = MAX_DIST_M,
                  max_angle: float = MAX_ANGLE_DEG) -> dict[int, list[Partner]]:
    """The true revisit partners of each keyframe (module docstring).

    Args:
        poses: ``(K, 4, 4)`` GT ``T_wc`` of the keyframes (metres); a row with NaN: no GT (never a partner).
        ids: ``(K,)`` keyframe ids (creation order: the gap is ``ids[j] − ids[i]``).
        min_gap: keyframes between the two at least (``loop.min_gap``).

    Returns:
        ``{j: [Partner, …]}`` for each keyframe id with at least one partner, nearest first.
    """
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    ids = np.asarray(ids, np.int64)
    ok = np.all(np.isfinite(poses), axis=(1, 2))
    p, R = poses[:, :3, 3], poses[:, :3, :3]
    out: dict[int, list[Partner]] = {}
    for j in np.flatnonzero(ok):
        old = np.flatnonzero(ok & (ids <= ids[j] - min_gap))
        if not len(old):
            continue
        d = np.linalg.norm(p[old] - p[j], axis=1)
        a = rotation_angle_deg(R[old], R[j])
        hit = (d <= max_dist) & (a <= max_angle)
        if hit.any():
            order = np.argsort(d[hit], kind="stable")
            out[int(ids[j])] = [Partner(int(ids[old][hit][k]), float(d[hit][k]), float(a[hit][k])) for k in order]
    return out


@dataclass
class RecallRow:
    """One query keyframe with a true partner: its best (nearest) partner, what the detector did, and why not more.

    Attributes:
        kf: the keyframe; partner, dist_m, angle_deg: its nearest true partner and their GT distance / angle.
        n_partners: its true partners; found, verified, closed: the stages reached (module docstring).
        reason: why it went no further ("" when closed).
        candidates: the candidates proposed; verified_kf: the one that passed geometry (−1: none);
        closed_kf: the keyframe the loop closed onto (−1: none).
    """

    kf: int
    partner: int
    dist_m: float
    angle_deg: float
    n_partners: int
    found: bool
    verified: bool
    closed: bool
    reason: str
    candidates: list[int] = field(default_factory=list)
    verified_kf: int = -1
    closed_kf: int = -1

    def record(self) -> dict[str, Scalar]:
        """A CSV-ready dict (candidates as space-separated ids)."""
        d = asdict(self)
        d["candidates"] = " ".join(map(str, self.candidates))
        return d


def _reason(q: LoopQuery, partners: set[int], n_candidates: int, closed_kf: int) -> str:
    """Why query ``q`` (a :attr:`LoopDetector.queries` record) did not close a loop onto a true partner."""
    if not partners & set(np.asarray(q["pool"]).tolist()):
        return "true partners outside its map unit (a segment no bridge joined)"
    if not partners & set(q["candidates"]):
        return f"appearance: no true partner among the {n_candidates} best candidates"
    if q["verified"] not in partners:
        tried = [c for c in q["geometry"] if c in partners]
        if tried:
            return f"geometry: {q['geometry'][tried[0]]}"
        return f"geometry: keyframe {q['verified']} (no true partner) passed before a true partner was tried"
    if closed_kf >= 0 and closed_kf not in partners:
        return f"closed onto keyframe {closed_kf}, no true partner"
    return q["outcome"] if q["outcome"] != "loop" else "verified, not closed"


def classify(revisits: Mapping[int, list[Partner]], queries: Mapping[int, LoopQuery],
             closed: Mapping[int, int], skipped: Mapping[int, str], n_candidates: int) -> list[RecallRow]:
    """One :class:`RecallRow` per keyframe with a true partner, in keyframe order.

    Args:
        revisits: :func:`true_revisits`.
        queries: ``{kf: record}`` of the detector's queries (:attr:`LoopDetector.queries`).
        closed: ``{query kf: match kf}`` of the loops closed.
        skipped: ``{kf: why it was not queried}``.
        n_candidates: candidates proposed per query (``loop.n_candidates``, for the reason's words).
    """
    rows = []
    for j in sorted(revisits):
        ps = revisits[j]
        partners = {p.kf for p in ps}
        q = queries.get(j)
        c_kf = int(closed.get(j, -1))
        if q is None:
            found = verified = False
            reason = skipped.get(j, "not queried")
            cands: list[int] = []
            v_kf = -1
        else:
            cands = [int(c) for c in q["candidates"]]
            v_kf = -1 if q["verified"] is None else int(q["verified"])
            found = bool(partners & set(cands))
            verified = v_kf in partners
            reason = ""
        is_closed = c_kf in partners
        if q is not None and not is_closed:
            reason = _reason(q, partners, n_candidates, c_kf)
        best = ps[0]
        rows.append(RecallRow(j, best.kf, best.dist_m, best.angle_deg, len(ps), found or is_closed,
                              verified or is_closed, is_closed, reason, cands, v_kf, c_kf))
    return rows


def counts(rows: list[RecallRow]) -> dict[str, Any]:
    """``{revisits, found, verified, closed, refused, reasons: {reason: n}}`` of :func:`classify`'s rows
    (``refused``: revisits not closed; ``reasons`` counts their reasons)."""
    return {"revisits": len(rows), "found": sum(r.found for r in rows), "verified": sum(r.verified for r in rows),
            "closed": sum(r.closed for r in rows), "refused": sum(not r.closed for r in rows),
            "reasons": dict(Counter(r.reason for r in rows if not r.closed).most_common())}

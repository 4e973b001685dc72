"""Trajectory accuracy: timestamp association and ATE (DESIGN §7).

The absolute trajectory error follows Sturm et al., "A Benchmark for the Evaluation of
RGB-D SLAM Systems", IROS 2012 (§VI-A): associate the estimated and the ground-truth poses
by timestamp, align the estimate to the ground truth with the least-squares similarity
(monocular, Sim(3)) or rigid (SE(3)) transform of Umeyama, "Least-Squares Estimation of
Transformation Parameters Between Two Point Patterns", IEEE PAMI 13(4), 1991, and report
statistics of the translational residuals. The alignment itself is
:mod:`mutualslam_cli.metrics.alignment`; the greedy one-to-one association (``unique``) is the
package's one :func:`mutualslam_cli.datasets.associate.associate`.

The numbers equal ``evo_ape tum REF EST -as --t_max_diff 0.02`` (evo 1.38.1, same pairs,
same alignment, same statistics; ``tests/metrics/test_ate_evo.py`` checks it on real data). Note
that the ``evo_ape`` command line defaults to ``--t_max_diff 0.01``; mslam's default is the
TUM benchmark's 0.02 s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, TypedDict

import numpy as np

from mutualslam_cli.datasets.associate import MAX_DT, associate, stamps_match
from mutualslam_cli.errors import ConfigError, DatasetError, GeometryError
from mutualslam_cli.metrics.alignment import (  # noqa: F401  (ALIGNMENTS, umeyama: importable from here too)
    ALIGNMENTS,
    align_positions,
    check_alignment,
    umeyama,
)
from mutualslam_cli.types import JSONObject, Trajectory, check_shape

logger = logging.getLogger(__name__)

ASSOCIATIONS = ("nearest", "unique")


# --------------------------------------------------------------------------- association


def _match_nearest(short: np.ndarray, long: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """For each stamp of ``short``, the nearest stamp of ``long`` within ``max_dt``.

    Same decisions as evo's ``sync.matching_time_indices`` (v1.38): inclusive window
    (:func:`~mutualslam_cli.datasets.associate.stamps_match`), a tie between the two neighbours
    goes to the earlier one, and a ``long`` stamp may be matched by several ``short`` stamps.
    """
    if len(long) == 0 or len(short) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    if np.any(np.diff(long) < 0):  # unsorted: plain nearest search, as evo falls back to
        diffs = np.abs(long[None, :] - short[:, None])
        j = np.argmin(diffs, axis=1)
        ok = stamps_match(diffs[np.arange(len(short)), j], max_dt)
        return np.nonzero(ok)[0], j[ok]
    j_ub = np.minimum(np.searchsorted(long, short, side="right"), len(long) - 1)
    diff_ub = long[j_ub] - short
    diff_lb = np.where(j_ub > 0, short - long[np.maximum(j_ub - 1, 0)], np.inf)
    in_range = (short >= long[0] - max_dt) & (short <= long[-1] + max_dt)
    take_ub = stamps_match(diff_ub, max_dt) & (diff_ub < diff_lb)
    take_lb = ~take_ub & stamps_match(diff_lb, max_dt) & (diff_lb <= diff_ub)
    ok = in_range & (take_ub | take_lb)
    j = np.where(take_ub, j_ub, j_ub - 1)
    return np.nonzero(ok)[0], j[ok]


def associate_indices(
    ref_t: np.ndarray,
    est_t: np.ndarray,
    max_dt: float = MAX_DT,
    method: Literal["nearest", "unique"] = "nearest",
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i_ref, i_est)`` of associated timestamps.

    Args:
        ref_t: ``(N,)`` reference timestamps, seconds.
        est_t: ``(M,)`` estimate timestamps, seconds.
        max_dt: largest accepted ``|t_ref − t_est|``, seconds (inclusive for both methods:
            :func:`~mutualslam_cli.datasets.associate.stamps_match`).
        method: ``nearest`` — evo's ``associate_trajectories`` (nearest-time): every pose of
            the trajectory with fewer poses (``est`` on a tie) takes its nearest stamp in the
            other one; a pose of the longer trajectory can serve two pairs (rare; only when
            the longer one is locally sparser). ``unique`` — TUM ``associate.py``: greedy
            one-to-one matching by increasing ``|dt|``
            (:func:`mutualslam_cli.datasets.associate.associate`).

    Returns:
        Two int arrays of equal length ``K``, sorted by the shorter trajectory's index
        (``unique``: by the reference index).
    """
    ref_t = np.asarray(ref_t, dtype=np.float64).reshape(-1)
    est_t = np.asarray(est_t, dtype=np.float64).reshape(-1)
    if method == "unique":
        pairs = sorted(associate(ref_t, est_t, max_dt))  # by reference index
        if not pairs:
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
        i_ref, i_est = np.array(pairs, dtype=int).T
        return i_ref, i_est
    if method != "nearest":
        raise ConfigError(f"unknown association method {method!r}; valid: {', '.join(ASSOCIATIONS)}")
    if len(est_t) > len(ref_t):  # evo: start from the trajectory with fewer poses
        i_ref, i_est = _match_nearest(ref_t, est_t, max_dt)
    else:
        i_est, i_ref = _match_nearest(est_t, ref_t, max_dt)
    return i_ref, i_est


def _no_overlap_message(ref: Trajectory, est: Trajectory, max_dt: float) -> str:
    def span(t: np.ndarray) -> str:
        return f"{t.min():.6f}–{t.max():.6f} s" if len(t) else "nothing (empty)"

    return (
        f"no timestamps of est within {max_dt:g} s of ref: est spans {span(est.timestamps)}, "
        f"ref spans {span(ref.timestamps)}"
    )


def associate_trajectories(
    ref: Trajectory,
    est: Trajectory,
    max_dt: float = MAX_DT,
    method: Literal["nearest", "unique"] = "nearest",
) -> tuple[Trajectory, Trajectory]:
    """Sub-trajectories ``(ref_sub, est_sub)`` of associated poses, pair ``k`` ↔ row ``k``.

    See :func:`associate_indices` for the matching rule (default: evo's, so that the ATE
    equals ``evo_ape``'s). Raises :class:`DatasetError` when no pair is found, naming both
    time spans.
    """
    i_ref, i_est = associate_indices(ref.timestamps, est.timestamps, max_dt, method)
    if len(i_ref) == 0:
        raise DatasetError(_no_overlap_message(ref, est, max_dt))
    logger.debug("associated %d of %d est / %d ref poses (max_dt %g s)", len(i_ref), len(est), len(ref), max_dt)
    return ref.subset(i_ref), est.subset(i_est)


# --------------------------------------------------------------------------- ATE


@dataclass
class AteResult:
    """Absolute trajectory error of one estimate against a reference (metres).

    Attributes:
        rmse, mean, median, max, min, std: statistics of ``errors`` (``std`` is the
            population standard deviation, as evo).
        n_pairs: number of associated pose pairs used.
        scale: the alignment scale ``s`` (1 for ``se3``/``none``).
        align: ``sim3`` | ``se3`` | ``none``.
        transform: ``(4, 4)`` ``[[s·R, t], [0, 1]]`` applied to the estimate's positions.
        errors: ``(K,)`` per-pair ``‖p_ref − (s·R·p_est + t)‖``, metres.
        ref_timestamps, est_timestamps: ``(K,)`` timestamps of the pairs.
        ref_positions, est_aligned: ``(K, 3)`` positions of the pairs (estimate aligned).
        max_dt: association window used, seconds.
        n_ref, n_est: poses in the input trajectories.
    """

    rmse: float
    mean: float
    median: float
    max: float
    min: float
    std: float
    n_pairs: int
    scale: float
    align: str
    transform: np.ndarray
    errors: np.ndarray
    ref_timestamps: np.ndarray
    est_timestamps: np.ndarray
    ref_positions: np.ndarray
    est_aligned: np.ndarray
    max_dt: float = MAX_DT
    n_ref: int = 0
    n_est: int = 0

    def summary(self) -> JSONObject:
        """Plain-value dict (no arrays) for ``summary.json``."""
        keys = ("rmse", "mean", "median", "max", "min", "std", "n_pairs", "scale", "align", "max_dt", "n_ref", "n_est")
        return {k: getattr(self, k) for k in keys}


class _Stats(TypedDict):
    """The six figures of :func:`_stats` (metres), as keyword arguments of the result records."""

    rmse: float
    mean: float
    median: float
    max: float
    min: float
    std: float


def _stats(errors: np.ndarray) -> _Stats:
    """RMSE, mean, median, max, min, std of translational errors (Sturm et al. 2012, eq. 3)."""
    if len(errors) == 0:
        nan = float("nan")
        return dict(rmse=nan, mean=nan, median=nan, max=nan, min=nan, std=nan)
    return dict(
        rmse=float(np.sqrt(np.mean(errors**2))),  # ATE_RMSE, Sturm et al. 2012 eq. 3
        mean=float(np.mean(errors)),
        median=float(np.median(errors)),
        max=float(np.max(errors)),
        min=float(np.min(errors)),
        std=float(np.std(errors)),
    )


def ate(
    ref: Trajectory,
    est: Trajectory,
    align: Literal["sim3", "se3", "none"] = "sim3",
    max_dt: float = MAX_DT,
    association: Literal["nearest", "unique"] = "nearest",
) -> AteResult:
    """Absolute trajectory error (Sturm et al. 2012, §VI-A) of ``est`` against ``ref``.

    Poses are associated by timestamp (:func:`associate_trajectories`), the estimate's
    positions are aligned to the reference by Umeyama (``sim3`` for monocular VO, ``se3``,
    or ``none``), and statistics of the position residuals are returned. Orientation is not
    part of the error (translational ATE, as ``evo_ape`` with its default pose relation).

    Raises:
        ConfigError: unknown ``align`` or ``association``.
        DatasetError: no pair within ``max_dt`` (the message gives both time spans).
        GeometryError: ``sim3``/``se3`` with fewer than 3 pairs or degenerate positions.
    """
    check_alignment(align)
    ref_sub, est_sub = associate_trajectories(ref, est, max_dt, association)
    p_ref, p_est = ref_sub.positions, est_sub.positions
    aligned, T, _, s = align_positions(p_ref, p_est, align)
    errors = np.linalg.norm(p_ref - aligned, axis=1)  # Sturm et al. 2012 eq. 2 (translation of F_i)
    return AteResult(
        **_stats(errors),
        n_pairs=len(errors),
        scale=s,
        align=align,
        transform=T,
        errors=errors,
        ref_timestamps=ref_sub.timestamps,
        est_timestamps=est_sub.timestamps,
        ref_positions=p_ref,
        est_aligned=aligned,
        max_dt=max_dt,
        n_ref=len(ref),
        n_est=len(est),
    )


@dataclass
class SegmentAte:
    """One segment of :func:`ate_segments`: id, pairs, and its RMSE/scale (NaN if skipped)."""

    segment: int
    n_pairs: int
    rmse: float
    scale: float
    skipped: str | None = None


@dataclass
class SegmentedAteResult:
    """ATE of a VO trajectory that re-initialised: every segment aligned on its own.

    Attributes:
        rmse, mean, median, max, min, std: over all pairs of the aligned segments (metres).
        n_pairs: pairs in aligned segments; ``n_pairs_skipped``: pairs in skipped segments.
        n_segments: segments with at least one pair; ``n_skipped``: of those, not aligned.
        segments: one :class:`SegmentAte` per segment with pairs.
        align: alignment used per segment.
        errors, ref_timestamps, est_timestamps, segment_of_pair: ``(K,)`` per aligned pair.
        note: a sentence saying the number is per-segment aligned (for reports).
    """

    rmse: float
    mean: float
    median: float
    max: float
    min: float
    std: float
    n_pairs: int
    n_pairs_skipped: int
    n_segments: int
    n_skipped: int
    segments: list[SegmentAte]
    align: str
    errors: np.ndarray
    ref_timestamps: np.ndarray
    est_timestamps: np.ndarray
    segment_of_pair: np.ndarray
    note: str = ""
    per_segment_alignment: bool = field(default=True)

    def summary(self) -> JSONObject:
        """Plain-value dict for ``summary.json``."""
        keys = ("rmse", "mean", "median", "max", "min", "std", "n_pairs", "n_pairs_skipped", "n_segments",
                "n_skipped", "align", "note", "per_segment_alignment")
        out = {k: getattr(self, k) for k in keys}
        out["segments"] = [vars(s).copy() for s in self.segments]
        return out


def ate_segments(
    ref: Trajectory,
    est: Trajectory,
    segments: np.ndarray,
    align: Literal["sim3", "se3", "none"] = "sim3",
    max_dt: float = MAX_DT,
    association: Literal["nearest", "unique"] = "nearest",
    min_pairs: int = 3,
) -> SegmentedAteResult:
    """ATE with a separate alignment (own scale) per VO segment between re-initialisations.

    Pairs are associated once over the whole trajectory (same pairs as :func:`ate`), then
    grouped by the segment id of their estimated pose. Segments with fewer than
    ``min_pairs`` pairs or degenerate positions are skipped and counted.

    Args:
        segments: ``(M,)`` integer segment id of each pose of ``est``.

    Raises:
        ShapeError: ``segments`` does not have one entry per estimated pose.
        DatasetError: no pair within ``max_dt``.
        GeometryError: no segment could be aligned.
    """
    check_alignment(align)
    segments = np.asarray(segments).reshape(-1)
    check_shape(segments, [len(est)], "segments (one id per est pose)")
    i_ref, i_est = associate_indices(ref.timestamps, est.timestamps, max_dt, association)
    if len(i_ref) == 0:
        raise DatasetError(_no_overlap_message(ref, est, max_dt))
    seg_of_pair = segments[i_est]
    per: list[SegmentAte] = []
    errs, t_ref, t_est, seg_ids = [], [], [], []
    n_skipped_pairs = 0
    for sid in np.unique(seg_of_pair):
        k = np.nonzero(seg_of_pair == sid)[0]
        p_ref, p_est = ref.positions[i_ref[k]], est.positions[i_est[k]]
        try:
            if align != "none" and len(k) < min_pairs:
                raise GeometryError(f"{len(k)} pairs < {min_pairs}")
            aligned, _, _, s = align_positions(p_ref, p_est, align)
        except GeometryError as exc:
            per.append(SegmentAte(int(sid), len(k), float("nan"), float("nan"), skipped=str(exc)))
            n_skipped_pairs += len(k)
            continue
        e = np.linalg.norm(p_ref - aligned, axis=1)  # Sturm et al. 2012 eq. 2, per segment
        per.append(SegmentAte(int(sid), len(k), float(np.sqrt(np.mean(e**2))), s))
        errs.append(e)
        t_ref.append(ref.timestamps[i_ref[k]])
        t_est.append(est.timestamps[i_est[k]])
        seg_ids.append(np.full(len(k), sid))
    n_skipped = sum(1 for s in per if s.skipped)
    if not errs:
        raise GeometryError(
            f"ATE per segment: none of {len(per)} segments could be aligned "
            f"({'; '.join(f'segment {s.segment}: {s.skipped}' for s in per)})"
        )
    errors = np.concatenate(errs)
    note = (
        f"each of {len(per) - n_skipped} segments aligned separately ({align}, own scale); "
        f"{n_skipped} segments ({n_skipped_pairs} pairs) skipped"
    )
    return SegmentedAteResult(
        **_stats(errors),
        n_pairs=len(errors),
        n_pairs_skipped=n_skipped_pairs,
        n_segments=len(per),
        n_skipped=n_skipped,
        segments=per,
        align=align,
        errors=errors,
        ref_timestamps=np.concatenate(t_ref),
        est_timestamps=np.concatenate(t_est),
        segment_of_pair=np.concatenate(seg_ids),
        note=note,
    )


def path_length(traj: Trajectory) -> float:
    """Length of the polyline through the camera centres, metres (0 for < 2 poses)."""
    if len(traj) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)))

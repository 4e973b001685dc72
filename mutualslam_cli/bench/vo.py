"""Speed and accuracy benchmark of the VO front end (DESIGN §10: ≥ 60 frames/s at 640×480, decode
included).

Usage: ``mslam bench vo [NAME_OR_PATH...]`` (:func:`vo_table`).
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from typing import TypedDict

from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.slam import evaluate_trajectory, map_esi
from mutualslam_cli.vo.frontend import STAGES, run_vo


class VOBench(TypedDict):
    """:func:`bench_vo`'s figures (see there)."""

    fps: float
    fps_runs: list[float]
    ms_per_frame: dict[str, float]
    frames: int
    keyframes: int
    points: int
    tracked_fraction: float
    repeats: int


class VOAccuracy(TypedDict):
    """:func:`vo_accuracy`'s facts (see there)."""

    frames: int
    tracked: float
    keyframes: int
    points: int
    segments: int
    ate_kf: float | None
    ate_all: float | None
    esi: float


def bench_vo(seq: Sequence, cfg: VOConfig | None = None, repeats: int = 3, seed: int = 0) -> VOBench:
    """Run the front end ``repeats`` times over ``seq`` and report medians.

    Args:
        seq: the sequence (frames are decoded inside the timed loop).
        cfg: VO options (default ``VOConfig()``).
        repeats: number of full runs; the median is reported.
        seed: RANSAC seed.

    Returns:
        ``{"fps": median frames/s, "fps_runs": [...], "ms_per_frame": {stage: median ms},
        "frames", "keyframes", "points", "tracked_fraction", "repeats"}``. Stage times are
        per frame over all frames; ``decode`` is only the time the tracker waited for the
        prefetching decoder.
    """
    cfg = cfg or VOConfig()
    runs = [run_vo(seq, cfg, seed=seed) for _ in range(max(1, repeats))]
    fps = [r.meta["fps"] for r in runs]
    last = runs[-1]
    return {
        "fps": statistics.median(fps),
        "fps_runs": fps,
        "ms_per_frame": {k: statistics.median(r.meta["timing"][k] for r in runs) for k in STAGES},
        "frames": len(seq),
        "keyframes": len(last.keyframes),
        "points": len(last.points),
        "tracked_fraction": last.tracked_fraction,
        "repeats": len(runs),
    }


def vo_accuracy(seq: Sequence, vo: VOResult) -> VOAccuracy:
    """Accuracy facts of one front-end run against the sequence's GT (the pipeline's metrics).

    Returns:
        ``{"frames", "tracked", "keyframes", "points", "segments", "ate_kf", "ate_all", "esi"}``;
        ATEs are Sim(3)-aligned RMSE in metres (per segment after a re-initialisation),
        ``None`` without GT; ``esi`` is the map points' scale-invariant log error against GT
        depth at their host pixels (distortion-aware), NaN without GT depth.
    """
    tr = evaluate_trajectory(seq, vo)
    esi, _ = map_esi(seq, vo)
    return {
        "frames": len(seq),
        "tracked": vo.tracked_fraction,
        "keyframes": len(vo.keyframes),
        "points": len(vo.points),
        "segments": vo.meta.get("segments", 1),
        "ate_kf": None if tr["kf"] is None else float(tr["kf"].rmse),
        "ate_all": None if tr["all"] is None else float(tr["all"].rmse),
        "esi": esi,
    }


#: The sequences of :func:`vo_table` when none is named.
VO_TABLE_SEQUENCES = ("tum_fr1_xyz", "icl_lr_kt2", "redkitchen_7scenes")


def vo_table(names: Iterable[str] = ()) -> None:
    """The accuracy/speed table (Markdown, to stdout) of the front end on each sequence (datasets.yaml name or
    folder; none: :data:`VO_TABLE_SEQUENCES`): tracked %, keyframes, map points, ATE (cm, keyframes and all
    frames), the map's e_si and frames/s (median of 3 runs)."""
    names = list(names) or list(VO_TABLE_SEQUENCES)
    print("| sequence | frames | tracked % | keyframes | map points | ATE kf [cm] | ATE all [cm] | e_si map | fps |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in names:
        seq = load_sequence(name)
        vo = run_vo(seq, VOConfig())
        acc = vo_accuracy(seq, vo)
        fps = bench_vo(seq, VOConfig(), repeats=3)["fps"]
        cm = lambda v: "n/a" if v is None else f"{100 * v:.2f}"  # noqa: E731
        print(f"| {seq.name} | {acc['frames']} | {100 * acc['tracked']:.1f} | {acc['keyframes']} | {acc['points']} "
              f"| {cm(acc['ate_kf'])} | {cm(acc['ate_all'])} | {acc['esi']:.3f} | {fps:.1f} |")


"""``make bench``: the speed figures of DESIGN §10 and the benchmarks of the VO, the BA and a fine-tuning step."""

from __future__ import annotations

from collections.abc import Mapping


def figure(figures: Mapping[str, object], key: str) -> float | None:
    """The number under ``key`` in a bag of bench figures (``mslam bench suite``'s: JSON-bound, keys made at run
    time), ``None`` when it is missing or not a number (a note, a failed part)."""
    v = figures.get(key)
    return v if isinstance(v, (int, float)) else None

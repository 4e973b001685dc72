"""The back end's records of what it did to the map: a loop closed (:class:`LoopRecord`), a segment merged
(:class:`MergeRecord`), a culling + BA run (:class:`BARun`). Each is read by name inside the run and becomes
JSON only where ``manifest.json`` is written (``to_json``, the keys in the order the manifest has always had)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, TypedDict

from mutualslam_cli.backend.ba.global_ba import BAStats
from mutualslam_cli.backend.loop_detector import LoopClosure
from mutualslam_cli.types import JSONObject


@dataclass(frozen=True)
class LoopRecord:
    """A loop closed on the map as it stood.

    Attributes:
        loop: the verified loop (query and match keyframes, the Sim(3), its scale and evidence).
        frame, timestamp: the query keyframe's frame and time (s); match_timestamp: the match keyframe's (s).
        ba_nearby_targets: nearby-keyframe targets of the BA that followed the pose graph (``None``: no BA stage).
    """

    loop: LoopClosure
    frame: int
    timestamp: float
    match_timestamp: float
    ba_nearby_targets: int | None = None

    @property
    def query(self) -> int:
        return self.loop.query

    @property
    def match(self) -> int:
        return self.loop.match

    def to_json(self) -> JSONObject:
        out = {**self.loop.record(), "frame": self.frame, "timestamp": self.timestamp,
               "match_timestamp": self.match_timestamp}
        if self.ba_nearby_targets is not None:
            out["ba_nearby_targets"] = self.ba_nearby_targets
        return out


class MergeSite(TypedDict):
    """Where a merge happened, as :class:`MergeRecord`'s fields: the segment merged and the one it was found in,
    the query keyframe's frame and time (s)."""

    segment: int
    onto: int
    frame: int
    timestamp: float


@dataclass(frozen=True)
class MergeRecord:
    """A segment found again in the map before it and merged.

    Attributes:
        loop: the verified match (the segment's keyframe ``loop.query`` seeing ``loop.match``).
        segment, onto: the segment merged and the one it was found in.
        frame, timestamp: the query keyframe's frame and time (s).
        how: ``similarity`` (a unit of its own moved whole), ``pose graph`` or ``pose graph + BA`` (closed as a
            loop within one unit); closed: that loop closure's record.
    """

    loop: LoopClosure
    segment: int
    onto: int
    frame: int
    timestamp: float
    how: Literal["similarity", "pose graph", "pose graph + BA"]
    closed: LoopRecord | None = None

    @property
    def query(self) -> int:
        return self.loop.query

    def to_json(self) -> JSONObject:
        out = {**self.loop.record(), "segment": self.segment, "onto": self.onto, "frame": self.frame,
               "timestamp": self.timestamp}
        out.update(how=self.how, **(self.closed.to_json() if self.closed is not None else {}))
        return out


@dataclass(frozen=True)
class BARun:
    """One culling + global BA: after keyframe ``kf_id``, what it did (:class:`~mutualslam_cli.backend.ba.global_ba.
    BAStats`: counts, costs before and after, seconds, …; the manifest leaves the per-round ``costs`` out)."""

    kf_id: int
    stats: BAStats = field(default_factory=BAStats)

    def to_json(self) -> JSONObject:
        return {"kf_id": self.kf_id, **self.stats.record()}

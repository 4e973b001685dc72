"""The frame records' named rows: what the map state keeps besides keyframes and points, one row per event.

:class:`Relocalised`: a relocalisation the front end accepted (``MapState.relocalisations``, the result's
``meta["relocalisations"]`` as :meth:`Relocalised.to_json`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from mutualslam_cli.types import JSONObject


@dataclass(frozen=True)
class Relocalised:
    """A relocalisation the front end accepted.

    Attributes:
        frame: the frame found again; timestamp: its time (s).
        keyframe: the keyframe it was found against; inliers: the pose's PnP inliers.
        frames_lost: frames since tracking was lost (0: not lost before); candidates_tried: keyframes tried.
    """

    frame: int
    timestamp: float
    keyframe: int
    inliers: int
    frames_lost: int
    candidates_tried: int

    def to_json(self) -> JSONObject:
        """The row as the result's ``meta`` holds it (keys in field order)."""
        return asdict(self)

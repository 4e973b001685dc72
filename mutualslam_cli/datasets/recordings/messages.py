"""The parts of ROS messages :mod:`~mutualslam_cli.datasets.recordings.rosbag` reads, as Protocols.

rosbags deserialises each message into a class it makes per bag from the bag's type store (ROS 1 Noetic or
ROS 2 Humble), so there is no one class to name: these say which fields the converter relies on.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from typing_extensions import Buffer


class Time(Protocol):
    """``builtin_interfaces/Time`` (ROS 1 ``time``, as rosbags reads it): whole seconds and nanoseconds."""

    sec: int
    nanosec: int


class Header(Protocol):
    """``std_msgs/Header``: the sensor time of a message."""

    stamp: Time


class Stamped(Protocol):
    """A message with a ``header`` (every type the converter reads). The converter's functions that take any
    of them (``Any``) tell them apart by their type name, as rosbags gives it."""

    header: Header


class RawImage(Stamped, Protocol):
    """``sensor_msgs/Image``: ``height × width`` pixels, rows ``step`` bytes apart, in ``encoding``."""

    height: int
    width: int
    step: int
    encoding: str
    is_bigendian: int
    data: Buffer  # rosbags: a uint8 array

"""rclpy's time types over the Cyclone runtime: ``Time`` and a node's ``Clock``.

A node's clock is the system time, or, while its ``use_sim_time`` parameter is true, the time
``/clock`` gives (:mod:`.time_source` drives it).
"""
from __future__ import annotations

import time

from rcbf_ros.ros.dds import messages


class Time:
    """rclpy.time.Time subset: wall-clock (ROS system time) nanoseconds since the epoch."""

    def __init__(self, *, seconds: float = 0.0, nanoseconds: int = 0) -> None:
        self.nanoseconds = int(seconds * 1e9) + int(nanoseconds)

    def to_msg(self) -> messages.Message:
        """A ``builtin_interfaces/msg/Time``."""
        sec, nanosec = divmod(self.nanoseconds, 10**9)
        return messages.get_message('builtin_interfaces/msg/Time')(sec=sec, nanosec=nanosec)

    def __repr__(self) -> str:
        return f'Time(nanoseconds={self.nanoseconds})'


class Clock:
    """rclpy.clock.ROSClock subset: system time, or the time ``/clock`` gives while the node's
    ``use_sim_time`` is true (:mod:`.time_source`)."""

    def __init__(self) -> None:
        self._ros_time_ns: int | None = None

    @property
    def ros_time_is_active(self) -> bool:
        return self._ros_time_ns is not None

    def _set_ros_time(self, nanoseconds: int | None) -> None:
        """Override the time (None: back to the system time)."""
        self._ros_time_ns = nanoseconds

    def now(self) -> Time:
        ros_time_ns = self._ros_time_ns
        return Time(nanoseconds=time.time_ns() if ros_time_ns is None else ros_time_ns)

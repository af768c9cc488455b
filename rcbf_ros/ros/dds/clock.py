"""rclpy's time types over the Cyclone runtime: ``Time``, ``ClockType`` and ``Clock``.

A node's clock (``ROS_TIME``) is the system time, or, while its ``use_sim_time`` parameter is
true, the time ``/clock`` gives (:mod:`.time_source` drives it). A ``STEADY_TIME`` clock is the
monotonic clock, whatever ``/clock`` or ``use_sim_time`` do: the clock of a timer that must
fire when the world goes quiet.
"""
from __future__ import annotations

import enum
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


class ClockType(enum.IntEnum):
    """rclpy.clock_type.ClockType (rcl's values)."""

    UNINITIALIZED = 0
    ROS_TIME = 1
    SYSTEM_TIME = 2
    STEADY_TIME = 3


class Clock:
    """rclpy.clock.Clock subset. ``ROS_TIME`` (a node's clock, rclpy's ROSClock): the system
    time, or the time ``/clock`` gives while the node's ``use_sim_time`` is true
    (:mod:`.time_source`); ``SYSTEM_TIME``: the system time; ``STEADY_TIME``: the monotonic
    clock."""

    def __init__(self, *, clock_type: ClockType = ClockType.SYSTEM_TIME) -> None:
        if not isinstance(clock_type, ClockType) or clock_type == ClockType.UNINITIALIZED:
            raise TypeError(f'clock_type: expected a ClockType, got {clock_type!r}')
        self._clock_type = clock_type
        self._ros_time_ns: int | None = None

    @property
    def clock_type(self) -> ClockType:
        return self._clock_type

    @property
    def ros_time_is_active(self) -> bool:
        """True while a ``ROS_TIME`` clock follows ``/clock`` (never for the others)."""
        return self._ros_time_ns is not None

    def _set_ros_time(self, nanoseconds: int | None) -> None:
        """Override the time of a ``ROS_TIME`` clock (None: back to the system time)."""
        if self._clock_type == ClockType.ROS_TIME:
            self._ros_time_ns = nanoseconds

    def now(self) -> Time:
        if self._clock_type == ClockType.STEADY_TIME:
            return Time(nanoseconds=time.monotonic_ns())
        ros_time_ns = self._ros_time_ns
        return Time(nanoseconds=time.time_ns() if ros_time_ns is None else ros_time_ns)

"""``/rosout``: every node's log lines as ``rcl_interfaces/msg/Log``, as rcl publishes them.

rcl gives each node (unless rosout is disabled) one writer on ``/rosout`` with
``rcl_qos_profile_rosout_default``: reliable, transient local, keep-last 1000, lifespan 10 s, so
that a late ``ros2 topic echo /rosout`` still gets the last ten seconds. A log line that passes
the logger's level becomes one message: ``stamp`` (the system time of the line), ``level``
(10 DEBUG ... 50 FATAL), ``name`` (the logger's name), ``msg``, and the caller's ``file``,
``function`` and ``line``. Nothing is sent for lines below the level, so a quiet logger costs
nothing.
"""
from __future__ import annotations

from typing import Any

from cyclonedds._clayer import ddspy_write
from cyclonedds.core import Policy, Qos
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from rcbf_ros.ros.console import console_line
from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.qos import DurabilityPolicy, QoSProfile, to_cyclone_qos, type_user_data

ROSOUT_TOPIC = '/rosout'
LOG_TYPE = 'rcl_interfaces/msg/Log'
ROSOUT_QOS = QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""rcl's ``rcl_qos_profile_rosout_default`` (reliable, transient local, keep-last 1000) ..."""
ROSOUT_LIFESPAN_S = 10
"""... with a lifespan of 10 s."""


class RosoutWriter:
    """A node's ``/rosout`` writer; :meth:`write` never raises (a failure is one stderr line,
    as rcl reports it)."""

    def __init__(self, participant: Any, topic: Topic) -> None:
        qos = to_cyclone_qos(ROSOUT_QOS, type_user_data(LOG_TYPE)) + Qos(
            Policy.Lifespan(duration(seconds=ROSOUT_LIFESPAN_S)))
        self.writer: DataWriter | None = DataWriter(participant, topic, qos=qos)
        self._log_type = messages.get_message(LOG_TYPE)
        self._time_type = messages.get_message('builtin_interfaces/msg/Time')
        # rosbags builds a type's serializer on first use (tens of ms): here, not in a callback
        messages.serialize_message(self._log_type())

    def write(self, *, stamp_ns: int, level: int, name: str, msg: str, file: str,
              function: str, line: int) -> None:
        """Publish one log line (nothing once :meth:`close` has run)."""
        writer = self.writer
        if writer is None:
            return
        try:
            sec, nanosec = divmod(stamp_ns, 10**9)
            message = self._log_type(
                stamp=self._time_type(sec=sec, nanosec=nanosec), level=level, name=name,
                msg=msg, file=file, function=function, line=max(0, min(line, 2**32 - 1)))
            ret = ddspy_write(writer._ref,
                              messages.dds_payload(messages.serialize_message(message)))
            if isinstance(ret, int) and ret < 0:
                raise RuntimeError(f'DDS write failed with code {ret}')
        except Exception as exc:  # noqa: BLE001 - logging must not fail the caller
            console_line(f'Failed to publish log message to rosout: {exc}')

    def close(self) -> None:
        """Delete the writer (idempotent); later lines go to the console only."""
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.__del__()

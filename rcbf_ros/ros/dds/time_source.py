"""``use_sim_time``: the node clock follows ``/clock``, as rclpy's TimeSource makes it.

Every node declares ``use_sim_time`` (bool, default False) unless it already has it (declared
from overrides). While it is true the node subscribes to ``/clock`` (``rosgraph_msgs/msg/Clock``,
best effort, keep-last 1) and ``get_clock().now()`` returns the last time received there (zero
until the first message); while false, the system time. Setting the parameter switches at once.
A message of a time no stamp can carry is dropped (:mod:`rcbf_ros.node_logic.sim_clock`).

The node's timers follow the same clock (:class:`rcbf_ros.ros.dds.endpoints.Timer`), unless
created on another one (``create_timer(..., clock=Clock(clock_type=ClockType.STEADY_TIME))``).
"""
from __future__ import annotations

import time
from typing import Any

from rcbf_ros.node_logic.sim_clock import ClockGuard
from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.parameters import set_parameters_result
from rcbf_ros.ros.dds.qos import QoSProfile, ReliabilityPolicy

USE_SIM_TIME = 'use_sim_time'
CLOCK_TOPIC = '/clock'
CLOCK_TYPE = 'rosgraph_msgs/msg/Clock'
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
"""rclpy's QoS of the ``/clock`` subscription."""


class TimeSource:
    """Drives a node's clock from ``/clock`` while ``use_sim_time`` is true."""

    def __init__(self, *, node: Any) -> None:
        self._node = node
        self._subscription: Any = None
        self._last_ns = 0
        self._guard = ClockGuard()
        if not node.has_parameter(USE_SIM_TIME):
            node.declare_parameter(USE_SIM_TIME, False)
        parameter = node.get_parameter(USE_SIM_TIME)
        if isinstance(parameter.value, bool):
            self.set_active(parameter.value)
        else:  # declared from an override of another type, as rclpy reports it
            node.get_logger().error(f"Invalid type for parameter '{USE_SIM_TIME}' "
                                    f'{parameter.type_!r} should be bool')
        node.add_on_set_parameters_callback(self.on_parameters_set)

    @property
    def active(self) -> bool:
        """True while the clock follows ``/clock``."""
        return self._subscription is not None

    def set_active(self, enabled: bool) -> None:
        """Follow ``/clock`` (True) or the system time (False)."""
        if enabled == self.active:
            return
        clock = self._node.get_clock()
        if enabled:
            clock._set_ros_time(self._last_ns)
            self._subscription = self._node.create_subscription(
                messages.get_message(CLOCK_TYPE), CLOCK_TOPIC, self._on_clock, CLOCK_QOS)
        else:
            clock._set_ros_time(None)
            subscription, self._subscription = self._subscription, None
            self._node.destroy_subscription(subscription)

    def on_parameters_set(self, parameters: list[Any]) -> Any:
        """rclpy's on-set-parameters callback of the time source: ``use_sim_time`` switches the
        clock; a value that is not a bool is refused (a ``SetParametersResult``)."""
        for parameter in parameters:
            if parameter.name != USE_SIM_TIME:
                continue
            if not isinstance(parameter.value, bool):
                reason = f'{USE_SIM_TIME} parameter set to something besides a bool'
                self._node.get_logger().error(reason)
                return set_parameters_result(False, reason)
            self.set_active(parameter.value)
            break
        return set_parameters_result(True)

    def _on_clock(self, message: Any) -> None:
        sec, nanosec = message.clock.sec, message.clock.nanosec
        take, line = self._guard.check(sec, nanosec, now_ns=time.monotonic_ns())
        if line:
            self._node.get_logger().warning(line)
        if not take:  # a time no stamp can carry: the clock keeps its time
            return
        self._last_ns = sec * 10**9 + nanosec
        if self.active:
            self._node.get_clock()._set_ros_time(self._last_ns)

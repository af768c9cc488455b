"""The one import of ROS middleware for every node: real rclpy if importable, else ours.

Selection (once, at import):

- ``RCBF_ROS_RUNTIME=rclpy``: use rclpy, fail loudly if it is missing;
- ``RCBF_ROS_RUNTIME=cyclone``: use our Cyclone DDS runtime (:mod:`rcbf_ros.ros.dds`) even where
  rclpy exists;
- unset / ``auto``: rclpy when ``import rclpy`` works (a sourced ROS 2 install), else Cyclone.

Both expose the same surface (see the names below); ``USING_RCLPY`` tells which one is active.
``Clock(clock_type=ClockType.STEADY_TIME)`` is the clock of a timer that must fire whatever
``/clock`` and ``use_sim_time`` do (``create_timer(..., clock=...)``).
Parameters: ``Parameter`` (with ``Parameter.Type``), ``ParameterDescriptor`` (the
rcl_interfaces message; pass a new one to every declaration, rclpy keeps and modifies it) and
``ParameterException``, the base of rclpy's parameter errors (an override of the wrong type, an
uninitialized typed parameter, ...).
"""
from __future__ import annotations

import os

from rcbf_ros.messages import conversions

_CHOICE = os.environ.get('RCBF_ROS_RUNTIME', 'auto').strip().lower()
if _CHOICE not in ('auto', 'rclpy', 'cyclone'):
    raise ImportError(f'RCBF_ROS_RUNTIME must be auto, rclpy or cyclone, got {_CHOICE!r}')

USING_RCLPY = False
if _CHOICE != 'cyclone':
    try:
        import rclpy  # noqa: F401
        USING_RCLPY = True
    except ImportError:
        if _CHOICE == 'rclpy':
            raise

if USING_RCLPY:
    from rcl_interfaces.msg import ParameterDescriptor
    import rclpy
    from rclpy.clock import Clock, ClockType
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        qos_profile_sensor_data,
        QoSProfile,
        ReliabilityPolicy,
    )
    from rclpy.serialization import deserialize_message, serialize_message
    from rosidl_runtime_py.utilities import get_message
else:
    from rcbf_ros.messages.cdr import deserialize_message, serialize_message
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.clock import Clock, ClockType
    from rcbf_ros.ros.dds.context import ExternalShutdownException
    from rcbf_ros.ros.dds.node import Node
    from rcbf_ros.ros.dds.parameters import Parameter, ParameterException
    from rcbf_ros.ros.dds.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        qos_profile_sensor_data,
        QoSProfile,
        ReliabilityPolicy,
    )

    ParameterDescriptor = get_message('rcl_interfaces/msg/ParameterDescriptor')

conversions.use_message_classes(get_message)  # the message builders make what we publish

__all__ = [
    'Clock', 'ClockType', 'DurabilityPolicy', 'ExternalShutdownException', 'HistoryPolicy',
    'Node', 'Parameter', 'ParameterDescriptor', 'ParameterException', 'QoSProfile',
    'ReliabilityPolicy', 'USING_RCLPY', 'deserialize_message', 'get_message',
    'qos_profile_sensor_data', 'rclpy', 'serialize_message',
]

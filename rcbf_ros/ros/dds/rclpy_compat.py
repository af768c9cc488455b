"""Module-level rclpy functions of the Cyclone runtime (what ``runtime.rclpy`` is without ROS)."""
from __future__ import annotations

import sys
import time
from types import SimpleNamespace
from typing import Any, Sequence

from rcbf_ros.parameters.arguments import remove_ros_args
from rcbf_ros.ros.dds.clock import Clock, ClockType
from rcbf_ros.ros.dds.context import Context, default_context
from rcbf_ros.ros.dds.context import spin as _spin
from rcbf_ros.ros.dds.context import spin_once as _spin_once


def init(*, args: Sequence[str] | None = None, context: Context | None = None,
         domain_id: int | None = None, **_ignored: Any) -> None:
    """Parse global ``--ros-args``, join the DDS domain, install SIGINT/SIGTERM handlers.

    Like rclpy, ``args=None`` means the process's own command line (``sys.argv``).
    """
    (context or default_context).init(sys.argv if args is None else args, domain_id)


def shutdown(*, context: Context | None = None) -> None:
    """Shut the context down (``RuntimeError`` if it is not initialized)."""
    (context or default_context).shutdown()


def try_shutdown(*, context: Context | None = None) -> None:
    """Shut the context down unless that already happened."""
    (context or default_context).try_shutdown()


def ok(*, context: Context | None = None) -> bool:
    """True between ``init`` and ``shutdown`` (or a SIGINT/SIGTERM)."""
    return (context or default_context).ok()


def spin(node: Any, executor: Any = None) -> None:
    """Run the node's callbacks in this thread until shutdown (returns) or a signal (raises)."""
    _spin(node)


def spin_once(node: Any, *, executor: Any = None, timeout_sec: float | None = None) -> None:
    """Run at most one callback, waiting up to ``timeout_sec`` seconds (None: until one)."""
    _spin_once(node, timeout_sec=timeout_sec)


def spin_until_future_complete(node: Any, future: Any, executor: Any = None,
                               timeout_sec: float | None = None) -> None:
    """Run the node's callbacks until ``future`` is done or ``timeout_sec`` passed."""
    deadline = None if timeout_sec is None else time.monotonic() + timeout_sec
    while not future.done() and node.context.ok():
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            return
        _spin_once(node, timeout_sec=0.1 if left is None else min(left, 0.1))


utilities = SimpleNamespace(remove_ros_args=remove_ros_args)
"""``rclpy.utilities.remove_ros_args``."""

clock = SimpleNamespace(Clock=Clock, ClockType=ClockType)
"""``rclpy.clock.Clock`` and ``rclpy.clock.ClockType``."""

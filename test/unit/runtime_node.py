"""A node of the Cyclone runtime for one test: the runtime started in the test's domain."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
import contextlib
from typing import Any

from rcbf_ros.ros.dds import rclpy_compat
from rcbf_ros.ros.dds.node import Node


@contextlib.contextmanager
def runtime_node(name: str, *, domain_id: int, args: Sequence[str] = (),
                 **options: Any) -> Iterator[Node]:
    """``rclpy.init(args=args)`` on ``domain_id`` and ``Node(name, **options)``; on leaving,
    the node destroyed and the runtime shut down."""
    rclpy_compat.init(args=list(args), domain_id=domain_id)
    node = Node(name, **options)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy_compat.try_shutdown()

"""Imported by the rclpy scripts of the ros2 tier (run under a real Jazzy, from this directory):
a node spinning until SIGINT, stopped as a Jazzy ``main()`` stops it."""
import rclpy
from rclpy.executors import ExternalShutdownException


def spin_until_stopped(node) -> None:
    """Spin ``node`` until SIGINT or an external shutdown, then destroy it and shut down."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()

"""Run by the ros2 tier under a real Jazzy: an rclpy node ``/safety_filter`` with one
parameter, ``alpha`` = 2.0, spinning until SIGINT; prints ``ready`` once created."""
import rclpy
from rclpy.executors import ExternalShutdownException


def main():
    rclpy.init()
    node = rclpy.create_node('safety_filter')
    node.declare_parameter('alpha', 2.0)
    print('ready', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


main()

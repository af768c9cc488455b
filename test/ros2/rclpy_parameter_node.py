"""Run by the ros2 tier under a real Jazzy: an rclpy node ``/safety_filter`` with one
parameter, ``alpha`` = 2.0, spinning until SIGINT; prints ``ready`` once created."""
import rclpy
from rclpy_spin import spin_until_stopped


def main():
    rclpy.init()
    node = rclpy.create_node('safety_filter')
    node.declare_parameter('alpha', 2.0)
    print('ready', flush=True)
    spin_until_stopped(node)


main()

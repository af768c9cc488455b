"""Run by the ros2 tier under a real Jazzy: an rclpy publisher of safety-filter proposals.

    python rclpy_proposer.py PROPOSALS.json SUBSCRIBERS

PROPOSALS.json: a list of ``{"u": [...], "state": [...]}``. Waits until /cmd_proposed has
SUBSCRIBERS matched subscriptions, then publishes each proposal as a Float64MultiArray with the
sections ``u`` and ``state`` (reliable, keep-all) at 20 Hz, spins one more second and exits 0.
Uses nothing of rcbf_ros.
"""
import json
import sys
import time

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, MultiArrayDimension


def main() -> None:
    with open(sys.argv[1], encoding='utf-8') as stream:
        proposals = json.load(stream)
    wanted = int(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node('rclpy_proposer')
    publisher = node.create_publisher(Float64MultiArray, '/cmd_proposed', QoSProfile(
        history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 60
    while publisher.get_subscription_count() < wanted:
        if time.monotonic() > deadline:
            sys.exit(f'only {publisher.get_subscription_count()} of {wanted} subscribers')
        rclpy.spin_once(node, timeout_sec=0.1)
    for proposal in proposals:
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=label, size=len(proposal[label]),
                                              stride=len(proposal[label]))
                          for label in ('u', 'state')]
        msg.data = [float(v) for v in proposal['u'] + proposal['state']]
        publisher.publish(msg)
        rclpy.spin_once(node, timeout_sec=0.05)
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f'published {len(proposals)}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


main()

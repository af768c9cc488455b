"""Run by the ros2 tier under a real Jazzy: an rclpy subscriber that writes what it receives.

    python rclpy_listener.py OUT.json SECONDS TOPIC:TYPE [TOPIC:TYPE ...]

Subscribes to every TOPIC (reliable, keep-all) and prints ``listening`` once every
subscription exists; after SECONDS without a new message (or on SIGINT) writes
``{topic: [message as an ordered dict, ...]}`` (rosidl_runtime_py's message_to_ordereddict) to
OUT.json. Uses nothing of rcbf_ros.
"""
import json
import sys
import time

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosidl_runtime_py.convert import message_to_ordereddict
from rosidl_runtime_py.utilities import get_message


def main() -> None:
    out, quiet_s, specs = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
    rclpy.init()
    node = rclpy.create_node('rclpy_listener')
    received = {spec.split(':')[0]: [] for spec in specs}
    last = [time.monotonic()]
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)

    def keep(topic):
        def callback(msg):
            received[topic].append(message_to_ordereddict(msg))
            last[0] = time.monotonic()
        return callback

    for spec in specs:
        topic, type_name = spec.split(':')
        node.create_subscription(get_message(type_name), topic, keep(topic), qos)
    print('listening', flush=True)
    try:
        while time.monotonic() - last[0] < quiet_s or not any(received.values()):
            rclpy.spin_once(node, timeout_sec=0.05)
    except KeyboardInterrupt:
        pass
    finally:
        with open(out, 'w', encoding='utf-8') as stream:
            json.dump(received, stream)
        node.destroy_node()
        rclpy.try_shutdown()


main()

"""Run under a real Jazzy: the safety filter node on rclpy, its source's frame placed by tf2.

    python rclpy_tf2_filter.py PARAMS.yaml

One process, two nodes on DDS: the filter (one scan source ``front`` on /scan, in frame
``laser``) and a robot publishing /tf_static base_link -> laser, /tf odom -> base_link and the
scans. Prints one JSON line: which buffer answers, the filter's subscriptions to /tf and
/tf_static, the points of each scenario (or the fail-safe's reason) and tf's counts.
"""
import json
import math
import sys
import time

from geometry_msgs.msg import TransformStamped
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan
from tf2_msgs.msg import TFMessage

from rcbf_ros.ros.safety_filter_node import SafetyFilterNode

S = 1_000_000_000
MOUNT = (0.3, -0.1, 0.25), 0.4
"""The laser on base_link: (x, y, z) and yaw."""
ODOM = ((9 * S, (1.0, 2.0, 0.2)), (11 * S, (3.0, 0.0, 0.6)))
"""odom -> base_link: (stamp after t0, (x, y, yaw)); t0 is 5 s before the node's clock, so
that every stamp lies within the cache of it (the buffer refuses any farther)."""
BEAMS = dict(angle_min=-0.2, increment=0.1, ranges=[1.0, 2.0, 0.5])


def stamped(parent, child, stamp_ns, translation, yaw):
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.header.stamp.sec, t.header.stamp.nanosec = divmod(stamp_ns, S)
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (
        float(v) for v in translation)
    t.transform.rotation.z, t.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return t


def scan(frame_id, stamp_ns):
    msg = LaserScan()
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, S)
    msg.angle_min = BEAMS['angle_min']
    msg.angle_increment = BEAMS['increment']
    msg.angle_max = msg.angle_min + msg.angle_increment * (len(BEAMS['ranges']) - 1)
    msg.range_min, msg.range_max, msg.scan_time = 0.05, 10.0, 0.1
    msg.ranges = [float(r) for r in BEAMS['ranges']]
    return msg


def main(params_file):
    rclpy.init()
    node = SafetyFilterNode(cli_args=[
        '--ros-args', '--params-file', params_file, '-p', 'observation_sources:=[front]',
        '-p', 'front.type:=scan', '-p', 'front.topic:=/scan', '-p', 'front.timeout_s:=1.0',
        '-p', 'footprint.radius:=0.2', '-p', 'transform_tolerance:=0.1'])
    robot = rclpy.create_node('robot')
    reliable = ReliabilityPolicy.RELIABLE
    tf_pub = robot.create_publisher(TFMessage, '/tf', QoSProfile(depth=100, reliability=reliable))
    static_pub = robot.create_publisher(TFMessage, '/tf_static', QoSProfile(
        depth=1, reliability=reliable, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    scan_pub = robot.create_publisher(LaserScan, '/scan', 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(robot)
    sources = node._sources

    def spin_until(check, what, publish=()):
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            for publisher, make in publish:
                publisher.publish(make())
            end = time.monotonic() + 0.1
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)
            if check():
                return
        sys.exit(f'timed out waiting for {what}')

    def placed(frame_id, after_s):
        stamp = t0 + int(after_s * S)
        spin_until(lambda: sources._sources['front'].stamp_ns == stamp
                   and sources._sources['front'].frame_id == frame_id,
                   f'a scan in {frame_id} at {after_s} s', [(scan_pub, lambda: scan(frame_id,
                                                                                    stamp))])
        out = sources.points(np.zeros(3), now_ns=time.monotonic_ns(), stamp_now_ns=stamp)
        return out if isinstance(out, str) else out[0].tolist()

    spin_until(lambda: min(p.get_subscription_count() for p in (tf_pub, static_pub, scan_pub))
               > 0, 'the filter to subscribe')
    t0 = (node.get_clock().now().nanoseconds // S - 5) * S
    (mx, my, mz), mount_yaw = MOUNT
    static_pub.publish(TFMessage(transforms=[stamped('base_link', 'laser', t0, (mx, my, mz),
                                                     mount_yaw)]))
    for after, (x, y, yaw) in ODOM:
        tf_pub.publish(TFMessage(transforms=[stamped('odom', 'base_link', t0 + after,
                                                     (x, y, 0.0), yaw)]))
    spin_until(lambda: sources.tf_counts['messages'] >= 3, 'the transforms')
    result = {
        't0_s': t0 // S,
        'backend': getattr(sources.tf, 'backend', type(sources.tf).__name__),
        'tf_subscriptions': sorted(s.topic_name for s in node.subscriptions
                                   if s.topic_name in ('/tf', '/tf_static')),
        'interpolated': placed('laser', 10.0),
        'held': placed('laser', 11.05),
        'too_old': placed('laser', 11.2),
        'too_new': placed('laser', 8.8),
        'missing': placed('laser2', 10.0),
    }
    nan = stamped('odom', 'base_link', t0 + 12 * S, (math.nan, 0.0, 0.0), 0.0)
    tf_pub.publish(TFMessage(transforms=[nan]))
    spin_until(lambda: sources.tf_counts['transforms_refused'] >= 1, 'the NaN transform')
    result['after_nan'] = placed('laser', 11.05)
    result['counts'] = dict(sources.tf_counts)
    executor.shutdown()
    node.destroy_node()
    robot.destroy_node()
    rclpy.try_shutdown()
    print(json.dumps(result))


if __name__ == '__main__':
    main(sys.argv[1])

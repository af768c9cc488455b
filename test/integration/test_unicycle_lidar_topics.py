"""The unicycle_lidar node as a separate process over real Cyclone DDS (loopback).

- cmd_vel in: LaserScan in ``laser``, Odometry odom -> base_link that moves with the command,
  /tf odom -> base_link, /tf_static base_link -> laser (late-joining: transient local);
- invalid parameters: the process exits with status 2 and names the key.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Any

from dds_harness import REPO, spawn, stop  # this directory: on sys.path for pytest
import pytest

UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
WAIT_S = 60.0

pytestmark = pytest.mark.integration


@pytest.fixture
def domain_id(ros_domain_id: int) -> int:
    """The test's own domain, never the runner's ROS_DOMAIN_ID: tests of parallel workers
    would share it, and one's filter_info reach another's scene node."""
    return ros_domain_id


class _Probe:
    """An in-process node: publishes cmd_vel, keeps what the robot publishes."""

    def __init__(self, domain_id: int) -> None:
        from rcbf_ros.ros.runtime import DurabilityPolicy, get_message, Node, QoSProfile, rclpy
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node = Node('lidar_probe')
        self.got: dict[str, list[Any]] = {'scan': [], 'odom': [], 'tf': [], 'tf_static': []}
        self.lock = threading.Lock()
        for topic, kind, qos in (
                ('scan', 'sensor_msgs/msg/LaserScan', QoSProfile(depth=10)),
                ('odom', 'nav_msgs/msg/Odometry', QoSProfile(depth=100)),
                ('/tf', 'tf2_msgs/msg/TFMessage', QoSProfile(depth=100)),
                ('/tf_static', 'tf2_msgs/msg/TFMessage',
                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))):
            self.node.create_subscription(get_message(kind), topic,
                                          self._keeper(topic.strip('/')), qos)
        self.twist = get_message('geometry_msgs/msg/Twist')
        self.cmd_pub = self.node.create_publisher(self.twist, 'cmd_vel', QoSProfile(depth=10))
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _keeper(self, key: str):
        def keep(msg: Any) -> None:
            with self.lock:
                self.got[key].append(msg)
        return keep

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def test_cmd_vel_in_scan_odometry_and_transforms_out(domain_id):
    process = spawn(domain_id, '-m', 'sim_nodes.unicycle_lidar_node', '--ros-args',
                    '--params-file', UNICYCLE, '-p', 'laser_mount:=[0.1, 0.0, 0.0]')
    probe = _Probe(domain_id)
    try:
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            assert process.poll() is None, stop(process, timeout=10)
            command = probe.twist()
            command.linear.x = 0.3
            probe.cmd_pub.publish(command)
            time.sleep(0.1)
            with probe.lock:
                odom = probe.got['odom'][-1] if probe.got['odom'] else None
                if (odom is not None and odom.pose.pose.position.x > -2.3
                        and probe.got['scan'] and probe.got['tf_static']):
                    break
        with probe.lock:
            got = {key: list(value) for key, value in probe.got.items()}
    finally:
        probe.close()
        output = stop(process, timeout=10)
    assert got['scan'] and got['tf'] and got['tf_static'], (
        {k: len(v) for k, v in got.items()}, output[-2000:])
    scan = got['scan'][-1]
    assert scan.header.frame_id == 'laser' and len(scan.ranges) == 360
    assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
    odom = got['odom'][-1]
    assert (odom.header.frame_id, odom.child_frame_id) == ('odom', 'base_link')
    assert odom.pose.pose.position.x > -2.3 and odom.twist.twist.linear.x > 0.1
    (static,) = got['tf_static'][-1].transforms
    assert (static.header.frame_id, static.child_frame_id) == ('base_link', 'laser')
    assert static.transform.translation.x == pytest.approx(0.1)
    (moving,) = got['tf'][-1].transforms
    assert (moving.header.frame_id, moving.child_frame_id) == ('odom', 'base_link')
    assert 'Traceback' not in output


@pytest.mark.parametrize('args, key', [
    (['-p', 'start:=[0.0, 0.0, 0.0]'], 'start'),
    (['-p', 'scan_rate_hz:=80.0'], 'scan_rate_hz'),
    (['-p', 'beams:=0'], 'beams'),
])
def test_invalid_parameters_exit_2_naming_the_key(domain_id, args, key):
    process = spawn(domain_id, '-m', 'sim_nodes.unicycle_lidar_node', '--ros-args',
                    '--params-file', UNICYCLE, *args)
    try:
        process.wait(timeout=WAIT_S)
    finally:
        output = stop(process, timeout=10)
    assert process.returncode == 2, output[-2000:]
    assert f'unicycle_lidar: invalid parameters: {key}:' in output, output[-2000:]
    assert 'Traceback' not in output

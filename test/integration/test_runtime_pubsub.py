"""Two separate processes talk over real Cyclone DDS through ``rcbf_ros.ros.runtime``.

Each test starts peer processes (this file run as a script, roles below) in the test's own
ROS_DOMAIN_ID on the loopback Cyclone configuration, then checks what arrived: content, the
exact CDR bytes against rosbags' serializer, completeness and order. Also: SIGTERM / SIGINT to a
spinning node runs its ``finally``.
"""
from __future__ import annotations

import json
from pathlib import Path
import signal
import subprocess
import sys
import time

# dds_harness: this directory, on sys.path for pytest and the children
from dds_harness import node_runtime, spawn
import pytest

PEER_TIMEOUT_S = 60.0
SUBSCRIPTIONS = 2
"""The subscriber role's subscriptions of one topic: raw bytes and decoded messages."""


# ----------------------------------------------------------------------------- peer roles
def _odometry(index: int):
    from rcbf_ros.ros.runtime import get_message
    odometry = get_message('nav_msgs/msg/Odometry')()
    odometry.header.stamp.sec = index
    odometry.header.frame_id = f'odom_{index}'
    odometry.child_frame_id = 'base_link'
    odometry.pose.pose.position.x = float(index)
    odometry.pose.covariance = [float(index + k) for k in range(36)]
    odometry.twist.twist.angular.z = -0.5 * index
    return odometry


def _array(index: int):
    from rcbf_ros.ros.runtime import get_message
    message = get_message('std_msgs/msg/Float64MultiArray')()
    message.data = [float(index), 0.25 * index, -1.0]
    return message


MAKERS = {'odometry': ('nav_msgs/msg/Odometry', _odometry),
          'array': ('std_msgs/msg/Float64MultiArray', _array)}


def _qos(name: str):
    from rcbf_ros.ros.runtime import HistoryPolicy, qos_profile_sensor_data, QoSProfile
    if name == 'sensor':
        return qos_profile_sensor_data
    if name == 'keep_all':
        return QoSProfile(history=HistoryPolicy.KEEP_ALL)
    return QoSProfile(depth=10)


def role_publisher(kind: str, qos: str, topic: str, count: int, burst: bool) -> None:
    """Publish ``count`` messages once matched (a burst), or at 50 Hz until the peer leaves."""
    from rcbf_ros.ros.runtime import get_message, Node, rclpy
    rclpy.init(args=sys.argv)
    node = Node('test_publisher')
    type_name, make = MAKERS[kind]
    publisher = node.create_publisher(get_message(type_name), topic, _qos(qos))
    deadline = time.monotonic() + PEER_TIMEOUT_S
    try:
        # Both of the subscriber's subscriptions (raw and decoded) before the first message:
        # else the later one misses what the earlier one got, and the two lists do not pair.
        while (publisher.get_subscription_count() < SUBSCRIPTIONS
               and time.monotonic() < deadline):
            rclpy.spin_once(node, timeout_sec=0.02)
        if burst:
            for index in range(count):
                publisher.publish(make(index))
        index = 0
        while publisher.get_subscription_count() > 0 and time.monotonic() < deadline:
            if not burst:
                publisher.publish(make(index))
                index += 1
            rclpy.spin_once(node, timeout_sec=0.02)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def role_subscriber(kind: str, qos: str, topic: str, count: int, out: str) -> None:
    """Record ``count`` messages (raw CDR hex and decoded) to ``out`` as JSON, then exit."""
    from rcbf_ros.ros.runtime import deserialize_message, get_message, Node, rclpy
    rclpy.init(args=sys.argv)
    node = Node('test_subscriber')
    type_name, _ = MAKERS[kind]
    message_class = get_message(type_name)
    raw: list[str] = []
    decoded: list = []
    node.create_subscription(message_class, topic, lambda data: raw.append(data.hex()),
                             _qos(qos), raw=True)
    node.create_subscription(message_class, topic, decoded.append, _qos(qos))
    deadline = time.monotonic() + PEER_TIMEOUT_S
    try:
        while (len(raw) < count or len(decoded) < count) and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        topics = dict(node.get_topic_names_and_types())
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if kind == 'odometry':
        fields = [[m.header.stamp.sec, m.header.frame_id, m.child_frame_id,
                   m.pose.pose.position.x, list(m.pose.covariance), m.twist.twist.angular.z]
                  for m in decoded]
    else:
        fields = [list(m.data) for m in decoded]
    same = all(deserialize_message(bytes.fromhex(r), message_class) == m
               for r, m in zip(raw, decoded))
    Path(out).write_text(json.dumps({'raw': raw, 'fields': fields, 'raw_matches_decoded': same,
                                     'topics': topics}))


def role_spinner(ready: str, marker: str) -> None:
    """Spin a node with a timer; on exit ``finally`` writes the exception name to ``marker``."""
    from rcbf_ros.ros.runtime import ExternalShutdownException, Node, rclpy, USING_RCLPY
    rclpy.init(args=sys.argv)
    node = Node('test_spinner')

    def spinning() -> None:
        # Once: then the executor waits, where the signal finds it.
        timer.cancel()
        Path(ready).touch()

    timer = node.create_timer(0.01, spinning)
    # rclpy's SIGTERM handler wakes the executor before it shuts the context down: an executor
    # that finds the context still up waits again, and an idle node would wait forever. This
    # timer wakes it again (it does nothing).
    node.create_timer(0.1, lambda: None)
    outcome = 'returned'
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException) as exc:
        outcome = type(exc).__name__
    except Exception as exc:
        # Real rclpy's signal handler shuts the context down from its own thread; when that
        # lands while the executor makes its next wait set, rcl refuses the shut-down context
        # (a known race of rclpy's, discussed in ros2/ros2cli#854). Our nodes do not use that
        # handler (rcbf_ros.ros.node_main). Our runtime must never take this path.
        if not (USING_RCLPY and type(exc).__name__ == 'RCLError'
                and 'context is not valid' in str(exc)):
            raise
        outcome = 'context refused'
    finally:
        Path(marker).write_text(outcome)
        node.destroy_node()
        rclpy.try_shutdown()


# ----------------------------------------------------------------------------- harness
def _start(domain_id: int, *args: str) -> subprocess.Popen:
    return spawn(domain_id, __file__, *args)


def _finish(process: subprocess.Popen) -> None:
    try:
        stdout, stderr = process.communicate(timeout=PEER_TIMEOUT_S + 30)
    except subprocess.TimeoutExpired:
        process.kill()  # no peer outlives its test
        process.communicate()
        raise
    assert process.returncode == 0, f'peer failed ({process.returncode}):\n{stderr}{stdout}'


def _expected_cdr(kind: str, index: int) -> bytes:
    """The same message built with rosbags' own classes, serialized by rosbags."""
    import numpy as np
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    t = store.types
    if kind == 'array':
        message = t['std_msgs/msg/Float64MultiArray'](
            layout=t['std_msgs/msg/MultiArrayLayout'](dim=[], data_offset=0),
            data=np.array([float(index), 0.25 * index, -1.0]))
        return bytes(store.serialize_cdr(message, 'std_msgs/msg/Float64MultiArray'))
    vec = t['geometry_msgs/msg/Vector3']
    message = t['nav_msgs/msg/Odometry'](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](sec=index,
                                                                                  nanosec=0),
                                        frame_id=f'odom_{index}'),
        child_frame_id='base_link',
        pose=t['geometry_msgs/msg/PoseWithCovariance'](
            pose=t['geometry_msgs/msg/Pose'](
                position=t['geometry_msgs/msg/Point'](x=float(index), y=0.0, z=0.0),
                orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.arange(index, index + 36, dtype=np.float64)),
        twist=t['geometry_msgs/msg/TwistWithCovariance'](
            twist=t['geometry_msgs/msg/Twist'](linear=vec(x=0.0, y=0.0, z=0.0),
                                               angular=vec(x=0.0, y=0.0, z=-0.5 * index)),
            covariance=np.zeros(36)))
    return bytes(store.serialize_cdr(message, 'nav_msgs/msg/Odometry'))


def _run_pair(domain_id: int, tmp_path: Path, *, kind: str, qos: str, count: int, burst: bool,
              pub_args: list[str], sub_args: list[str]) -> dict:
    out = tmp_path / 'received.json'
    subscriber = _start(domain_id, 'subscriber', kind, qos, sub_args[0], str(count), str(out),
                        *sub_args[1:])
    publisher = _start(domain_id, 'publisher', kind, qos, pub_args[0], str(count),
                       'burst' if burst else 'stream', *pub_args[1:])
    _finish(subscriber)
    _finish(publisher)
    return json.loads(out.read_text())


@pytest.mark.integration
def test_default_qos_remapped_odometry_content_and_wire_bytes(ros_domain_id, tmp_path):
    # The subscriber asks for relative 'odom_in' in namespace /robot; a remap points it at the
    # publisher's absolute '/robot/odom'.
    received = _run_pair(
        ros_domain_id, tmp_path, kind='odometry', qos='default', count=5, burst=False,
        pub_args=['/robot/odom'],
        sub_args=['odom_in', '--ros-args', '-r', '__ns:=/robot', '-r', 'odom_in:=odom'])
    assert len(received['raw']) >= 5 and received['raw_matches_decoded']
    first = received['fields'][0][0]  # streamed: the subscriber may join mid-stream
    for offset, (raw, fields) in enumerate(zip(received['raw'][:5], received['fields'][:5])):
        index = first + offset
        assert bytes.fromhex(raw) == _expected_cdr('odometry', index)
        assert fields == [index, f'odom_{index}', 'base_link', float(index),
                          [float(index + k) for k in range(36)], -0.5 * index]
    assert received['topics']['/robot/odom'] == ['nav_msgs/msg/Odometry']


@pytest.mark.integration
def test_sensor_data_qos_float64_multi_array(ros_domain_id, tmp_path):
    received = _run_pair(ros_domain_id, tmp_path, kind='array', qos='sensor', count=5,
                         burst=False, pub_args=['state'], sub_args=['/state'])
    assert len(received['raw']) >= 5 and received['raw_matches_decoded']
    for raw, data in zip(received['raw'], received['fields']):
        index = int(data[0])
        assert data == [float(index), 0.25 * index, -1.0]
        assert bytes.fromhex(raw) == _expected_cdr('array', index)


@pytest.mark.integration
def test_keep_all_reliable_burst_arrives_complete_and_in_order(ros_domain_id, tmp_path):
    count = 2000
    received = _run_pair(ros_domain_id, tmp_path, kind='array', qos='keep_all', count=count,
                         burst=True, pub_args=['burst'], sub_args=['burst'])
    assert [int(data[0]) for data in received['fields']] == list(range(count))
    assert len(received['raw']) == count


@pytest.mark.integration
@pytest.mark.parametrize('signum, expected', [(signal.SIGTERM, 'ExternalShutdownException'),
                                              (signal.SIGINT, 'KeyboardInterrupt')])
def test_signal_to_spinning_node_runs_finally(ros_domain_id, tmp_path, signum, expected):
    ready, marker = tmp_path / 'ready', tmp_path / 'marker'
    spinner = _start(ros_domain_id, 'spinner', str(ready), str(marker))
    deadline = time.monotonic() + PEER_TIMEOUT_S
    while not ready.exists() and spinner.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ready.exists(), spinner.communicate()[1]
    spinner.send_signal(signum)
    _finish(spinner)
    outcome = marker.read_text()
    if signum == signal.SIGTERM and node_runtime() == 'rclpy':
        # Real rclpy: when the shutdown lands between its executor's wake-up and the check of
        # the context in rclpy.spin's loop, spin returns without raising; when it lands while
        # the executor makes its next wait set, rcl refuses the context (role_spinner). All
        # three are rclpy's (the last in about 1 of 14 runs here).
        assert outcome in (expected, 'returned', 'context refused')
    else:
        assert outcome == expected


if __name__ == '__main__':
    role, *rest = sys.argv[1:]
    if role == 'publisher':
        role_publisher(rest[0], rest[1], rest[2], int(rest[3]), rest[4] == 'burst')
    elif role == 'subscriber':
        role_subscriber(rest[0], rest[1], rest[2], int(rest[3]), rest[4])
    elif role == 'spinner':
        role_spinner(rest[0], rest[1])
    else:
        raise SystemExit(f'unknown role {role!r}')

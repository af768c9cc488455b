"""The safety_filter node with a LaserScan in a frame of its own, placed through tf, over real
Cyclone DDS (loopback).

The node runs as its own process with config/unicycle.yaml and one observation source,
``front`` (a LaserScan on /scan in frame ``laser``); the test publishes, as a robot would,
``/tf_static`` (base_link -> laser: the laser 0.3 m ahead of the base's centre, turned 90 deg
to the left, latched), ``/tf`` (odom -> base_link at the robot's pose, stamped now), the scans
(stamped now) and proposals that carry their own state, full speed ahead:

- scans before any transform: the fail-safe, the reason naming both frames;
- with the transforms, a wall 0.8 m ahead of the base (0.5 m to the laser's right): the
  proposal is slowed down, not stopped;
- /tf silent while the scans go on: the transform is too old for the scans' stamps, the
  fail-safe naming both frames;
- tf messages with a NaN translation, a zero quaternion or a stamp an hour ahead of the
  node's clock: refused and counted, never a traceback; the good transforms around them keep
  the robot moving.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

from dds_harness import stop  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import (
    _connect,
    _exchange,
    _handshake,
    _sections,
    _start_filter,
    _wait_matched,
    Probe,
)

pytestmark = pytest.mark.integration

SOURCE = ('-p', 'observation_sources:=[front]', '-p', 'front.type:=scan',
          '-p', 'front.topic:=/scan', '-p', 'front.timeout_s:=1.0',
          '-p', 'footprint.radius:=0.2')
STATE = [2.0, 0.0, 0.0]
"""Clear of every obstacle of config/unicycle.yaml, heading away from them."""
AHEAD = {'u': [2.5, 0.0], 'state': STATE}
MOUNT_X = 0.3
"""The laser's place on base_link (m ahead of the centre); it looks 90 deg to the left."""


def _stamp(t: Any, now: int) -> Any:
    return t['builtin_interfaces/msg/Time'](sec=now // 10**9, nanosec=now % 10**9)


def _tf(parent: str, child: str, translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0),
        ahead_ns: int = 0) -> bytes:
    """A TFMessage of one transform stamped now (and ``ahead_ns`` on; rosbags' encoder)."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    transform = t['geometry_msgs/msg/TransformStamped'](
        header=t['std_msgs/msg/Header'](stamp=_stamp(t, time.time_ns() + ahead_ns),
                                        frame_id=parent),
        child_frame_id=child, transform=t['geometry_msgs/msg/Transform'](
            translation=t['geometry_msgs/msg/Vector3'](*map(float, translation)),
            rotation=t['geometry_msgs/msg/Quaternion'](*map(float, rotation))))
    msg = t['tf2_msgs/msg/TFMessage'](transforms=[transform])
    return bytes(store.serialize_cdr(msg, 'tf2_msgs/msg/TFMessage'))


def _wall_scan() -> bytes:
    """A LaserScan in ``laser`` stamped now: a wall 0.8 m ahead of the base is, to the laser
    turned left at MOUNT_X, the line y = -(0.8 - MOUNT_X) of its frame, on beams around
    -90 deg."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    angle_min, increment, count = -math.pi / 2 - 0.5, 0.01, 101
    angles = angle_min + increment * np.arange(count)
    ranges = (0.8 - MOUNT_X) / -np.sin(angles)
    msg = t['sensor_msgs/msg/LaserScan'](
        header=t['std_msgs/msg/Header'](stamp=_stamp(t, time.time_ns()), frame_id='laser'),
        angle_min=angle_min, angle_max=angle_min + increment * (count - 1),
        angle_increment=increment, time_increment=0.0, scan_time=0.1, range_min=0.05,
        range_max=10.0, ranges=ranges.astype(np.float32), intensities=np.zeros(0, np.float32))
    return bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/LaserScan'))


def _odom() -> bytes:
    """odom -> base_link at the robot's pose (STATE), stamped now."""
    x, y, yaw = STATE
    return _tf('odom', 'base_link', (x, y, 0.0), (0.0, 0.0, math.sin(yaw / 2),
                                                   math.cos(yaw / 2)))


def _answer(probe: Probe, publish: list[tuple[Any, Any]], proposal_pub: Any, proposal: Any,
            done: Callable[[int, str], bool]) -> tuple[Any, tuple[int, str, dict[str, str]]]:
    """Publish each (publisher, () -> bytes) of ``publish``, then the proposal; repeat until
    ``done(level, reason)`` of the answer (a sample may be lost until a reader matches)."""
    for _ in range(50):
        for publisher, make in publish:
            publisher.publish(make())
        time.sleep(0.1)
        command, diagnostic = _exchange(probe, proposal_pub, proposal)
        if done(diagnostic[0], diagnostic[1]):
            return command, diagnostic
    raise AssertionError(f'the answers kept saying {diagnostic[1]!r}')


def _placed(level: int, reason: str) -> bool:
    """The source's points were used (its messages and transforms arrived)."""
    return not reason.startswith('source front: ')


def test_a_scan_in_the_laser_frame_is_placed_through_tf(ros_domain_id):
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.runtime import (
        DurabilityPolicy,
        get_message,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
        USING_RCLPY,
    )
    probe = Probe(ros_domain_id)
    process = _start_filter(ros_domain_id, *SOURCE)
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        scan_pub = probe.publisher('sensor_msgs/msg/LaserScan', '/scan')
        tf_type = get_message('tf2_msgs/msg/TFMessage')
        tf_pub = probe.node.create_publisher(tf_type, '/tf', QoSProfile(
            depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE))
        static_pub = probe.node.create_publisher(tf_type, '/tf_static', QoSProfile(
            depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        proposal_pub, _ = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                   with_state=False)
        for publisher in (scan_pub, tf_pub, static_pub):
            _wait_matched(publisher, process)
        ahead = sections_to_msg(AHEAD)
        _handshake(probe, proposal_pub, ahead)
        untransformed = _answer(probe, [(scan_pub, _wall_scan)], proposal_pub, ahead,
                                lambda _, reason: 'no message yet' not in reason)
        static_pub.publish(_tf('base_link', 'laser', (MOUNT_X, 0.0, 0.2),
                               (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))))
        walled = _answer(probe, [(tf_pub, _odom), (scan_pub, _wall_scan)], proposal_pub, ahead,
                         _placed)
        stale = _answer(probe, [(scan_pub, _wall_scan)], proposal_pub, ahead,
                        lambda level, _: level == 2)
        hostile = _answer(probe, [
            (tf_pub, lambda: _tf('odom', 'base_link', (math.nan, 0.0, 0.0))),
            (tf_pub, lambda: _tf('odom', 'base_link', rotation=(0.0, 0.0, 0.0, 0.0))),
            (tf_pub, lambda: _tf('odom', 'base_link', ahead_ns=3_600 * 10**9)),
            (tf_pub, _odom), (scan_pub, _wall_scan)], proposal_pub, ahead, _placed)
        process_alive = process.poll() is None
    finally:
        output = stop(process, timeout=10)
        probe.close()
    assert process_alive, output[-4000:]
    command, (level, message, _) = untransformed
    assert level == 2 and message.startswith(
        "source front: frame 'laser' is placed neither in the state's 'odom' nor in the "
        "robot's 'base_link' by tf"), message
    np.testing.assert_array_equal(command['u'], [0.0, 0.0])
    command, (level, message, values) = walled
    assert level == 0 and values['fail_safe'] == 'False', message
    assert 0.0 <= command['u'][0] < 1.5, command          # slowed for the wall, not refused
    command, (level, message, values) = stale
    assert level == 2 and message.startswith(
        "source front: no transform from 'laser' to 'odom' at "), message
    # our buffer names the link; tf2_ros's (on rclpy) the chain's newest time
    assert ("'odom' -> 'base_link' too old" in message
            or USING_RCLPY and ': too old: the newest is at ' in message), message
    assert int(values['front.untransformed']) >= 2
    np.testing.assert_array_equal(command['u'], [0.0, 0.0])
    command, (level, message, values) = hostile
    assert level == 0 and 0.0 <= command['u'][0] < 1.5, message
    # NaN, zero quaternion, an hour ahead of the node's clock: each refused (the good odom
    # after them is read, and /tf is read in order)
    assert int(values['tf.transforms_refused']) >= 3, values
    assert int(values['tf.messages']) >= 5 and int(values['tf.refused']) == 0, values
    assert 'Traceback' not in output, output[-4000:]
    assert "/tf refused: transforms[0] 'odom' -> 'base_link': translation (nan" in output
    assert ('tf: tf2_ros Buffer and TransformListener' if USING_RCLPY else
            "tf: the filter's own buffer on /tf and /tf_static (the Cyclone runtime)") in output

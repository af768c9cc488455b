"""The safety_filter node with a LaserScan source, over real Cyclone DDS (loopback).

The node runs as its own process with config/unicycle.yaml and one observation source,
``front`` (a LaserScan on /scan, timeout 1 s, footprint radius 0.2 m); the test publishes the
scans (encoded by rosbags, stamped now) and proposals that carry their own state, 2 m clear of
every obstacle of the config, full speed ahead:

- before any scan: the fail-safe, the reason naming the source;
- a scan showing a wall 0.8 m ahead: the proposal is slowed down, not stopped;
- no scan for longer than the timeout: the fail-safe, naming the source;
- hostile scans (NaN geometry, more beams than the bound, angles beyond the bound, flipped
  bytes): each refused in one line and counted, the fail-safe meanwhile, no traceback; a good
  scan afterwards is used again.
"""
from __future__ import annotations

from collections.abc import Iterator
import contextlib
import math
import time
from typing import Any

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
    UNICYCLE,
)

pytestmark = pytest.mark.integration

SOURCE = ('-p', 'observation_sources:=[front]', '-p', 'front.type:=scan',
          '-p', 'front.topic:=/scan', '-p', 'front.timeout_s:=1.0',
          '-p', 'footprint.radius:=0.2')
STATE = [2.0, 0.0, 0.0]
"""Clear of every obstacle of config/unicycle.yaml, heading away from them."""
AHEAD = {'u': [2.5, 0.0], 'state': STATE}


def _encoded(type_name: str, frame_id: str = 'base_link', **fields: Any) -> bytes:
    """A ``type_name`` message with ``fields``, its header in ``frame_id`` stamped now
    (rosbags' encoder)."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    now = time.time_ns()
    header = t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
        sec=now // 10**9, nanosec=now % 10**9), frame_id=frame_id)
    return bytes(store.serialize_cdr(t[type_name](header=header, **fields), type_name))


def _scan(ranges: Any, *, angle_min: float = -0.5, increment: float = 0.01,
          range_min: float = 0.05, range_max: float = 10.0) -> bytes:
    """A LaserScan in base_link stamped now."""
    return _encoded(
        'sensor_msgs/msg/LaserScan',
        angle_min=angle_min, angle_max=angle_min + increment * (len(ranges) - 1),
        angle_increment=increment, time_increment=0.0, scan_time=0.1, range_min=range_min,
        range_max=range_max, ranges=np.asarray(ranges, np.float32),
        intensities=np.zeros(0, np.float32))


def _wall(distance: float = 0.8) -> bytes:
    """A straight wall ``distance`` ahead across 101 beams of -0.5..0.5 rad."""
    angles = -0.5 + 0.01 * np.arange(101)
    return _scan(distance / np.cos(angles))


def _answer_after_scan(probe: Probe, scan_pub: Any, proposal_pub: Any, scan: bytes,
                       proposal: Any) -> tuple[Any, tuple[int, str, dict[str, str]]]:
    """Publish ``scan`` and then the proposal until the answer's reason is no longer the
    missing-scan one (a sample may be lost until the reader matches)."""
    for _ in range(50):
        scan_pub.publish(scan)
        time.sleep(0.1)
        command, diagnostic = _exchange(probe, proposal_pub, proposal)
        if 'no message yet' not in diagnostic[1]:
            return command, diagnostic
    raise AssertionError('the scan never reached the filter')


@contextlib.contextmanager
def _source_run(ros_domain_id: int, args: tuple[str, ...], message_type: str, topic: str
                ) -> Iterator[tuple[Probe, Any, Any, Any]]:
    """The filter started with ``args``, matched with a probe that publishes
    ``message_type`` on ``topic`` and proposals (AHEAD, carrying their state), after the first
    answer: (probe, source publisher, proposal publisher, the proposal). On leaving, the node
    must still run, and it must not have printed a traceback."""
    from rcbf_ros.messages.conversions import sections_to_msg
    probe = Probe(ros_domain_id)
    process = _start_filter(ros_domain_id, *args)
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        source_pub = probe.publisher(message_type, topic)
        proposal_pub, _ = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                   with_state=False)
        _wait_matched(source_pub, process)
        ahead = sections_to_msg(AHEAD)
        _handshake(probe, proposal_pub, ahead)
        yield probe, source_pub, proposal_pub, ahead
        process_alive = process.poll() is None
    finally:
        output = stop(process, timeout=10)
        probe.close()
    assert process_alive, output[-4000:]
    assert 'Traceback' not in output, output[-4000:]


def test_a_scan_source_slows_the_robot_and_fails_safe_without_fresh_scans(ros_domain_id):
    with _source_run(ros_domain_id, SOURCE, 'sensor_msgs/msg/LaserScan', '/scan') as (
            probe, scan_pub, proposal_pub, ahead):
        no_scan = _exchange(probe, proposal_pub, ahead)
        walled = _answer_after_scan(probe, scan_pub, proposal_pub, _wall(), ahead)
        time.sleep(1.5)                                   # longer than front.timeout_s
        stale = _exchange(probe, proposal_pub, ahead)
        hostile = []
        for scan in (_scan([1.0, 2.0], range_min=math.nan),
                     _scan(np.ones(200_001)),
                     _scan([1.0], angle_min=3.0e38),
                     _scan([1.0] * 10, increment=1.0e37)):
            hostile.append(_answer_after_scan(probe, scan_pub, proposal_pub, scan, ahead))
        rng = np.random.default_rng(7)
        flipped = 0
        for _ in range(40):                               # flipped bytes of a valid scan
            data = bytearray(_wall())
            for where in rng.integers(4, len(data), 3):
                data[where] = int(rng.integers(0, 256))
            try:
                scan_pub.publish(bytes(data))
                flipped += 1
            except RuntimeError:                          # the writer refuses malformed CDR
                pass
        time.sleep(0.5)
        again = _answer_after_scan(probe, scan_pub, proposal_pub, _wall(), ahead)
    level, message, values = no_scan[1]
    assert level == 2 and message.startswith('source front: no message yet on /scan'), message
    np.testing.assert_array_equal(no_scan[0]['u'], [0.0, 0.0])
    command, (level, message, values) = walled
    assert level == 0 and values['fail_safe'] == 'False', message
    assert 0.0 <= command['u'][0] < 1.5, command          # slowed for the wall, not refused
    command, (level, message, values) = stale
    assert level == 2 and message.startswith('source front: latest message'), message
    assert 'front.timeout_s 1' in message
    for index, (command, (level, message, _)) in enumerate(hostile):
        assert level == 2 and message.startswith('source front: latest message refused'), (
            index, message)
        np.testing.assert_array_equal(command['u'], [0.0, 0.0])
    command, (level, message, values) = again
    assert level == 0 and 0.0 <= command['u'][0] < 1.5, message
    assert int(values['front.refused']) >= len(hostile)
    assert int(values['front.messages']) >= 2 + len(hostile)
    assert int(values['front.stale']) >= 2


CLOUD = ('-p', 'observation_sources:=[cloud]', '-p', 'cloud.type:=pointcloud',
         '-p', 'cloud.topic:=/points', '-p', 'cloud.timeout_s:=1.0',
         '-p', 'cloud.min_height:=0.05', '-p', 'cloud.max_height:=0.5',
         '-p', 'footprint.radius:=0.2')


def _cloud(points: np.ndarray, frame_id: str = 'base_link') -> bytes:
    """A PointCloud2 of (N, 3) float32 x, y, z in ``frame_id`` stamped now."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    field = jazzy_typestore().types['sensor_msgs/msg/PointField']
    data = np.ascontiguousarray(points, dtype='<f4')
    return _encoded(
        'sensor_msgs/msg/PointCloud2', frame_id,
        height=1, width=len(data),
        fields=[field(name=name, offset=4 * k, datatype=7, count=1)
                for k, name in enumerate('xyz')],
        is_bigendian=False, point_step=12, row_step=12 * len(data),
        data=data.view(np.uint8).ravel(), is_dense=True)


def _cloud_wall(distance: float = 0.8) -> bytes:
    """A wall ``distance`` ahead, 4 m wide, from the floor (out of the z band) to 1 m."""
    y, z = np.meshgrid(np.linspace(-2.0, 2.0, 81), np.linspace(0.0, 1.0, 21))
    return _cloud(np.stack([np.full(y.size, distance), y.ravel(), z.ravel()], axis=1))


def test_a_pointcloud_source_slows_the_robot_before_a_wall(ros_domain_id):
    with _source_run(ros_domain_id, CLOUD, 'sensor_msgs/msg/PointCloud2', '/points') as (
            probe, cloud_pub, proposal_pub, ahead):
        no_cloud = _exchange(probe, proposal_pub, ahead)
        walled = _answer_after_scan(probe, cloud_pub, proposal_pub, _cloud_wall(), ahead)
        floor = _answer_after_scan(  # the same wall below the z band: nothing in the way
            probe, cloud_pub, proposal_pub,
            _cloud(np.array([[0.8, y, 0.01] for y in np.linspace(-2.0, 2.0, 81)])), ahead)
    level, message, _ = no_cloud[1]
    assert level == 2 and message.startswith('source cloud: no message yet on /points'), message
    command, (level, message, values) = walled
    assert level == 0 and values['fail_safe'] == 'False', message
    assert 0.0 <= command['u'][0] < 1.5, command          # slowed for the wall, not refused
    command, (level, message, values) = floor
    assert level == 0 and values['fail_safe'] == 'False', message
    np.testing.assert_array_equal(command['u'], AHEAD['u'])
    assert int(values['cloud.messages']) >= 2 and int(values['cloud.refused']) == 0


RANGE = ('-p', 'observation_sources:=[sonar]', '-p', 'sonar.type:=range',
         '-p', 'sonar.topic:=/sonar', '-p', 'sonar.timeout_s:=1.0',
         '-p', 'footprint.radius:=0.2')


def _range(reading: float, field_of_view: float = 0.5) -> bytes:
    """A sensor_msgs/Range in base_link stamped now."""
    return _encoded('sensor_msgs/msg/Range', radiation_type=0, field_of_view=field_of_view,
                    min_range=0.02, max_range=4.0, range=reading, variance=0.0)


def test_a_range_source_slows_the_robot_before_what_its_sonar_sees(ros_domain_id):
    with _source_run(ros_domain_id, RANGE, 'sensor_msgs/msg/Range', '/sonar') as (
            probe, range_pub, proposal_pub, ahead):
        near = _answer_after_scan(probe, range_pub, proposal_pub, _range(0.8), ahead)
        clear = _answer_after_scan(probe, range_pub, proposal_pub, _range(math.inf), ahead)
        for _ in range(50):  # until the refused reading is in (a sample may be lost)
            hostile = _answer_after_scan(probe, range_pub, proposal_pub,
                                         _range(0.8, field_of_view=math.nan), ahead)
            if 'refused' in hostile[1][1]:
                break
    command, (level, message, values) = near
    assert level == 0 and values['fail_safe'] == 'False', message
    assert 0.0 <= command['u'][0] < 1.5, command  # slowed for the arc, not refused
    command, (level, message, values) = clear  # +inf: nothing within range
    assert level == 0 and values['fail_safe'] == 'False', message
    np.testing.assert_array_equal(command['u'], AHEAD['u'])
    command, (level, message, values) = hostile
    assert level == 2 and message.startswith(
        'source sonar: latest message refused: sensor_msgs/msg/Range: field_of_view nan'), message
    assert int(values['sonar.refused']) >= 1


def test_a_robot_with_only_a_lidar_runs_without_static_obstacles(ros_domain_id, tmp_path):
    """config/unicycle.yaml without its obstacles' centres and radii: the scan's points are
    the filter's only rows."""
    import yaml

    from rcbf_ros.messages.conversions import sections_to_msg
    with open(UNICYCLE) as stream:
        document = yaml.safe_load(stream)
    for node in document.values():
        geometry = node['ros__parameters'].get('obstacles', {})
        for key in ('x', 'y', 'radius'):
            geometry.pop(key, None)
    params_file = tmp_path / 'lidar_only.yaml'
    params_file.write_text(yaml.safe_dump(document))
    probe = Probe(ros_domain_id)
    process = _start_filter(ros_domain_id, *SOURCE, params_file=str(params_file))
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        scan_pub = probe.publisher('sensor_msgs/msg/LaserScan', '/scan')
        proposal_pub, _ = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                   with_state=False)
        _wait_matched(scan_pub, process)
        # where config/unicycle.yaml's centre obstacle stood: gone with its parameters
        ahead = sections_to_msg({'u': [2.5, 0.0], 'state': [-1.0, 0.0, 0.0]})
        _handshake(probe, proposal_pub, ahead)
        no_scan = _exchange(probe, proposal_pub, ahead)
        walled = _answer_after_scan(probe, scan_pub, proposal_pub, _wall(), ahead)
        open_space = _answer_after_scan(probe, scan_pub, proposal_pub,
                                        _scan([math.inf] * 101), ahead)
        process_alive = process.poll() is None
    finally:
        output = stop(process, timeout=10)
        probe.close()
    assert process_alive, output[-4000:]
    level, message, _ = no_scan[1]
    assert level == 2 and message.startswith('source front: no message yet'), message
    command, (level, message, values) = walled
    assert level == 0 and 0.0 <= command['u'][0] < 1.5, message
    assert [key for key in values if key.startswith('h.')] == ['h.sensor_points'], values
    command, (level, message, _) = open_space
    assert level == 0, message
    np.testing.assert_array_equal(command['u'], [2.5, 0.0])
    assert 'Traceback' not in output, output[-4000:]

"""The scene_markers node as a separate process over real Cyclone DDS (loopback).

- a state and the filter's diagnostics in: a MarkerArray out, in the configured frame, with the
  robot at that state and the margin rings coloured by the reported barrier values;
- invalid parameters: the process exits with status 2 and names the key.
"""
from __future__ import annotations

import subprocess
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
    """An in-process node: publishes state and diagnostics, keeps every MarkerArray."""

    def __init__(self, domain_id: int) -> None:
        from rcbf_ros.ros.runtime import get_message, Node, QoSProfile, rclpy
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node = Node('scene_probe')
        qos = QoSProfile(depth=100)
        self.arrays: list[Any] = []
        self.lock = threading.Lock()
        self.node.create_subscription(get_message('visualization_msgs/msg/MarkerArray'),
                                      '/scene_markers', self._store, qos)
        self.state_pub = self.node.create_publisher(
            get_message('std_msgs/msg/Float64MultiArray'), '/state', qos)
        self.diagnostics_pub = self.node.create_publisher(
            get_message('diagnostic_msgs/msg/DiagnosticArray'), '/diagnostics', qos)
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _store(self, msg: Any) -> None:
        with self.lock:
            self.arrays.append(msg)

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def publish_until(self, publish, accept, process: subprocess.Popen) -> Any:
        """Publish (again every 0.3 s: the first samples may precede the match) until a
        MarkerArray that ``accept`` takes arrives; return it. Only arrays that arrive from
        now on count (one that came before was made without this publish)."""
        deadline = time.monotonic() + WAIT_S
        with self.lock:
            seen = len(self.arrays)
        while time.monotonic() < deadline:
            assert process.poll() is None, stop(process, timeout=10)
            publish()
            time.sleep(0.3)
            with self.lock:
                fresh, seen = self.arrays[seen:], len(self.arrays)
            for msg in fresh:
                if accept(msg):
                    return msg
        raise AssertionError(f'no accepted MarkerArray within {WAIT_S} s ({seen} arrived)')

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def _by_ns(msg: Any, ns: str) -> list[Any]:
    return sorted((m for m in msg.markers if m.ns == ns), key=lambda m: m.id)


def test_state_and_diagnostics_in_markers_out(domain_id):
    from rcbf_ros.messages.conversions import diagnostic_status, sections_to_msg
    from rcbf_ros.node_logic.scene import AMBER, GREEN, RED
    from rcbf_ros.ros.runtime import get_message
    process = spawn(domain_id, '-m', 'rcbf_ros.ros.scene_node', '--ros-args',
                    '--params-file', UNICYCLE, '-p', 'frame_id:=odom', '-p', 'rate_hz:=20.0')
    probe = _Probe(domain_id)
    try:
        state = sections_to_msg({'state': [-1.0, 0.5, 0.25]})
        first = probe.publish_until(
            lambda: probe.state_pub.publish(state),
            lambda msg: any(m.ns == 'robot' for m in msg.markers), process)
        diagnostics = get_message('diagnostic_msgs/msg/DiagnosticArray')()
        diagnostics.status = [diagnostic_status(
            name='safety_filter', level=0, message='filtering',
            values={'h.obstacle_0': -0.5, 'h.obstacle_1': 0.05, 'h.obstacle_2': 2.0,
                    'h.obstacle_3': 2.0, 'h.obstacle_4': 2.0, 'min_h': -0.5})]
        coloured = probe.publish_until(
            lambda: probe.diagnostics_pub.publish(diagnostics),
            lambda msg: any(m.ns == 'status' for m in msg.markers), process)
    finally:
        probe.close()
        output = stop(process, timeout=10)
    assert 'unicycle: 5 obstacles, 5 barriers' in output, output[-2000:]
    for msg in (first, coloured):
        assert {m.header.frame_id for m in msg.markers} == {'odom'}
        assert len(_by_ns(msg, 'obstacles')) == 5 and len(_by_ns(msg, 'margins')) == 5
        (arrow,) = _by_ns(msg, 'robot')
        assert (arrow.pose.position.x, arrow.pose.position.y) == (-1.0, 0.5)
    rings = [m.color for m in _by_ns(coloured, 'margins')]
    for colour, expected in zip(rings, (RED, AMBER, GREEN)):
        assert (colour.r, colour.g, colour.b) == pytest.approx(expected[:3], abs=1e-6)
    texts = _by_ns(coloured, 'barriers')
    assert texts[0].text == 'obstacle_0  h = -0.500'
    assert _by_ns(coloured, 'status')[0].text == 'filtering'


@pytest.mark.parametrize('args, key', [
    (['--params-file', UNICYCLE, '-p', 'caution_h:=-1.0'], 'caution_h: must be >= 0'),
    (['--params-file', UNICYCLE, '-p', 'obstacles.y:=[0.0]'], 'obstacles.y'),
    ([], 'system: required'),
    (['--params-file', str(REPO / 'config' / 'unicycle_lidar.yaml'), '-p', 'frame_id:=map'],
     "frame_id: 'map' is not odom_frame_id 'odom'"),
])
def test_invalid_parameters_exit_2_naming_the_key(domain_id, args, key):
    process = spawn(domain_id, '-m', 'rcbf_ros.ros.scene_node', '--ros-args', *args)
    try:
        process.wait(timeout=WAIT_S)
    finally:
        output = stop(process, timeout=10)
    assert process.returncode == 2, output[-2000:]
    assert f'scene_markers: invalid parameters: {key}' in output
    assert 'Traceback' not in output


def test_the_obstacles_topic_replaces_the_drawn_obstacles(domain_id):
    """A latched obstacle set published before the node starts is drawn (transient-local);
    a new set replaces it (a DELETEALL first, so no old disc stays in the viewer); a bad one
    is an ERROR and the drawn set stays."""
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.runtime import (
        DurabilityPolicy,
        get_message,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
    )
    probe = _Probe(domain_id)
    array = get_message('std_msgs/msg/Float64MultiArray')
    obstacles_pub = probe.node.create_publisher(array, '/obstacles', QoSProfile(
        depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    obstacles_pub.publish(array(data=[1.0, 2.0, 0.5, 3.0, 4.0, 0.25]))  # before the node exists
    process = spawn(domain_id, '-m', 'rcbf_ros.ros.scene_node', '--ros-args',
                    '--params-file', UNICYCLE, '-p', 'rate_hz:=20.0')
    try:
        state = sections_to_msg({'state': [-1.0, 0.5, 0.25]})
        latched = probe.publish_until(
            lambda: probe.state_pub.publish(state),
            lambda msg: len(_by_ns(msg, 'obstacles')) == 2, process)
        replaced = probe.publish_until(
            lambda: obstacles_pub.publish(array(data=[-2.0, 0.0, 0.75])),
            lambda msg: len(_by_ns(msg, 'obstacles')) == 1, process)
        obstacles_pub.publish(array(data=[-2.0, 0.0]))
        time.sleep(0.5)
        with probe.lock:
            before = len(probe.arrays)
        probe.state_pub.publish(sections_to_msg({'state': [-1.0, 0.0, 0.0]}))
        kept = None
        deadline = time.monotonic() + WAIT_S
        while kept is None and time.monotonic() < deadline:
            time.sleep(0.1)
            with probe.lock:
                kept = probe.arrays[before] if len(probe.arrays) > before else None
        assert process.poll() is None
    finally:
        probe.close()
        output = stop(process, timeout=10)
    assert [(m.pose.position.x, m.pose.position.y) for m in _by_ns(latched, 'obstacles')] == [
        (1.0, 2.0), (3.0, 4.0)]
    assert replaced.markers[0].action == 3  # DELETEALL before the new set
    assert [(m.pose.position.x, m.scale.x) for m in _by_ns(replaced, 'obstacles')] == [
        (-2.0, 1.5)]
    assert [m.pose.position.x for m in _by_ns(kept, 'obstacles')] == [-2.0]
    assert 'obstacles message refused, the obstacles drawn are unchanged: obstacles: data' in \
        output, output[-2000:]


def test_filter_info_binding_points_are_drawn_and_a_bad_sample_is_skipped(domain_id):
    """A filter_info with binding_points over DDS: a sphere per point and a line to each one
    that binds, with the footprint ring; a sample whose section holds a NaN: one warning, the
    node goes on and the drawn points stay."""
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.runtime import get_message, QoSProfile
    process = spawn(domain_id, '-m', 'rcbf_ros.ros.scene_node', '--ros-args',
                    '--params-file', UNICYCLE, '-p', 'rate_hz:=20.0', '-p',
                    'footprint.radius:=0.25')
    probe = _Probe(domain_id)
    info_pub = probe.node.create_publisher(get_message('std_msgs/msg/Float64MultiArray'),
                                           '/filter_info', QoSProfile(depth=10))
    rows = [1.0, 0.5, 0.0, 0.2, -1.0, 2.0, 0.4, 1.0]  # [x, y, row value, h]: binds, does not
    head = {'u': [0.0, 0.0], 'u_rl': [0.0, 0.0], 'u_s': [0.0, 0.0], 'fail_safe': [0.0],
            'status': [0.0]}
    try:
        state = sections_to_msg({'state': [-1.0, 0.5, 0.0]})
        good = sections_to_msg({**head, 'binding_points': rows})

        def publish() -> None:
            probe.state_pub.publish(state)
            info_pub.publish(good)
        drawn = probe.publish_until(
            publish, lambda msg: any(m.ns == 'binding_points' and m.points
                                     for m in msg.markers), process)
        bad = sections_to_msg({**head, 'binding_points': [1.0, 0.5, float('nan'), 0.2]})
        with probe.lock:
            seen = len(probe.arrays)
        kept = probe.publish_until(
            lambda: (info_pub.publish(bad), probe.state_pub.publish(state)),
            lambda msg: True, process)
        with probe.lock:
            later = probe.arrays[seen:]
        time.sleep(0.5)
        assert process.poll() is None
    finally:
        probe.close()
        output = stop(process, timeout=10)
    (spheres,) = _by_ns(drawn, 'binding_points')
    assert [(p.x, p.y) for p in spheres.points] == [(1.0, 0.5), (-1.0, 2.0)]
    (lines,) = _by_ns(drawn, 'active_rows')
    assert [(p.x, p.y) for p in lines.points] == [(-1.0 + 0.03, 0.5), (1.0, 0.5)]
    assert len(_by_ns(drawn, 'footprint')) == 1
    for msg in [kept, *later]:  # the bad sample changed nothing drawn
        assert [(p.x, p.y) for p in _by_ns(msg, 'binding_points')[0].points] == [
            (1.0, 0.5), (-1.0, 2.0)]
    assert 'filter_info: binding_points: contains NaN or inf; sample skipped' in output, \
        output[-2000:]
    assert 'Traceback' not in output

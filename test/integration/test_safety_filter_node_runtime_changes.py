"""The safety_filter's gains and obstacles change while it runs, over real Cyclone DDS (loopback).

- ``obstacles`` topic (a separate filter process): moving an obstacle in front of the robot
  makes the filter correct a proposal it passed before; a malformed message is an ERROR that
  names the field, the node lives on and keeps the obstacles it had;
- parameters (the filter node in this process, its parameter calls made in its own spin
  thread, between message callbacks, as a parameter service runs them): a valid ``k_c`` shows
  in the rows the diagnostics report; an invalid one is refused with a reason naming the key,
  and the answers stay exactly what they were.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

from dds_harness import REPO, spawn, stop  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import (
    _diagnostic,
    _exchange,
    _exchange_with_state,
    _handshake,
    _sections,
    _wait_matched,
    EVERY_DIAGNOSTIC,
    Probe,
)

UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
AHEAD = [2.0, 0.0, 0.0]  # heading +x: no obstacle of unicycle.yaml in the way
UNSAFE = {'u': [2.5, 0.0]}
# unicycle.yaml's obstacles with the first one moved from the origin to 0.85 m ahead of AHEAD
MOVED = [2.85, 0.0, 0.6, -1.5, 1.5, 0.6, -1.5, -1.5, 0.6, 1.5, -1.5, 0.6, 1.5, 1.5, 0.6]

pytestmark = pytest.mark.integration


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def _obstacles_publisher(probe: Probe) -> Any:
    from rcbf_ros.ros.runtime import (
        DurabilityPolicy,
        get_message,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
    )
    qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return probe.node.create_publisher(get_message('std_msgs/msg/Float64MultiArray'),
                                       '/obstacles', qos)


def _array(values: list[float]) -> Any:
    from rcbf_ros.ros.runtime import get_message
    return get_message('std_msgs/msg/Float64MultiArray')(data=values)


def _until(answer: Callable[[], tuple[Any, Any]], accept: Callable[[Any, Any], bool]
           ) -> tuple[Any, Any]:
    """Exchange proposals until ``accept(command, diagnostic)`` (a change needs a moment)."""
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        command, diagnostic = answer()
        if accept(command, diagnostic):
            return command, diagnostic
        time.sleep(0.1)
    raise AssertionError(f'no accepted answer within 30 s; last {command}, {diagnostic}')


def test_obstacles_topic_moves_an_obstacle_and_a_bad_message_changes_nothing(
        ros_domain_id, probe):
    from rcbf_ros.messages.conversions import sections_to_msg
    process = spawn(ros_domain_id, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
                    '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC)
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        probe.subscribe('diagnostic_msgs/msg/DiagnosticArray', '/diagnostics', _diagnostic)
        state_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/state')
        proposal_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/cmd_proposed')
        obstacles_pub = _obstacles_publisher(probe)
        probe.start()
        _wait_matched(proposal_pub, process)
        _wait_matched(state_pub, process)
        _wait_matched(obstacles_pub, process)
        _handshake(probe, proposal_pub, sections_to_msg(UNSAFE))
        free, _ = _exchange_with_state(probe, state_pub, AHEAD, proposal_pub,
                                       sections_to_msg(UNSAFE))

        def answer() -> tuple[Any, Any]:
            state_pub.publish(sections_to_msg({'state': AHEAD}))
            time.sleep(0.05)
            return _exchange(probe, proposal_pub, sections_to_msg(UNSAFE))

        obstacles_pub.publish(_array(MOVED))
        braked, (level, _, values) = _until(answer, lambda c, d: c['u'][0] < 2.5)
        # Keep-last 1: the node sees only the latest set, so each bad one gets its time.
        obstacles_pub.publish(_array(MOVED[:-1]))   # 14 values: not rows of [x, y, radius]
        time.sleep(1.0)
        obstacles_pub.publish(_array([2.85, 0.0, -0.6]))  # a negative radius
        time.sleep(1.0)
        after_bad, (after_level, _, after_values) = answer()
        assert process.poll() is None
    finally:
        output = stop(process, timeout=10)
    np.testing.assert_array_equal(free['u'], [2.5, 0.0])   # nothing ahead: passed through
    assert level == 0 and 0.0 <= braked['u'][0] < 2.5      # the moved obstacle: braked
    assert float(values['h.obstacle_0']) == pytest.approx(0.82 ** 2 - 0.7 ** 2)
    np.testing.assert_allclose(after_bad['u'], braked['u'], atol=1e-6)  # the moved set stayed
    assert after_level == 0 and after_values['h.obstacle_0'] == values['h.obstacle_0']
    assert 'filter updated from the obstacles topic: obstacles.x' in output, output[-3000:]
    errors = [line for line in output.splitlines() if '[ERROR]' in line]
    assert any('obstacles message refused' in line and 'data' in line for line in errors)
    assert any('obstacles message refused' in line and 'obstacles.radius' in line
               for line in errors), errors
    assert 'Traceback' not in output


class _InProcessFilter:
    """A SafetyFilterNode in this process, spun in its own thread; parameter calls go through
    :meth:`call`, run in that thread between two message callbacks."""

    def __init__(self, *extra: str) -> None:
        from rcbf_ros.ros.runtime import rclpy
        from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
        self.rclpy = rclpy
        self.node = SafetyFilterNode(
            cli_args=['--ros-args', '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC, *extra])
        self._calls: queue.Queue = queue.Queue()
        self._running = True
        # The probe spins rclpy's global executor in a thread of its own; an executor is not
        # to be shared between threads, so on rclpy this node gets one of its own.
        from rcbf_ros.ros.runtime import USING_RCLPY
        if USING_RCLPY:
            from rclpy.executors import SingleThreadedExecutor
            executor = SingleThreadedExecutor()
            executor.add_node(self.node)
            self._spin_once = lambda: executor.spin_once(timeout_sec=0.02)
        else:
            self._spin_once = lambda: rclpy.spin_once(self.node, timeout_sec=0.02)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self._spin_once()
            while not self._calls.empty():
                call, done = self._calls.get()
                done.put(call())

    def call(self, function: Callable[[], Any]) -> Any:
        done: queue.Queue = queue.Queue()
        self._calls.put((function, done))
        return done.get(timeout=30)

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=5)
        self.node.destroy_node()


def test_a_gain_set_while_filtering_and_a_refused_one(probe, capfd):
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.runtime import Parameter
    running = _InProcessFilter()
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        probe.subscribe('diagnostic_msgs/msg/DiagnosticArray', '/diagnostics', _diagnostic)
        proposal_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/cmd_proposed')
        probe.start()
        proposal = sections_to_msg({'u': [0.3, 0.0], 'state': [-3.0, 0.0, 0.0]})
        _handshake(probe, proposal_pub, proposal)
        _, (_, _, before) = _exchange(probe, proposal_pub, proposal)
        good = running.call(lambda: running.node.set_parameters(
            [Parameter('k_c', value=0.0)])[0])
        _, (level, _, after) = _exchange(probe, proposal_pub, proposal)
        bad = running.call(lambda: running.node.set_parameters(
            [Parameter('k_c', value=-1.0)])[0])
        bad_atomic = running.call(lambda: running.node.set_parameters_atomically(
            [Parameter('alpha', value=3.0), Parameter('obstacles.margin', value=-0.5)]))
        _, (_, _, unchanged) = _exchange(probe, proposal_pub, proposal)
        k_c, alpha = running.node.config.problem.k_c, running.node.config.problem.alpha
    finally:
        running.close()
    log = capfd.readouterr().err
    assert good.successful and level == 0
    rows = sorted(k for k in before if k.startswith('constraint.'))
    # k_c = 0: the robust margin k_c |dh/dx| std leaves every obstacle row
    assert all(float(after[k]) > float(before[k]) for k in rows)
    assert not bad.successful and bad.reason.startswith('Parameter k_c out of range')
    assert not bad_atomic.successful and bad_atomic.reason.startswith(
        ('obstacles.margin', 'Parameter obstacles.margin out of range'))
    assert (k_c, alpha) == (0.0, 2.0)   # the refused atomic set left alpha alone too
    assert all(unchanged[k] == after[k] for k in rows)
    assert 'filter updated: k_c: 2.0 -> 0.0' in log
    assert '[WARN]' in log and 'parameter change refused: k_c: -1.0 is outside' in log


def test_a_source_key_set_at_runtime_is_refused_naming_it(probe, capfd):
    """The sources are subscribed once, at start: a set of any ``<name>.*`` key is refused
    by its read-only descriptor, one WARN line naming the key, and the source keeps its
    settings (a set that was stored but not applied would leave a false timeout in force)."""
    from rcbf_ros.ros.runtime import Parameter
    running = _InProcessFilter('-p', 'observation_sources:=[front]', '-p', 'front.type:=scan',
                               '-p', 'front.topic:=/scan', '-p', 'front.timeout_s:=1.0',
                               '-p', 'footprint.radius:=0.2')
    try:
        results = {key: running.call(lambda key=key, value=value: running.node.set_parameters(
            [Parameter(key, value=value)])[0]) for key, value in (
                ('front.timeout_s', 5.0), ('front.topic', '/other'), ('k_c', 1.0))}
        timeout = running.node._sources.params('front').timeout_s
        stored = running.call(lambda: running.node.get_parameter('front.timeout_s').value)
    finally:
        running.close()
    log = capfd.readouterr().err
    assert not results['front.timeout_s'].successful
    assert not results['front.topic'].successful
    assert results['k_c'].successful  # the others still change at runtime
    assert (timeout, stored) == (1.0, 1.0)
    refused = [line for line in log.splitlines() if 'parameter change refused' in line]
    assert any('front.timeout_s is read-only' in line for line in refused), log
    assert any('front.topic is read-only' in line for line in refused), log

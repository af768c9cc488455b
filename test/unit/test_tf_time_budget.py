"""The executor time ``/tf`` may take in the safety filter (rcbf_ros.node_logic.time_budget).

A node answers on one thread: a reliable keep-last-100 ``/tf`` queue full of 1,024-transform
messages (15-30 ms each to read) held every answer back for seconds. The time ``/tf`` takes is
now charged to a budget, and a message that comes while it is spent is refused unread and
counted. The clock here is the test's own: no test is timed.
"""
from __future__ import annotations

from pathlib import Path
import time

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from tf_messages import tf_bytes, transform_stamped
import yaml

from rcbf_ros.node_logic.time_budget import TimeBudget
from rcbf_ros.ros import safety_filter_node
from rcbf_ros.ros.dds import rclpy_compat as rclpy

MS = 1_000_000


class FakeClock:
    """Monotonic ns that move only when the test says."""

    def __init__(self) -> None:
        self.ns = 1_000 * MS

    def __call__(self) -> int:
        return self.ns


@settings(max_examples=200, deadline=None)
@given(share=st.floats(0.01, 1.0), burst_ms=st.floats(0.1, 100.0),
       steps=st.lists(st.tuples(st.integers(0, 200 * MS), st.integers(0, 100 * MS)),
                      min_size=1, max_size=200))
def test_the_stream_takes_at_most_its_share_and_a_burst(share: float, burst_ms: float,
                                                       steps: list[tuple[int, int]]) -> None:
    """Messages arrive after ``gap`` ns and take ``cost`` ns when read: what is read takes at
    most the share of the time between readings, the burst and one message; after a quiet
    while of (burst + one message) / share the next message is read."""
    clock = FakeClock()
    budget = TimeBudget(share=share, burst_s=burst_ms / 1e3, clock=clock)
    read_ns = idle_ns = largest = 0
    for gap, cost in steps:
        clock.ns += gap
        idle_ns += gap
        started = budget.admit()
        if started is None:
            continue
        clock.ns += cost
        budget.charge(started)
        read_ns += cost
        largest = max(largest, cost)
        assert read_ns <= share * idle_ns + budget.burst_ns + largest + 1
    clock.ns += int((budget.burst_ns + largest) / share) + 1
    assert budget.admit() is not None


@pytest.mark.parametrize(('share', 'burst_s'), [
    (0.0, 0.02), (-0.1, 0.02), (1.5, 0.02), (float('nan'), 0.02), ('0.5', 0.02),
    (0.25, 0.0), (0.25, -1.0), (0.25, float('inf')), (0.25, float('nan'))])
def test_a_budget_that_bounds_nothing_is_refused_naming_the_argument(share, burst_s) -> None:
    with pytest.raises(ValueError, match='share|burst_s'):
        TimeBudget(share=share, burst_s=burst_s)


ROBOT = {'/**': {'ros__parameters': {
    'system': 'unicycle', 'input_limits': {'min': [-0.3, -1.9], 'max': [0.3, 1.9]},
    'alpha': 2.0, 'fail_safe_action': [0.0, 0.0],
    'obstacles': {'margin': 0.05, 'lookahead': 0.015, 'heading_index': 2, 'speed_input': 0},
    'odom_frame_id': 'odom', 'base_frame_id': 'base_link', 'footprint.radius': 0.18,
    'observation_sources': ['scan'], 'scan.type': 'scan', 'scan.topic': '/scan'}}}


@pytest.fixture
def node(ros_domain_id: int, tmp_path: Path):
    params = tmp_path / 'robot.yaml'
    params.write_text(yaml.safe_dump(ROBOT))
    rclpy.init(args=['--ros-args', '--params-file', str(params)], domain_id=ros_domain_id)
    instance = safety_filter_node.SafetyFilterNode()
    yield instance
    instance.destroy_node()
    rclpy.try_shutdown()


def test_a_tf_flood_is_read_within_its_share_and_the_rest_refused_unread(node) -> None:
    """100 /tf messages that each take 30 ms to read, queued at once: the first is read, the
    rest refused unread and counted in tf.refused, with one WARN; once the budget has filled
    again a message is read and its transform kept. /tf_static is always read."""
    clock = FakeClock()
    node._tf_budget.clock = node._tf_budget.work_clock = clock
    reads: list[bool] = []
    read_tf = node._sources.read_tf

    def slow_read(data, *, static, now_ns=None):
        reads.append(static)
        clock.ns += 30 * MS
        return read_tf(data, static=static, now_ns=now_ns)
    node._sources.read_tf = slow_read
    warnings: list[str] = []
    node.get_logger().warning = warnings.append
    stamp = node.get_clock().now().nanoseconds
    message = tf_bytes(transform_stamped('odom', 'base_link', stamp_ns=stamp))
    for _ in range(100):
        node._on_tf(message, False)
    assert reads == [False]
    counts = node._sources.tf_counts
    assert counts['messages'] == 100 and counts['refused'] == 99, counts
    assert len(warnings) == 1 and 'refused: unread' in warnings[0], warnings
    node._on_tf(tf_bytes(transform_stamped('base_link', 'laser', stamp_ns=stamp)), True)
    assert reads == [False, True]
    clock.ns += int(safety_filter_node.TF_TIME_BURST_S / safety_filter_node.TF_TIME_SHARE * 1e9)
    clock.ns += 30 * MS
    node._on_tf(tf_bytes(transform_stamped('odom', 'base_link', stamp_ns=stamp + 1)), False)
    assert reads == [False, True, False]
    assert node._sources.tf.frames == {'odom', 'base_link', 'laser'}


def test_the_tf2_listener_reads_within_the_same_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    """On rclpy (tf2_ros's listener, here stand-ins of tf2_ros and rclpy.duration): a /tf
    message that comes while the budget is spent is refused unread, counted, and said through
    the node's callback; /tf_static is always read."""
    import sys
    import types

    from rcbf_ros.ros import tf2_buffer

    class Listener:
        def __init__(self, buffer, node, *, qos, static_qos) -> None:
            self.buffer = buffer
    fake_tf2 = types.SimpleNamespace(Buffer=lambda cache_time: object(),
                                     TransformListener=Listener)
    fake_duration = types.SimpleNamespace(Duration=lambda nanoseconds: nanoseconds)
    monkeypatch.setitem(sys.modules, 'tf2_ros', fake_tf2)
    monkeypatch.setitem(sys.modules, 'rclpy.duration', fake_duration)
    clock = FakeClock()
    node = types.SimpleNamespace(get_clock=lambda: types.SimpleNamespace(
        now=lambda: types.SimpleNamespace(nanoseconds=clock.ns)))
    said: list[tuple[str, str]] = []
    budget = TimeBudget(share=0.25, burst_s=0.02, clock=clock)
    tf2 = tf2_buffer.start_tf2(node, lambda topic, reason: said.append((topic, reason)),
                               qos=None, static_qos=None, budget=budget)
    assert not isinstance(tf2, str), tf2
    taken: list[bool] = []

    def slow_take(message, *, static, now_ns=None) -> str:
        taken.append(static)
        clock.ns += 30 * MS
        return ''
    tf2.feed.take = slow_take
    for _ in range(100):
        tf2.listener.callback(object())
    tf2.listener.static_callback(object())
    assert taken == [False, True]
    # the stand-in take counts nothing: these are the refusals alone
    assert tf2.feed.counts['messages'] == 99 and tf2.feed.counts['refused'] == 99
    assert said[0] == ('/tf', '') and all(
        topic == '/tf' and reason.startswith('unread') for topic, reason in said[1:100])
    clock.ns += int((budget.burst_ns + 30 * MS) / budget.share) + 1
    tf2.listener.callback(object())
    assert taken == [False, True, False]


def test_a_reading_held_up_by_the_machine_is_charged_its_work_not_its_wait():
    """A /tf reading of 1 ms of CPU that a garbage collection or the scheduler stretched to
    150 ms: the robot's next transform is still read."""
    wall, work = [0], [0]
    budget = TimeBudget(share=0.25, burst_s=0.02, clock=lambda: wall[0],
                        work_clock=lambda: work[0])
    started = budget.admit()
    assert started is not None
    wall[0] += 150_000_000
    work[0] += 1_000_000
    budget.charge(started)
    wall[0] += 10_000_000  # the next odometry transform, 10 ms later
    assert budget.admit() is not None
    assert TimeBudget(share=0.25, burst_s=0.02).work_clock is time.thread_time_ns

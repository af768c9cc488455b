"""The Cyclone runtime's executor in one process: timers, one callback per spin_once,
shutdown from a callback ends spin, graph queries."""
from __future__ import annotations

import math
import sys
import threading

from hypothesis import given
from hypothesis import strategies as st
import pytest
from runtime_node import runtime_node

from rcbf_ros.messages.classes import get_message
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import INT64_MAX, timer_period_ns

Float64 = get_message('std_msgs/msg/Float64')


@pytest.fixture
def node(ros_domain_id):
    with runtime_node('executor_test', domain_id=ros_domain_id) as instance:
        yield instance


def test_spin_returns_after_shutdown_from_a_timer(node):
    ticks = []

    def tick():
        ticks.append(threading.get_ident())
        if len(ticks) == 3:
            rclpy.shutdown()
    node.create_timer(0.001, tick)
    rclpy.spin(node)
    assert ticks == [threading.get_ident()] * 3  # in the spinning thread, stopped at shutdown
    assert not rclpy.ok()


def test_a_timer_on_the_steady_clock_ticks_while_the_simulated_time_stands_still(node):
    """With ``use_sim_time`` true and no ``/clock``, the node's clock stands at 0: a timer on it
    never fires, one on a ``STEADY_TIME`` clock does (as rclpy's)."""
    from rcbf_ros.ros.runtime import Parameter
    assert node.set_parameters([Parameter('use_sim_time', value=True)])[0].successful
    assert node.get_clock().ros_time_is_active and node.get_clock().now().nanoseconds == 0
    steady = rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.STEADY_TIME)
    assert not steady.ros_time_is_active and steady.now().nanoseconds > 0
    on_ros_time, on_steady = [], []
    node.create_timer(0.001, lambda: on_ros_time.append(1))
    node.create_timer(0.001, lambda: on_steady.append(1), clock=steady)
    for _ in range(1000):   # a 1 ms timer: far more spins than 5 ticks take, even loaded
        if len(on_steady) >= 5:
            break
        rclpy.spin_once(node, timeout_sec=0.05)
    assert len(on_steady) >= 5 and not on_ros_time


def test_a_guard_condition_triggered_from_another_thread_runs_its_callback_in_the_spin(node):
    calls = []
    guard = node.create_guard_condition(lambda: calls.append(threading.get_ident()))
    triggers = [threading.Thread(target=guard.trigger) for _ in range(3)]
    for thread in triggers:
        thread.start()
    for thread in triggers:
        thread.join()
    for _ in range(100):   # spin_once waits for the wake-up: the first call runs it
        if calls:
            break
        rclpy.spin_once(node, timeout_sec=0.1)
    for _ in range(3):
        rclpy.spin_once(node, timeout_sec=0.01)
    assert calls == [threading.get_ident()]  # three triggers before the spin: one call
    assert node.destroy_guard_condition(guard) and not node.destroy_guard_condition(guard)
    guard.trigger()
    for _ in range(3):
        rclpy.spin_once(node, timeout_sec=0.01)
    assert len(calls) == 1


def test_a_clock_of_no_known_type_is_refused():
    with pytest.raises(TypeError, match='clock_type'):
        rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.UNINITIALIZED)
    with pytest.raises(TypeError, match='clock_type'):
        rclpy.clock.Clock(clock_type=3)


def test_a_canceled_timer_stops_until_reset_and_a_destroyed_one_for_good(node):
    ticks = []
    timer = node.create_timer(0.001, lambda: ticks.append(1))
    while not ticks:
        rclpy.spin_once(node, timeout_sec=0.05)
    timer.cancel()
    assert timer.is_canceled()
    count = len(ticks)
    for _ in range(5):
        rclpy.spin_once(node, timeout_sec=0.01)
    assert len(ticks) == count
    timer.reset()
    assert not timer.is_canceled()
    while len(ticks) == count:
        rclpy.spin_once(node, timeout_sec=0.05)
    assert node.destroy_timer(timer) and not node.destroy_timer(timer)
    count = len(ticks)
    for _ in range(5):
        rclpy.spin_once(node, timeout_sec=0.01)
    assert len(ticks) == count


def test_spin_once_runs_one_callback_at_a_time_in_order(node):
    received = []
    publisher = node.create_publisher(Float64, 'numbers', 10)
    node.create_subscription(Float64, 'numbers', lambda m: received.append(m.data), 10)
    while publisher.get_subscription_count() == 0:
        rclpy.spin_once(node, timeout_sec=0.01)
    for value in (1.0, 2.0, 3.0):
        publisher.publish(Float64(data=value))
    while not received:
        rclpy.spin_once(node, timeout_sec=0.1)
    assert received == [1.0]
    rclpy.spin_once(node, timeout_sec=0.1)
    rclpy.spin_once(node, timeout_sec=0.1)
    assert received == [1.0, 2.0, 3.0]


def test_spin_once_returns_on_timeout_without_work(node):
    rclpy.spin_once(node, timeout_sec=0.01)  # must come back without any entity
    assert rclpy.ok()


def test_publish_checks_the_message_type(node):
    publisher = node.create_publisher(Float64, 'numbers', 10)
    with pytest.raises(TypeError, match='std_msgs/msg/Float64'):
        publisher.publish(get_message('std_msgs/msg/Bool')(data=True))


def test_graph_lists_ros_topics_with_ros_type_names(node):
    node.create_publisher(get_message('geometry_msgs/msg/Twist'), 'cmd_vel', 10)
    node.create_subscription(Float64, '/gain', lambda m: None, 10)
    topics = dict(node.get_topic_names_and_types())
    assert topics['/cmd_vel'] == ['geometry_msgs/msg/Twist']
    assert topics['/gain'] == ['std_msgs/msg/Float64']
    assert node.count_publishers('cmd_vel') == 1 and node.count_subscribers('gain') == 1


def test_endpoint_info_reports_the_offered_qos_and_the_participant(node):
    from rcbf_ros.ros.dds.qos import DurabilityPolicy, HistoryPolicy, QoSProfile
    latched = QoSProfile(depth=7, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_publisher(get_message('std_msgs/msg/String'), 'events', latched)
    node.create_subscription(get_message('std_msgs/msg/String'), '/events', lambda m: None, 3)
    while node.count_subscribers('events') == 0 or node.count_publishers('events') == 0:
        rclpy.spin_once(node, timeout_sec=0.01)
    (publisher,) = node.get_publishers_info_by_topic('events')
    (subscription,) = node.get_subscriptions_info_by_topic('/events')
    assert publisher.topic_type == 'std_msgs/msg/String'
    assert publisher.qos_profile == latched
    assert subscription.qos_profile.durability == DurabilityPolicy.VOLATILE
    assert subscription.qos_profile.history == HistoryPolicy.KEEP_LAST
    assert subscription.qos_profile.depth == 3
    assert len(publisher.endpoint_gid) == 16
    # One participant per process: the GUIDs share their 12-byte prefix, not the endpoint id.
    assert publisher.endpoint_gid[:12] == subscription.endpoint_gid[:12]
    assert publisher.endpoint_gid != subscription.endpoint_gid
    assert node.get_publishers_info_by_topic('other') == []


def test_graph_queries_see_endpoints_come_and_go(node):
    publisher = node.create_publisher(Float64, 'transient', 10)
    while node.count_publishers('transient') == 0:
        rclpy.spin_once(node, timeout_sec=0.01)
    assert node.count_publishers('transient') == 1
    node.destroy_publisher(publisher)
    for _ in range(200):
        if node.count_publishers('transient') == 0:
            break
        rclpy.spin_once(node, timeout_sec=0.01)
    assert node.count_publishers('transient') == 0


def test_a_late_transient_local_subscriber_gets_the_writers_whole_history(node):
    from rcbf_ros.ros.dds.qos import DurabilityPolicy, QoSProfile
    latched = QoSProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = node.create_publisher(Float64, 'latched', latched)
    for value in range(7):
        publisher.publish(Float64(data=float(value)))
    received = []
    node.create_subscription(Float64, 'latched', lambda m: received.append(m.data), latched)
    for _ in range(100):
        if len(received) == 5:
            break
        rclpy.spin_once(node, timeout_sec=0.02)
    assert received == [2.0, 3.0, 4.0, 5.0, 6.0]  # keep-last 5, not Cyclone's default 1


# --- waiting: a wake-up says which readers hold samples ------------------------------------------

def _drain(node) -> None:
    while node._waitset.wait(0):
        rclpy.spin_once(node, timeout_sec=0)


def test_a_wait_reports_exactly_the_triggered_conditions(node):
    publisher = node.create_publisher(Float64, 'numbers', 10)
    subscription = node.create_subscription(Float64, 'numbers', lambda m: None, 10)
    idle = node.create_subscription(Float64, 'other', lambda m: None, 10)
    _drain(node)
    assert node._waitset.wait(0) == []
    node._wake()
    assert node._waitset.wait(0) == [node._guard._ref]
    node._guard.take()
    publisher.publish(Float64(data=1.0))
    assert node._waitset.wait(1_000_000_000) == [subscription._condition._ref]
    assert idle._condition._ref not in node._waitset.wait(0)
    rclpy.spin_once(node, timeout_sec=0)
    assert node._waitset.wait(0) == []


def test_more_triggered_readers_than_the_first_buffer_holds_all_deliver(node):
    count = 3 * len(node._waitset._triggered)
    received: list[int] = []
    publishers = []
    for index in range(count):
        publishers.append(node.create_publisher(Float64, f'topic_{index}', 10))
        node.create_subscription(Float64, f'topic_{index}',
                                 lambda m, index=index: received.append(index), 10)
    _drain(node)
    for index, publisher in enumerate(publishers):
        publisher.publish(Float64(data=float(index)))
    assert len(node._waitset.wait(1_000_000_000)) == count  # local delivery: all at once
    for _ in range(10 * count):
        if len(received) == count:
            break
        rclpy.spin_once(node, timeout_sec=0.05)
    assert sorted(received) == list(range(count))
    assert received == sorted(received)  # taken in creation order


def test_idle_readers_are_not_asked_after_every_wake_up(node, monkeypatch):
    publisher = node.create_publisher(Float64, 'busy', 10)
    received = []
    node.create_subscription(Float64, 'busy', lambda m: received.append(m.data), 10)
    idle = node.create_subscription(Float64, 'quiet', lambda m: None, 10)
    _drain(node)
    asked = []
    monkeypatch.setattr(idle, '_take_ready', lambda: asked.append('idle') or [])
    for endpoint in node._service_endpoints:  # the parameter services
        monkeypatch.setattr(endpoint, '_take_ready',
                            lambda endpoint=endpoint: asked.append(endpoint.srv_name) or [])
    for value in range(20):
        publisher.publish(Float64(data=float(value)))
        while len(received) <= value:
            rclpy.spin_once(node, timeout_sec=0.1)
    assert received == [float(v) for v in range(20)] and asked == []


@pytest.mark.parametrize('period', [1e308, math.inf, -math.inf, math.nan, -1.0, 0.0, 1e-300,
                                    9.3e9, '0.1', True, None])
def test_a_timer_period_that_does_not_fit_is_refused_naming_it(node, period):
    """rclpy refuses these with rcl's "timer period must be non-negative" or a bare
    OverflowError / ValueError / TypeError (and runs 0 as always due); here one ValueError
    line naming timer_period_sec, and no timer is made."""
    before = list(node._timers)
    with pytest.raises(ValueError, match=r'^timer_period_sec: [^\n]+$'):
        node.create_timer(period, lambda: None)
    assert node._timers == before


@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers()))
def test_a_timer_period_is_a_positive_int64_of_nanoseconds_or_one_refusal(period):
    try:
        period_ns = timer_period_ns(period)
    except ValueError as exc:
        assert str(exc).startswith('timer_period_sec: ') and '\n' not in str(exc)
        assert not 1e-9 <= period <= 9.2e9
    else:
        assert 0 < period_ns <= INT64_MAX
        assert period_ns == round(period * 1e9)


def _interrupted_at_line(k: int, domain_id: int) -> bool:
    """Build a node with ``KeyboardInterrupt`` raised at the ``k``-th line ``Node.__init__``
    runs (as a SIGINT lands), then shut the runtime down; whether line ``k`` was reached."""
    from rcbf_ros.ros.dds.node import Node
    lines = [0]

    def trace(frame, event, arg):
        if frame.f_code is not Node.__init__.__code__:
            return None
        if event == 'line':
            lines[0] += 1
            if lines[0] == k:
                raise KeyboardInterrupt
        return trace
    rclpy.init(args=[], domain_id=domain_id)
    sys.settrace(lambda frame, event, arg: trace if frame.f_code is Node.__init__.__code__
                 else None)
    try:
        Node('interrupted')
    except KeyboardInterrupt:
        pass
    finally:
        sys.settrace(None)
    rclpy.try_shutdown()  # must not raise, whatever the node had built
    assert not rclpy.ok()
    return lines[0] >= k


def test_a_signal_at_any_line_of_a_node_s_construction_leaves_a_runtime_that_shuts_down(
        ros_domain_id):
    """A launch stops its nodes with SIGINT, which may land while one is still being built:
    the runtime's shutdown then destroys a node that holds only part of its entities."""
    k = 1
    while _interrupted_at_line(k, ros_domain_id):
        k += 1
    assert k > 40  # every line of the constructor was a landing point

"""A ``/clock`` message of a time no stamp can carry (negative seconds, past int32 seconds) is
dropped before it reaches the node clock, said once a second, on our runtime and, through
``node_main``, before rclpy's time source (which raises on negative seconds)."""
from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from runtime_node import runtime_node

from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.conversions import diagnostics_to_cdr
from rcbf_ros.node_logic.sim_clock import ClockGuard, LATEST_STAMP_NS, WARN_PERIOD_NS
from rcbf_ros.ros.node_main import guard_sim_clock

Clock = get_message('rosgraph_msgs/msg/Clock')
INT32 = st.integers(-2**31, 2**31 - 1)
UINT32 = st.integers(0, 2**32 - 1)
EDGES = st.sampled_from([(-2**31, 0), (-1, 2**32 - 1), (0, 0), (2**31 - 1, 999_999_999),
                         (2**31 - 1, 10**9), (2**31 - 1, 2**32 - 1), (2**31 - 5, 2**32 - 1)])
CLOCKS = st.one_of(st.tuples(INT32, UINT32), EDGES)


def _clock(sec: int, nanosec: int) -> Any:
    message = Clock()
    message.clock.sec, message.clock.nanosec = sec, nanosec
    return message


@given(clocks=st.lists(CLOCKS, max_size=20),
       gaps=st.lists(st.integers(0, 3 * WARN_PERIOD_NS), min_size=20, max_size=20))
def test_a_time_is_taken_exactly_when_a_stamp_can_carry_it_and_said_once_a_second(clocks, gaps):
    guard, now, said = ClockGuard(), 0, []
    for (sec, nanosec), gap in zip(clocks, gaps):
        now += gap
        take, line = guard.check(sec, nanosec, now_ns=now)
        time_ns = sec * 10**9 + nanosec
        assert take == (sec >= 0 and time_ns <= LATEST_STAMP_NS)
        if take:
            assert not line
            diagnostics_to_cdr(stamp_ns=time_ns, name='n', level=0, message='', values={})
        if line:
            assert '\n' not in line and line.startswith('/clock: message refused')
            said.append(now)
    assert all(b - a >= WARN_PERIOD_NS for a, b in zip(said, said[1:]))
    assert guard.refused == sum(not (s >= 0 and s * 10**9 + n <= LATEST_STAMP_NS)
                                for s, n in clocks)
    assert bool(said) == bool(guard.refused)


def test_our_runtime_keeps_the_last_time_a_stamp_can_carry(ros_domain_id):
    from rcbf_ros.ros.runtime import Parameter
    with runtime_node('sim_clock_test', domain_id=ros_domain_id) as node:
        assert node.set_parameters([Parameter('use_sim_time', value=True)])[0].successful

        @settings(max_examples=60, deadline=None)
        @given(clocks=st.lists(CLOCKS, min_size=1, max_size=8))
        def keeps(clocks):
            expected = node.get_clock().now().nanoseconds
            for sec, nanosec in clocks:
                node._time_source._on_clock(_clock(sec, nanosec))  # as the subscription calls it
                if sec >= 0 and sec * 10**9 + nanosec <= LATEST_STAMP_NS:
                    expected = sec * 10**9 + nanosec
                assert node.get_clock().now().nanoseconds == expected
        keeps()


class _RclpyTimeSource:
    """rclpy's TimeSource as far as the guard sees it: it raises on negative seconds."""

    def __init__(self, subscribed: bool) -> None:
        self.taken: list[int] = []
        self._clock_sub = SimpleNamespace(callback=self.clock_callback) if subscribed else None

    def clock_callback(self, message: Any) -> None:
        if message.clock.sec < 0:
            raise ValueError('Seconds value must not be negative')
        self.taken.append(message.clock.sec * 10**9 + message.clock.nanosec)


@pytest.mark.parametrize('subscribed', [True, False])
@given(clocks=st.lists(CLOCKS, max_size=10))
def test_on_rclpy_the_time_source_gets_only_the_times_a_stamp_can_carry(subscribed, clocks):
    source, lines = _RclpyTimeSource(subscribed), []
    logger = SimpleNamespace(warning=lines.append)
    guard_sim_clock(SimpleNamespace(_time_source=source, get_logger=lambda: logger))
    callback = (source._clock_sub.callback if subscribed  # the subscription made at start
                else source.clock_callback)               # the one use_sim_time makes later
    for sec, nanosec in clocks:
        callback(_clock(sec, nanosec))
    assert source.taken == [s * 10**9 + n for s, n in clocks
                            if s >= 0 and s * 10**9 + n <= LATEST_STAMP_NS]
    assert len(lines) <= 1 and all('\n' not in line for line in lines)

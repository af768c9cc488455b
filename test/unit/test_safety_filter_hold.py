"""The node's side of the sampled-data margin: a state at most ``latency_s`` old at each
decision, and an answer within ``control_period_s`` of the latest (the hold timer).

First the pure logic on fake clocks (:func:`decide`, :func:`decide_held`, :func:`hold_due`,
:func:`decide_hold`); then a fine-step closed loop of the Unicycle at a wall, driven by those
functions as the node drives them (the state arrives at 2 Hz, slower than 1 / T): with the
checks the wall is never crossed, without them it is; then the node's callbacks with its
monotonic clock replaced by one the test moves (no DDS traffic).
"""
from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_safety_filter_callbacks import _cdr, FAIL_SAFE
from test_safety_filter_refilter import _node_harness

from rcbf_ros.core.barriers import HalfPlane
from rcbf_ros.core.dynamics import Unicycle
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.messages.conversions import msg_to_sections
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as fl
from rcbf_ros.ros.dds import rclpy_compat as rclpy

SECOND = 1_000_000_000
MS = 1_000_000
T, L = 0.05, 0.02
AT_WALL = np.array([0.6, 0.0, 0.0])   # 0.4 m from the wall x <= 1, facing it
FULL = [2.5, 0.0]


@pytest.fixture(scope='module')
def wall_filter() -> SafetyFilter:
    """A Unicycle, the wall x <= 1, alpha 5, the margin of T and L."""
    problem = RCBFProblem(system=Unicycle(u_min=(-2.0, -3.0), u_max=(2.5, 3.0)),
                          families=(HalfPlane(normals=((-1.0, 0.0),), offsets=(-1.0,)),),
                          alpha=5.0, k_c=0.0)
    return SafetyFilter(problem, control_period_s=T, latency_s=L)


def _decide(safety_filter: SafetyFilter, state: fl.StateSample, now_ns: int,
            **kwargs: Any) -> fl.Decision:
    return fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=np.array(FULL)),
                     latest_state=state, now_ns=now_ns, max_state_age_s=0.5, **kwargs)


def _held(received_ns: int, state: np.ndarray | None = None) -> fl.HeldProposal:
    proposal = fl.Proposal(u=np.array(FULL), state=state)
    return fl.HeldProposal(sample=fl.ProposalSample(proposal), received_ns=received_ns)


# --- the state's age ----------------------------------------------------------------------------

def test_the_limit_is_latency_s_only_with_a_margin():
    assert fl.state_age_limit_s(control_period_s=0.0, latency_s=0.0) is None
    assert fl.state_age_limit_s(control_period_s=T, latency_s=0.0) == 0.0
    assert fl.state_age_limit_s(control_period_s=0.0, latency_s=L) == L
    assert fl.state_age_limit_s(control_period_s=T, latency_s=L) == L


def test_a_topic_state_older_than_latency_s_gives_the_fail_safe(wall_filter):
    state = fl.StateSample(received_ns=10 * SECOND, state=AT_WALL)
    fresh = _decide(wall_filter, state, 10 * SECOND + 20 * MS, latency_s=L)
    assert not fresh.fail_safe and 0.0 < fresh.u_safe[0] < 2.5   # slowed by the wall
    late = _decide(wall_filter, state, 10 * SECOND + 21 * MS, latency_s=L)
    assert late.fail_safe and late.level == fl.ERROR
    np.testing.assert_array_equal(late.u_safe, wall_filter.fail_safe_action)
    assert late.reason == 'late state: 0.021000 s old > latency_s = 0.02'
    assert fl.status_code(late) == STATUS_CODES['late state'] == 19
    np.testing.assert_array_equal(late.state, AT_WALL)
    assert late.state_source == 'topic'
    # Without a margin (latency_s None) max_state_age_s alone applies, as before.
    assert not _decide(wall_filter, state, 10 * SECOND + 400 * MS).fail_safe


def test_the_proposals_own_state_ages_from_the_proposals_arrival(wall_filter):
    held = _held(10 * SECOND, state=AT_WALL)
    kwargs = dict(held=held, safety_filter=wall_filter, latest_state=None,
                  max_state_age_s=0.5, max_proposal_age_s=0.5, latency_s=L)
    assert not fl.decide_held(again=False, now_ns=10 * SECOND, **kwargs).fail_safe
    assert not fl.decide_held(again=True, now_ns=10 * SECOND + 20 * MS, **kwargs).fail_safe
    late = fl.decide_held(again=True, now_ns=10 * SECOND + 30 * MS, **kwargs)
    assert late.fail_safe and late.state_source == 'proposal'
    assert late.reason == 'late state: 0.030000 s old > latency_s = 0.02'
    # Without a margin a proposal's own state has no age check (as before).
    kwargs['latency_s'] = None
    assert not fl.decide_held(again=True, now_ns=10 * SECOND + 300 * MS, **kwargs).fail_safe


def test_an_odometry_stamp_in_the_past_or_the_future(wall_filter):
    """The age is the larger of the stamp's (on the node's clock) and the arrival's: a stamp
    in the past makes a state that just arrived old; one in the future does not make a state
    that arrived long ago young."""
    arrived, clock = 10 * SECOND, 50 * SECOND   # monotonic and ROS clocks differ
    def decision(stamp_ns: int, now_ns: int) -> fl.Decision:
        sample = fl.StateSample(received_ns=arrived, state=AT_WALL, stamp_ns=stamp_ns)
        return _decide(wall_filter, sample, now_ns, latency_s=L,
                       stamp_now_ns=clock + (now_ns - arrived))
    assert not decision(clock - 10 * MS, arrived + 5 * MS).fail_safe       # 15 ms old
    past = decision(clock - 30 * MS, arrived + 1 * MS)                      # 31 ms by stamp
    assert past.fail_safe and past.reason.startswith('late state: 0.031000 s old')
    future = decision(clock + SECOND, arrived + 25 * MS)                    # 25 ms by arrival
    assert future.fail_safe and future.reason.startswith('late state: 0.025000 s old')
    assert not decision(clock + SECOND, arrived + 5 * MS).fail_safe
    assert decision(0, arrived).fail_safe   # an unstamped Odometry proves no age


@settings(max_examples=60, deadline=None)
@given(age_us=st.integers(0, 100_000), stamp_age_us=st.integers(-10 ** 6, 10 ** 6),
       limit_us=st.integers(0, 100_000))
def test_late_exactly_when_older_than_the_limit(wall_filter, age_us, stamp_age_us, limit_us):
    now, clock = 7 * SECOND, 3 * SECOND
    sample = fl.StateSample(received_ns=now - age_us * 1000, state=AT_WALL,
                            stamp_ns=clock - stamp_age_us * 1000)
    decision = _decide(wall_filter, sample, now, latency_s=limit_us / 1e6, stamp_now_ns=clock)
    late = max(age_us, stamp_age_us) > limit_us
    assert (fl.reason_key(decision.reason) == 'late state') == late


def test_the_odometry_stamp_reaches_the_sample():
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.runtime import deserialize_message
    msg = get_message('nav_msgs/msg/Odometry')()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.pose.pose.orientation.w = 1.0
    edge = filter_edge.FilterEdge(state_type='odometry', command_type='array',
                                  system='unicycle', n_x=3, n_u=2,
                                  deserialize=deserialize_message, get_message=get_message)
    sample, count = edge.read_state(serialize_message(msg), received_ns=5)
    assert count == '' and sample.stamp_ns == 12 * SECOND + 345
    edge = filter_edge.FilterEdge(state_type='array', command_type='array', system='unicycle',
                                  n_x=3, n_u=2, deserialize=deserialize_message,
                                  get_message=get_message)
    array, _ = edge.read_state(_cdr({'state': [0.0, 0.0, 0.0]}), received_ns=5)
    assert array.state is not None and array.stamp_ns is None


# --- the hold timer -----------------------------------------------------------------------------

def test_hold_due_needs_a_period_and_an_answer():
    assert not fl.hold_due(control_period_s=0.0, timer_period_s=0.01, last_answer_ns=0,
                           now_ns=SECOND)
    assert not fl.hold_due(control_period_s=T, timer_period_s=0.0125, last_answer_ns=None,
                           now_ns=SECOND)
    assert fl.hold_timer_period_s(0.0) is None
    assert fl.hold_timer_period_s(T) == T / 4
    assert fl.hold_timer_period_s(1e-6) == fl.HOLD_TIMER_MIN_PERIOD_S   # bounded


@settings(max_examples=80, deadline=None)
@given(period_ms=st.sampled_from([4, 10, 20, 50, 100, 1000]), phase_us=st.integers(0, 10 ** 6),
       answers_us=st.lists(st.integers(0, 2 * 10 ** 6), max_size=20))
def test_the_timer_leaves_no_gap_longer_than_the_period(period_ms, phase_us, answers_us):
    """Timer calls every T / 4 from any phase, other answers at any times: the answers
    (theirs and the timer's, one per call at most) are never more than T apart."""
    control = period_ms * 1e-3
    tick_ns = round(fl.hold_timer_period_s(control) * 1e9)
    events = sorted([(t * 1000, False) for t in answers_us]
                    + [(phase_us * 1000 % tick_ns + k * tick_ns, True)
                       for k in range(2 * 10 ** 9 // tick_ns + 4)])
    answers, last = [0], 0
    for now, is_tick in events:
        if now < 0:
            continue
        if not is_tick or fl.hold_due(control_period_s=control, timer_period_s=tick_ns / 1e9,
                                      last_answer_ns=last, now_ns=now):
            answers.append(now)
            last = now
    gaps = np.diff([a for a in answers if a <= 2 * SECOND])
    assert gaps.size and gaps.max() <= round(control * 1e9)


def test_the_hold_answer_names_control_period_s_when_the_state_is_late(wall_filter):
    state = fl.StateSample(received_ns=10 * SECOND, state=AT_WALL)
    kwargs = dict(safety_filter=wall_filter, control_period_s=T, latest_state=state,
                  max_state_age_s=0.5, max_proposal_age_s=0.5, latency_s=L)
    again = fl.decide_hold(held=_held(10 * SECOND), now_ns=10 * SECOND + 10 * MS, **kwargs)
    assert not again.fail_safe and 0.0 < again.u_safe[0] < 2.5
    late = fl.decide_hold(held=_held(10 * SECOND), now_ns=10 * SECOND + 40 * MS, **kwargs)
    assert late.fail_safe and fl.status_code(late) == 19
    assert 'latency_s = 0.02' in late.reason and 'control_period_s = 0.05' in late.reason
    lost = fl.decide_hold(held=None, now_ns=10 * SECOND + 40 * MS, **kwargs)
    assert lost.fail_safe and 'control_period_s' in lost.reason


# --- the closed loop ----------------------------------------------------------------------------

def _closed_loop(safety_filter: SafetyFilter, *, enforced: bool, seconds: float = 3.0,
                 state_period_ms: int = 500) -> float:
    """The least h = 1 - x of a Unicycle at the wall x <= 1 on 1 ms Euler steps: one proposal
    (full speed at the wall) at 0, states every ``state_period_ms`` (fresh on arrival), each
    answered again (refilter_on_state); ``enforced``: the latency_s check and the hold timer
    at T / 4 as the node runs them, else neither. The base holds the latest answer."""
    x = AT_WALL.copy()
    held = _held(0)
    tick_ns = round(fl.hold_timer_period_s(T) * 1e9)
    limit = fl.state_age_limit_s(control_period_s=T, latency_s=L) if enforced else None
    common = dict(safety_filter=safety_filter, max_state_age_s=0.5, max_proposal_age_s=1e9,
                  latency_s=limit)
    latest = fl.StateSample(received_ns=0, state=x.copy())
    u = fl.decide_held(held=held, again=False, latest_state=latest, now_ns=0, **common).u_safe
    last, least = 0, 1.0 - x[0]
    for step in range(1, round(seconds * 1000) + 1):
        now = step * MS
        x = x + 1e-3 * np.array([u[0] * np.cos(x[2]), u[0] * np.sin(x[2]), u[1]])
        least = min(least, 1.0 - x[0])
        if step % state_period_ms == 0:
            latest = fl.StateSample(received_ns=now, state=x.copy())
            if fl.refilter_due(enabled=True, held=held, last_answer_ns=last, now_ns=now,
                               min_period_s=0.01):
                u = fl.decide_held(held=held, again=True, latest_state=latest, now_ns=now,
                                   **common).u_safe
                last = now
        elif enforced and now % tick_ns == 0 and fl.hold_due(
                control_period_s=T, timer_period_s=tick_ns / 1e9, last_answer_ns=last,
                now_ns=now):
            u = fl.decide_hold(held=held, control_period_s=T, latest_state=latest, now_ns=now,
                               **common).u_safe
            last = now
    return least


def test_a_command_held_at_a_wall_keeps_off_it_only_with_the_checks(wall_filter):
    """v = 0.93 m/s answered at x = 0.6; odometry at 2 Hz. Held for 0.5 s
    the command crosses the wall; with the checks the robot stops within T + L of its state
    and creeps up to the wall without crossing it."""
    assert _closed_loop(wall_filter, enforced=False) < -0.03
    assert _closed_loop(wall_filter, enforced=True) > 0.0


# --- the node -----------------------------------------------------------------------------------

@pytest.fixture
def held_node(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(ros_domain_id, monkeypatch, '-p', f'control_period_s:={T}',
                                    '-p', f'latency_s:={L}')
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture
def plain_node(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(ros_domain_id, monkeypatch)
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


FREE = [-2.5, -2.5, -0.75 * np.pi]   # config/unicycle.yaml: in a corner, heading away


def test_the_timer_answers_within_the_period_then_fails_safe_on_a_late_state(held_node):
    harness, clock = held_node
    node = harness.node
    assert node._hold_period_s == T / 4 and node._hold_timer is not None
    node._on_hold()
    assert len(harness.commands) == 0   # nothing answered yet: nothing to hold
    node._on_state(_cdr({'state': FREE}))
    u, _ = harness.answer(_cdr({'u': [1.0, 0.3]}))
    assert list(u) == [1.0, 0.3]
    clock.now_ns += 30 * MS
    node._on_hold()                      # the next call (12.5 ms later) is within T
    assert len(harness.commands) == 1
    node._on_state(_cdr({'state': FREE}))   # refilter_on_state off: no answer
    clock.now_ns += 8 * MS
    node._on_hold()                      # 38 ms since the answer: now, at the 8 ms old state
    assert len(harness.commands) == 2 and node.holds == 1
    info = msg_to_sections(harness.infos[-1])
    assert info['fail_safe'][0] == 0 and list(info['u']) == [1.0, 0.3]
    clock.now_ns += 38 * MS             # the state is 46 ms old now
    node._on_hold()
    info = msg_to_sections(harness.infos[-1])
    assert len(harness.commands) == 3 and info['fail_safe'][0] == 1
    assert info['status'][0] == STATUS_CODES['late state']
    assert list(info['u']) == FAIL_SAFE
    clock.now_ns += 5 * MS
    node._on_hold()                      # one answer per call, none while the last is new
    assert len(harness.commands) == 3


def test_a_proposal_is_answered_late_only_past_latency_s(held_node):
    harness, clock = held_node
    harness.node._on_state(_cdr({'state': FREE}))
    clock.now_ns += 20 * MS
    u, _ = harness.answer(_cdr({'u': [1.0, 0.3]}))
    assert list(u) == [1.0, 0.3]
    clock.now_ns += 1 * MS
    u, diagnostic = harness.answer(_cdr({'u': [1.0, 0.3]}))
    assert list(u) == FAIL_SAFE and diagnostic is not None
    assert diagnostic[1] == 'late state: 0.021000 s old > latency_s = 0.02'


def test_without_a_margin_there_is_no_timer_and_no_age_bound(plain_node):
    harness, clock = plain_node
    node = harness.node
    assert node._hold_timer is None and node._hold_period_s is None
    node._on_state(_cdr({'state': FREE}))
    clock.now_ns += 300 * MS
    u, _ = harness.answer(_cdr({'u': [1.0, 0.3]}))
    assert list(u) == [1.0, 0.3]
    clock.now_ns += SECOND
    node._on_hold()
    assert len(harness.commands) == 1


def test_the_timer_follows_control_period_s_at_runtime(plain_node):
    from rcbf_ros.ros.runtime import Parameter
    harness, _ = plain_node
    node = harness.node
    result = node.set_parameters([Parameter('control_period_s', Parameter.Type.DOUBLE, 0.1)])
    assert result[0].successful and node._hold_period_s == 0.025
    assert node._hold_timer is not None
    result = node.set_parameters([Parameter('control_period_s', Parameter.Type.DOUBLE, 0.0)])
    assert result[0].successful and node._hold_period_s is None and node._hold_timer is None

"""The proposal in force filtered again at each new state (``refilter_on_state``).

First the pure logic on a fake clock (:func:`decide_held`, :func:`refilter_due`, a real
SafetyFilter from config/unicycle.yaml behind every decision); then the node's callbacks called
directly with the node's monotonic clock replaced by one the test moves (no peers, no DDS
traffic): a controller that proposes once and goes quiet while states keep coming.
"""
from __future__ import annotations

import time
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_observation_sources import _scan
from test_safety_filter_callbacks import _cdr, _harness, _odometry, _twist_stamped, FAIL_SAFE

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.messages.conversions import msg_to_sections
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as fl
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.runtime import Parameter

SECOND = 1_000_000_000
MS = 1_000_000
FREE_STATE = np.array([-2.5, -2.5, -0.75 * np.pi])  # in a corner, heading away from obstacles
FAR = np.array([-3.0, 0.0, 0.0])                     # 2.4 m from the centre obstacle, facing it
FACING_OBSTACLE = np.array([-0.85, 0.0, 0.0])        # 0.25 m from it, facing it
AT_OBSTACLE = [2.5, 0.0]                             # full speed ahead


@pytest.fixture(scope='module')
def safety_filter() -> SafetyFilter:
    config = filter_config_from_params(load_params(find_config('unicycle'), 'safety_filter'))
    return SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action)


def _held(u: list[float], received_ns: int, **sections: Any) -> fl.HeldProposal:
    proposal = fl.Proposal(u=np.array(u), **{k: np.array(v) for k, v in sections.items()})
    return fl.HeldProposal(sample=fl.ProposalSample(proposal), received_ns=received_ns)


def _again(safety_filter: SafetyFilter, held: fl.HeldProposal, state: np.ndarray,
           state_ns: int, now_ns: int, **kwargs: Any) -> fl.Decision:
    return fl.decide_held(
        held=held, again=True, safety_filter=safety_filter,
        latest_state=fl.StateSample(received_ns=state_ns, state=state), now_ns=now_ns,
        max_state_age_s=0.5, max_proposal_age_s=0.5, **kwargs)


# --- the decision -------------------------------------------------------------------------------

def test_a_held_proposal_is_corrected_at_a_new_state_and_fails_safe_once_too_old(
        safety_filter):
    held = _held(AT_OBSTACLE, received_ns=10 * SECOND)
    # At its arrival, far away: passed as is.
    first = fl.decide_held(held=held, again=False, safety_filter=safety_filter,
                           latest_state=fl.StateSample(10 * SECOND, FAR), now_ns=10 * SECOND,
                           max_state_age_s=0.5, max_proposal_age_s=0.5)
    assert first.level == fl.OK and list(first.u_safe) == AT_OBSTACLE
    # 0.3 s later the robot is 0.25 m from the obstacle: the same proposal is slowed down.
    near = _again(safety_filter, held, FACING_OBSTACLE, 10_300 * MS, 10_300 * MS)
    assert near.level == fl.OK and not near.fail_safe and 0.0 <= near.u_safe[0] < 2.5
    np.testing.assert_array_equal(near.u_rl, AT_OBSTACLE)
    np.testing.assert_array_equal(near.state, FACING_OBSTACLE)
    assert near.state_source == 'topic'
    # 0.61 s after its arrival, even far from everything: the fail-safe, one reason.
    stale = _again(safety_filter, held, FREE_STATE, 10_610 * MS, 10_610 * MS)
    assert stale.fail_safe and stale.level == fl.ERROR
    np.testing.assert_array_equal(stale.u_safe, safety_filter.fail_safe_action)
    assert stale.reason == 'stale proposal: 0.610 s old > max_proposal_age_s = 0.5'
    assert fl.status_code(stale) == STATUS_CODES['stale proposal'] == 18
    np.testing.assert_array_equal(stale.u_rl, AT_OBSTACLE)  # what was held, in filter_info


def test_at_its_arrival_a_proposal_has_no_age(safety_filter):
    """Answered when it arrives (re-filtering off, or a proposal's own answer): the age check
    does not apply, whatever the clock says."""
    held = _held([1.0, 0.3], received_ns=10 * SECOND)
    decision = fl.decide_held(held=held, again=False, safety_filter=safety_filter,
                              latest_state=fl.StateSample(99 * SECOND, FREE_STATE),
                              now_ns=99 * SECOND, max_state_age_s=0.5,
                              max_proposal_age_s=0.5)
    assert decision.level == fl.OK and list(decision.u_safe) == [1.0, 0.3]


@settings(max_examples=60, deadline=None)
@given(age_ms=st.integers(0, 2000), limit_ms=st.integers(1, 1500))
def test_the_age_limit_is_since_the_arrival(safety_filter, age_ms, limit_ms):
    held = _held([1.0, 0.3], received_ns=5 * SECOND)
    now = 5 * SECOND + age_ms * MS
    decision = fl.decide_held(held=held, again=True, safety_filter=safety_filter,
                              latest_state=fl.StateSample(now, FREE_STATE), now_ns=now,
                              max_state_age_s=0.5, max_proposal_age_s=limit_ms / 1000)
    assert decision.fail_safe == (age_ms > limit_ms)
    assert decision.reason.startswith('stale proposal: ') == (age_ms > limit_ms)


def test_the_newest_state_is_the_one_filtered_at(safety_filter):
    """A proposal with its own ``state`` section is filtered at it until a state message
    arrives after the proposal; from then on at the state message."""
    held = _held(AT_OBSTACLE, received_ns=10 * SECOND, state=FAR)
    older = _again(safety_filter, held, FACING_OBSTACLE, 9 * SECOND, 10_100 * MS,
                   )  # the state message arrived before the proposal: its own state is newer
    assert older.state_source == 'proposal' and list(older.u_safe) == AT_OBSTACLE
    newer = _again(safety_filter, held, FACING_OBSTACLE, 10_050 * MS, 10_100 * MS)
    assert newer.state_source == 'topic' and newer.u_safe[0] < 2.5
    np.testing.assert_array_equal(newer.state, FACING_OBSTACLE)


def test_a_refiltered_proposal_keeps_its_disturbance_sections(safety_filter):
    """The disturbance box rides on the held proposal: the answer again is the proposal's
    answer at the new state, sections and all."""
    held = _held(AT_OBSTACLE, received_ns=10 * SECOND, disturbance_mean=[0.0] * 3,
                 disturbance_std=[0.3] * 3)
    again = _again(safety_filter, held, FACING_OBSTACLE, 10_100 * MS, 10_100 * MS)
    fresh = fl.decide(safety_filter=safety_filter, proposal=held.sample.proposal,
                      latest_state=fl.StateSample(10_100 * MS, FACING_OBSTACLE),
                      now_ns=10_100 * MS, max_state_age_s=0.5)
    plain = _again(safety_filter, _held(AT_OBSTACLE, 10 * SECOND), FACING_OBSTACLE,
                   10_100 * MS, 10_100 * MS)
    np.testing.assert_array_equal(again.u_safe, fresh.u_safe)
    assert again.u_safe[0] < plain.u_safe[0]  # the wider box slows down more


def test_a_held_bad_or_undecodable_proposal_gives_the_fail_safe_again(safety_filter):
    bad = fl.HeldProposal(sample=fl.ProposalSample(None, 'u: contains NaN'),
                          received_ns=10 * SECOND)
    undecodable = fl.HeldProposal(
        sample=fl.ProposalSample(None, 'not a Twist', undecodable=True), received_ns=10 * SECOND)
    for held, reason in ((bad, 'bad proposal: u: contains NaN'),
                         (undecodable, 'undecodable proposal: not a Twist')):
        decision = _again(safety_filter, held, FREE_STATE, 10_100 * MS, 10_100 * MS)
        assert decision.fail_safe and decision.reason == reason


# --- when a state is answered -------------------------------------------------------------------

def test_refilter_due_needs_the_switch_a_proposal_and_the_period():
    held = _held([0.0, 0.0], received_ns=0)
    due = dict(enabled=True, held=held, last_answer_ns=1 * SECOND, min_period_s=0.02)
    assert fl.refilter_due(now_ns=1 * SECOND + 20 * MS, **due)
    assert not fl.refilter_due(now_ns=1 * SECOND + 19 * MS, **due)
    assert not fl.refilter_due(now_ns=9 * SECOND, **{**due, 'enabled': False})
    assert not fl.refilter_due(now_ns=9 * SECOND, **{**due, 'held': None})
    assert fl.refilter_due(now_ns=0, **{**due, 'last_answer_ns': None})


@settings(max_examples=150, deadline=None)
@given(events=st.lists(st.tuples(st.integers(0, 30 * MS), st.booleans()), max_size=300),
       period_ms=st.sampled_from([0, 1, 7, 20, 100]))
def test_refilters_are_bounded_by_the_period_and_follow_no_answer_too_soon(events, period_ms):
    """Any arrivals of states (False) and proposals (True): at most one answer per state,
    every answer to a state at least min_period_s after the answer before it, so that in any
    span T there are at most T / min_period_s + 1 of them."""
    now, last_answer, answers = 0, None, []
    for gap, is_proposal in events:
        now += gap
        if is_proposal:
            last_answer = now
            answers.append((now, True))
        elif fl.refilter_due(enabled=True, held=_held([0.0, 0.0], 0), last_answer_ns=last_answer,
                             now_ns=now, min_period_s=period_ms / 1000):
            assert last_answer is None or now - last_answer >= period_ms * MS
            last_answer = now
            answers.append((now, False))
    refilters = [t for t, proposed in answers if not proposed]
    if period_ms and refilters:
        span = refilters[-1] - refilters[0]
        assert len(refilters) <= span // (period_ms * MS) + 1
    assert len(refilters) <= sum(1 for _, proposed in events if not proposed)


# --- the node's callbacks -----------------------------------------------------------------------

class _Clock:
    """A monotonic clock the test moves (stands in for the node's ``time`` module)."""

    def __init__(self) -> None:
        self.now_ns = 100 * SECOND

    def monotonic_ns(self) -> int:
        return self.now_ns


def _node_harness(ros_domain_id: int, monkeypatch: Any, *ros_args: str):
    from rcbf_ros.ros import safety_filter_node
    clock = _Clock()
    monkeypatch.setattr(safety_filter_node, 'time', clock)
    return _harness(ros_domain_id, *ros_args), clock


@pytest.fixture
def refilter(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(ros_domain_id, monkeypatch, '-p', 'refilter_on_state:=true')
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture
def lockstep(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(ros_domain_id, monkeypatch)
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


def _info(harness: Any, index: int = -1) -> dict[str, np.ndarray]:
    return msg_to_sections(harness.infos[index])


def test_by_default_a_state_gets_no_answer(lockstep):
    """Lock-step: exactly one answer per proposal, whatever states come in between."""
    harness, clock = lockstep
    assert harness.node.settings.refilter_on_state is False
    harness.node._on_state(_cdr({'state': list(FAR)}))
    harness.answer(_cdr({'u': AT_OBSTACLE}))
    for step in range(50):
        clock.now_ns += 20 * MS
        harness.node._on_state(_cdr({'state': [-3.0 + 0.04 * step, 0.0, 0.0]}))
    assert len(harness.commands) == len(harness.infos) == 1
    assert harness.node.refilters == 0


def test_a_quiet_controller_is_corrected_then_stopped(refilter, capsys):
    """One proposal at the obstacle, then states every 20 ms as the robot drives at it: an
    answer per state, slowed down before the obstacle, the fail-safe after 0.5 s (status
    18, one throttled log line), until a new proposal is filtered again."""
    harness, clock = refilter
    node = harness.node
    node._on_state(_cdr({'state': list(FAR)}))
    proposed_ns = clock.now_ns
    u, _ = harness.answer(_cdr({'u': AT_OBSTACLE}))
    assert list(u) == AT_OBSTACLE
    xs = [*np.linspace(-3.0, -0.85, 20), *[-0.85] * 10]   # there after 0.4 s, then 0.2 s more
    for x in xs:
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': [float(x), 0.0, 0.0]}))
    assert len(harness.commands) == len(harness.infos) == 1 + len(xs)  # one per state
    assert node.refilters == len(xs) and node.proposals_received == 1
    for index in range(1, len(harness.infos)):
        info = _info(harness, index)
        age_s = (index * 20 * MS) / SECOND
        np.testing.assert_array_equal(info['u_rl'], AT_OBSTACLE)
        np.testing.assert_array_equal(msg_to_sections(harness.commands[index])['u'], info['u'])
        assert info['fail_safe'][0] == (1.0 if age_s > 0.5 else 0.0), index
        if age_s <= 0.5:   # filtered at the state that came
            np.testing.assert_array_equal(info['state'], [xs[index - 1], 0.0, 0.0])
    corrected = [_info(harness, i)['u'][0] for i in range(1, len(harness.infos))
                 if _info(harness, i)['fail_safe'][0] == 0]
    assert min(corrected) < 2.5   # slowed down before the obstacle, without a new proposal
    last = _info(harness, -1)
    assert last['status'][0] == STATUS_CODES['stale proposal']
    np.testing.assert_array_equal(last['u'], FAIL_SAFE)
    # The fail-safe keeps coming at the state rate; its log line is throttled.
    for _ in range(10):
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))
    assert len(harness.commands) == 1 + len(xs) + 10
    assert all(_info(harness, -i)['fail_safe'][0] == 1 for i in range(1, 11))
    log = capsys.readouterr().err
    assert log.count('fail-safe: stale proposal: ') == 1, log   # throttled (log_throttle_s 1)
    # ... for stop_pub_timeout (2 s) after its first answer (the state at 0.52 s, the first
    # after the proposal went stale at 0.5 s), then nothing
    sent, answered = len(harness.commands), 0
    while clock.now_ns + 20 * MS <= proposed_ns + int(2.52 * SECOND):
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))
        answered += 1
    assert answered > 50 and len(harness.commands) == sent + answered
    for _ in range(50):
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))
    assert len(harness.commands) == sent + answered  # the base holds the fail-safe it got
    # A new proposal: filtered again, and held.
    u, _ = harness.answer(_cdr({'u': [1.0, 0.0]}))
    assert list(u) == [1.0, 0.0]
    clock.now_ns += 20 * MS
    node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))
    assert list(_info(harness, -1)['u']) == [1.0, 0.0]


def test_an_answer_after_the_node_went_quiet_is_not_a_late_one(refilter, capsys):
    """With control_period_s (0.05 s): a controller quiet for good gets the fail-safe at each
    state (20 ms apart: none late) for stop_pub_timeout (0.1 s), then the node goes quiet;
    the next proposal's answer, a second later, is no overrun of the period (none was owed:
    the base held the fail-safe), so neither counted in late_answers nor said in the log."""
    harness, clock = refilter
    node = harness.node
    assert node.set_parameters([Parameter('control_period_s', value=0.05),
                                Parameter('stop_pub_timeout', value=0.1)])[0].successful
    node._on_state(_cdr({'state': list(FAR)}))
    harness.answer(_cdr({'u': [1.0, 0.0]}))
    for _ in range(50):  # 1 s of states: answered to 0.62 s (the fail-safe from 0.52), then none
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': list(FAR)}))
    assert len(harness.commands) == 1 + 31
    assert _info(harness)['status'][0] == STATUS_CODES['stale proposal']
    u, _ = harness.answer(_cdr({'u': [1.0, 0.0]}))
    assert list(u) == [1.0, 0.0] and len(harness.commands) == 1 + 31 + 1
    assert node.late_answers == 0
    assert 'late answer' not in capsys.readouterr().err


def test_a_stale_proposal_stays_stale_when_max_proposal_age_s_is_raised(refilter):
    """A proposal gone stale (0.5 s), then max_proposal_age_s raised to 100 s, at once or
    after the node went quiet: the quiet controller's command does not come back (the
    fail-safe, status 18, while answers go out); a new proposal is filtered as usual."""
    harness, clock = refilter
    node = harness.node
    assert node.set_parameters([Parameter('stop_pub_timeout', value=0.1)])[0].successful
    node._on_state(_cdr({'state': list(FAR)}))
    u, _ = harness.answer(_cdr({'u': [1.0, 0.0]}))
    assert list(u) == [1.0, 0.0]
    for _ in range(27):  # to 0.54 s: stale from 0.52 s
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': list(FAR)}))
    assert _info(harness)['status'][0] == STATUS_CODES['stale proposal']
    assert node.set_parameters([Parameter('max_proposal_age_s', value=100.0)])[0].successful
    for _ in range(30):  # the fail-safe to 0.62 s (stop_pub_timeout from 0.52 s), then none
        clock.now_ns += 20 * MS
        node._on_state(_cdr({'state': list(FAR)}))
    answers = [msg_to_sections(info) for info in harness.infos[28:]]
    assert len(answers) == 4 and all(info['fail_safe'][0] == 1 for info in answers)
    assert all(info['status'][0] == STATUS_CODES['stale proposal'] for info in answers)
    u, _ = harness.answer(_cdr({'u': [1.0, 0.0]}))
    assert list(u) == [1.0, 0.0]
    clock.now_ns += 20 * MS
    node._on_state(_cdr({'state': list(FAR)}))
    assert list(_info(harness)['u']) == [1.0, 0.0]  # the new one: fresh for 100 s


def test_states_faster_than_the_period_are_answered_at_most_once_a_period(refilter):
    """States at 1 kHz for 1 s with the default refilter_min_period_s (0.01 s): 100 answers,
    not 1000; and none right after a proposal's answer."""
    harness, clock = refilter
    node = harness.node
    assert node.settings.refilter_min_period_s == 0.01
    node._on_state(_cdr({'state': list(FREE_STATE)}))
    harness.answer(_cdr({'u': [1.0, 0.3]}))
    for _ in range(1000):
        clock.now_ns += 1 * MS
        node._on_state(_cdr({'state': list(FREE_STATE)}))
    assert node.refilters == 100 and len(harness.commands) == 101
    clock.now_ns += 1 * MS
    harness.answer(_cdr({'u': [1.0, 0.3]}))
    clock.now_ns += 5 * MS
    node._on_state(_cdr({'state': list(FREE_STATE)}))   # 5 ms after a proposal's answer
    assert node.refilters == 100


def test_no_answer_before_a_first_proposal_nor_after_an_internal_error(refilter, monkeypatch):
    harness, clock = refilter
    node = harness.node
    for _ in range(5):
        clock.now_ns += 50 * MS
        node._on_state(_cdr({'state': list(FREE_STATE)}))
    assert harness.commands == []
    harness.answer(_cdr({'u': [1.0, 0.3]}))

    def broken(*_args: Any, **_kwargs: Any) -> None:
        raise RuntimeError('broken reader')
    monkeypatch.setattr(node._edge, 'read_proposal', broken)
    u, _ = harness.answer(_cdr({'u': [1.0, 0.3]}))   # the fail-safe: nothing held any more
    np.testing.assert_array_equal(u, FAIL_SAFE)
    clock.now_ns += 50 * MS
    node._on_state(_cdr({'state': list(FREE_STATE)}))
    assert len(harness.commands) == 2


def test_a_bad_state_turns_the_held_command_into_the_fail_safe(refilter):
    harness, clock = refilter
    harness.node._on_state(_cdr({'state': list(FREE_STATE)}))
    harness.answer(_cdr({'u': [1.0, 0.3]}))
    clock.now_ns += 50 * MS
    harness.node._on_state(_cdr({'state': [np.nan, 0.0, 0.0]}))
    info = _info(harness, -1)
    assert info['fail_safe'][0] == 1 and info['status'][0] == STATUS_CODES['bad state']


@pytest.fixture
def stamped_refilter(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(
        ros_domain_id, monkeypatch, '-p', 'refilter_on_state:=true', '-p',
        'command_type:=twist_stamped', '-p', 'state_type:=odometry', '-p',
        'state_frame_id:=map')
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


def test_a_refiltered_twist_stamped_has_the_proposals_frame_and_a_fresh_stamp(
        stamped_refilter):
    """The proposal's header.frame_id; the stamp of the node's clock at the answer (a
    consumer that checks a command's age sees it new), not the proposal's."""
    harness, clock = stamped_refilter
    harness.node._on_state(_odometry(-3.0, 0.0, 0.0))
    harness.answer(_twist_stamped(AT_OBSTACLE, 1234, 567_000_000, 'base_link'))
    clock.now_ns += 50 * MS
    before_ns = time.time_ns()
    harness.node._on_state(_odometry(-0.85, 0.0, 0.0))
    after_ns = time.time_ns()
    command = harness.commands[-1]
    assert len(harness.commands) == 2 and command.header.frame_id == 'base_link'
    stamp_ns = command.header.stamp.sec * SECOND + command.header.stamp.nanosec
    assert before_ns <= stamp_ns <= after_ns
    assert 0.0 <= command.twist.linear.x < 2.5   # corrected at the new state


def test_the_switch_changes_at_runtime(lockstep):
    from rcbf_ros.ros.runtime import Parameter
    harness, clock = lockstep
    node = harness.node
    node._on_state(_cdr({'state': list(FREE_STATE)}))
    harness.answer(_cdr({'u': [1.0, 0.3]}))
    result = node.set_parameters([Parameter('refilter_on_state', Parameter.Type.BOOL, True)])
    assert result[0].successful and node.settings.refilter_on_state is True
    clock.now_ns += 50 * MS
    node._on_state(_cdr({'state': list(FREE_STATE)}))
    assert len(harness.commands) == 2
    result = node.set_parameters([Parameter('max_proposal_age_s', Parameter.Type.DOUBLE, 0.0)])
    assert not result[0].successful and 'max_proposal_age_s' in result[0].reason


def test_status_18_is_the_stale_proposal_only():
    assert [k for k, v in STATUS_CODES.items() if v == 18] == ['stale proposal']
    decision = fl.Decision(u_safe=np.zeros(2), u_rl=None, level=fl.ERROR, fail_safe=True,
                           reason='stale proposal: 0.610 s old > max_proposal_age_s = 0.5')
    assert filter_edge.status_name(decision) == 'stale proposal'


def test_a_bool_for_a_number_is_refused_even_where_it_equals_the_value(lockstep):
    """``True == 1.0`` in Python: log_throttle_s:=true on its default 1.0 was stored without a
    filter built for it; it is built, and refused, as any value the key does not take."""
    from rcbf_ros.ros.runtime import Parameter
    node = lockstep[0].node
    (result,) = node.set_parameters([Parameter('log_throttle_s', Parameter.Type.BOOL, True)])
    assert not result.successful and result.reason.startswith('log_throttle_s: ')
    assert node.get_parameter('log_throttle_s').value == 1.0


@pytest.fixture
def source_refilter(ros_domain_id, monkeypatch):
    instance, clock = _node_harness(
        ros_domain_id, monkeypatch, '-p', 'refilter_on_state:=true', '-p',
        "observation_sources:=['front']", '-p', 'front.type:=scan', '-p', 'front.topic:=scan',
        '-p', 'footprint.radius:=0.2')
    yield instance, clock
    instance.node.destroy_node()
    rclpy.try_shutdown()


def _scan_now(ranges: list[float]) -> bytes:
    """A LaserScan in base_link, stamped now on the system clock (the node's)."""
    data = bytearray(_scan(ranges))
    now_ns = time.time_ns()
    data[4:8] = (now_ns // SECOND).to_bytes(4, 'little', signed=True)
    data[8:12] = (now_ns % SECOND).to_bytes(4, 'little')
    return bytes(data)


def test_a_source_message_is_answered_too(source_refilter):
    """A scan, like a state, re-filters the proposal in force: without one the proposal's
    answer is the fail-safe (no message yet); the scan's answer filters it."""
    harness, clock = source_refilter
    node = harness.node
    node._on_state(_cdr({'state': list(FAR)}))
    u, _ = harness.answer(_cdr({'u': [1.0, 0.0]}))
    np.testing.assert_array_equal(u, FAIL_SAFE)
    assert _info(harness)['status'][0] == STATUS_CODES['source unusable']
    clock.now_ns += 50 * MS
    node._on_source('front', _scan_now([5.0]))
    assert len(harness.commands) == 2 and node.refilters == 1
    info = _info(harness)
    assert info['fail_safe'][0] == 0, info
    np.testing.assert_array_equal(info['u'], [1.0, 0.0])

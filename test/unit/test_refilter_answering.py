"""``rcbf_ros refilter`` answers as the node does: at proposals, at states (refilter_on_state)
and at the hold timer's calls (control_period_s), refusing states older than latency_s.

Bags built here with known timing (a proposal 1 ms after the first state, states every 10 ms,
a controller that goes quiet); the expected answers are counted by hand from the node's rules
(docs/SAFETY_FILTER.md) in each test's docstring. The cross-check drives the node's
:class:`AnswerRules` as the node's unit tests do (a timer call every period, each message in
turn, no arithmetic) and compares its decisions one for one with the bag written.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_refilter import _sections, PARAMS_A
import yaml

from rcbf_ros.bag import BagWriter, read_bag
from rcbf_ros.bag.refilter import (
    HOLD_STRETCH_LIMIT,
    main,
    OUTPUT_INFO_TOPIC,
    refilter_bag,
    RefilterError,
)
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.messages.conversions import sections_from_cdr
from rcbf_ros.node_logic import safety_filter as fl
from rcbf_ros.node_logic.answer_rules import AnswerRules

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
T, L = 0.05, 0.02
FREE = [-2.4, 0.0, 0.0]          # config A: far from both obstacles
AWAY = [0.0, -20.0, 0.0]         # far enough for the margin of latency_s 1 s
U = [1.0, 0.05]


def _params(**node: Any) -> dict:
    return {**PARAMS_A, 'control_period_s': T, 'latency_s': L, **node}


def _bag(directory: Path, *, states_ms: list[float], proposals_ms: list[float],
         state: list[float] = FREE) -> Path:
    """/state (``state``) and /cmd_proposed (U) at the given times after T0 (ms)."""
    events = sorted([(t, 0, '/state') for t in states_ms] + [(t, 1, '/cmd_proposed')
                                                             for t in proposals_ms])
    with BagWriter(directory) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        for t, _, topic in events:
            body = _sections(state=state) if topic == '/state' else _sections(u=U)
            bag.write_message(topic, body, T0 + round(t * MS))
    return directory


def _answers(path: Path) -> list[tuple[float, dict[str, np.ndarray]]]:
    """(ms after T0, filter_info sections) of each answer written, in order."""
    return [((m.log_time_ns - T0) / MS, sections_from_cdr(m.data, 'u'))
            for m in read_bag(path, topics=[OUTPUT_INFO_TOPIC])]


def _status(info: dict[str, np.ndarray]) -> int:
    return int(info['status'][0])


def test_a_quiet_controller_gets_hold_answers_every_three_calls(tmp_path: Path) -> None:
    """States every 10 ms from 0 to 400 ms, one proposal at 1 ms, lock-step. The timer calls
    every 12.5 ms from 0 (the first state) and answers at a call 37.5 ms or more after the
    latest answer: 50 (49 ms after the proposal's; 36.5 at 37.5 is too soon), then every 3
    calls: 87.5, 125, ..., 387.5 (425 is after the last message). Each at the state before
    it (10 ms or less old: within latency_s 0.02), filtered (OK)."""
    source = _bag(tmp_path / 'run', states_ms=[10.0 * k for k in range(41)],
                  proposals_ms=[1.0])
    summary = refilter_bag(source, tmp_path / 'out', _params())
    answers = _answers(tmp_path / 'out')
    holds = [50.0 + 37.5 * j for j in range(10)]
    assert [t for t, _ in answers] == [1.0, *holds]
    assert (summary.proposals, summary.refilters, summary.holds, summary.hold_repeats) == (
        1, 0, 10, 0)
    for t, info in answers:
        assert info['fail_safe'][0] == 0 and list(info['u']) == U, t
    assert summary.fail_safe_answers == {'proposal': 0, 'refilter': 0, 'hold': 0}
    assert 'answers: proposal 1   re-filter 0   hold 10' in summary.format()


def test_states_stopping_give_a_late_state_fail_safe_then_repeats(tmp_path: Path) -> None:
    """States every 10 ms to 100 ms, then one at 300 ms; a proposal at 1 ms. Holds at 50 and
    87.5 (at states 10 and 7.5 ms old), then at 125 the state of 100 is 25 ms old: the
    fail-safe, status 19 (late state), saying that the command in force ran out. In the
    stretch to 300 ms nothing else changes: the calls at 162.5, 200, 237.5 and 275 would
    repeat it (counted, not written)."""
    source = _bag(tmp_path / 'run', states_ms=[10.0 * k for k in range(11)] + [300.0],
                  proposals_ms=[1.0])
    summary = refilter_bag(source, tmp_path / 'out', _params())
    answers = _answers(tmp_path / 'out')
    assert [t for t, _ in answers] == [1.0, 50.0, 87.5, 125.0]
    assert [_status(info) for _, info in answers[:3]] == [0, 0, 0]
    late = answers[-1][1]
    assert late['fail_safe'][0] == 1 and _status(late) == STATUS_CODES['late state'] == 19
    assert (summary.holds, summary.hold_repeats) == (3, 4)
    assert summary.fail_safe_answers == {'proposal': 0, 'refilter': 0, 'hold': 1}
    diagnostics = [m for m in read_bag(tmp_path / 'out', topics=['/refilter/diagnostics'])]
    assert b'control_period_s = 0.05' in diagnostics[-1].data
    assert b'late state: 0.025000 s old > latency_s = 0.02' in diagnostics[-1].data


def test_refilter_on_state_answers_each_state_then_the_timer_fills_the_gap(
        tmp_path: Path) -> None:
    """refilter_on_state (refilter_min_period_s 0.01): the state at 10 ms is 9 ms after the
    proposal's answer (too soon); those at 20 ... 100 ms are answered (9), the timer not (an
    answer every 10 ms). After 100: the call at 137.5 answers at a 37.5 ms old state: late,
    the fail-safe; 175, 212.5, 250 and 287.5 repeat it. The state at 300 comes 12.5 ms after
    the latest (repeated) answer: re-filtered, fresh, OK."""
    source = _bag(tmp_path / 'run', states_ms=[10.0 * k for k in range(11)] + [300.0],
                  proposals_ms=[1.0])
    summary = refilter_bag(source, tmp_path / 'out', _params(refilter_on_state=True))
    answers = _answers(tmp_path / 'out')
    assert [t for t, _ in answers] == [1.0, *(10.0 * k for k in range(2, 11)), 137.5, 300.0]
    assert [_status(info) for _, info in answers] == [0] * 10 + [19, 0]
    assert (summary.refilters, summary.holds, summary.hold_repeats) == (10, 1, 4)
    np.testing.assert_array_equal(answers[-1][1]['state'], FREE)


def test_without_control_period_the_old_answers_stand(tmp_path: Path) -> None:
    """control_period_s and latency_s 0 (refilter_on_state off, the node's default): one
    answer per proposal, however old the state (within max_state_age_s)."""
    source = _bag(tmp_path / 'run', states_ms=[0.0], proposals_ms=[1.0, 200.0, 400.0])
    summary = refilter_bag(source, tmp_path / 'out', PARAMS_A)
    assert [t for t, _ in _answers(tmp_path / 'out')] == [1.0, 200.0, 400.0]
    assert summary.processed == 3 and summary.holds == summary.refilters == 0


def test_a_proposal_at_a_late_state_is_the_fail_safe(tmp_path: Path) -> None:
    """With latency_s 0.02 a proposal 30 ms after the state is answered with the fail-safe
    (status 19), counted as skipped with its reason; one 20 ms after it is filtered."""
    source = _bag(tmp_path / 'run', states_ms=[0.0, 100.0], proposals_ms=[20.0, 130.0])
    summary = refilter_bag(source, tmp_path / 'out', dict(PARAMS_A, latency_s=L))
    answers = _answers(tmp_path / 'out')
    assert [(t, _status(info)) for t, info in answers] == [(20.0, 0), (130.0, 19)]
    assert summary.processed == 1 and summary.skipped == {'late state': 1}


def test_a_long_gap_costs_nothing_when_nothing_is_held(tmp_path: Path) -> None:
    """Two states a year apart and a proposal after them: no call answers before the first
    answer (nothing is held), and the year is skipped by arithmetic, not called 2.5e9
    times."""
    year_ms = 365 * 24 * 3600 * 1000.0
    source = _bag(tmp_path / 'run', states_ms=[0.0, year_ms], proposals_ms=[year_ms + 1])
    summary = refilter_bag(source, tmp_path / 'out', _params())
    assert [t for t, _ in _answers(tmp_path / 'out')] == [year_ms + 1]
    assert summary.holds == summary.hold_repeats == 0


@pytest.mark.parametrize('stop_pub_timeout', [2.0, 1e9])
def test_a_long_gap_after_a_proposal_is_one_fail_safe_and_counted_repeats(
        tmp_path: Path, stop_pub_timeout: float) -> None:
    """A proposal, then a year without messages: the node's timer answers every 37.5 ms,
    the fail-safe from the first late state on; written up to that one, the rest counted,
    up to max_proposal_age_s + stop_pub_timeout after the proposal (then the node is quiet:
    with 1e9 s, the whole year)."""
    year_ns = 365 * 24 * 3600 * 10 ** 9
    source = _bag(tmp_path / 'run', states_ms=[0.0, year_ns / MS], proposals_ms=[1.0])
    summary = refilter_bag(source, tmp_path / 'out',
                           _params(stop_pub_timeout=stop_pub_timeout))
    answers = _answers(tmp_path / 'out')
    assert [t for t, _ in answers] == [1.0, 50.0]   # the state at 0 is 50 ms old: late
    assert _status(answers[-1][1]) == 19
    period_ns = round(T / 4 * 1e9)
    quiet_ns = MS + round((0.5 + stop_pub_timeout) * 1e9)  # max_proposal_age_s 0.5
    calls = min(year_ns, quiet_ns) // period_ns     # the last call that answers
    assert summary.hold_repeats == (calls - 4) // 3 and summary.holds == 1


def test_the_longest_quiet_stretch_within_the_limits_is_simulated(tmp_path: Path) -> None:
    """control_period_s 0.001 (a call every 1 ms, each answering) and latency_s at its limit
    1 s: the answers stay OK while the state is at most 1 s old, then the fail-safe. The
    proposal's at 0.5 ms and 1000 holds (ages 1 ... 1000 ms), the late one at 1001 ms, then
    3999 repeats to 5000 ms: 1000 OK holds, under HOLD_STRETCH_LIMIT."""
    source = _bag(tmp_path / 'run', states_ms=[0.0, 5000.0], proposals_ms=[0.5], state=AWAY)
    summary = refilter_bag(source, tmp_path / 'out', _params(
        control_period_s=0.001, latency_s=1.0, max_proposal_age_s=10.0, max_state_age_s=10.0))
    statuses = [_status(info) for _, info in _answers(tmp_path / 'out')]
    assert statuses == [0] * 1001 + [19] and summary.holds == 1001
    assert 1000 < HOLD_STRETCH_LIMIT and summary.hold_repeats == 5000 - 1001


def test_a_stretch_past_the_limit_is_refused_in_one_line(tmp_path: Path, capsys: Any,
                                                         monkeypatch: Any) -> None:
    """Should the parameters' limits allow more answers before the fail-safe than
    HOLD_STRETCH_LIMIT (here lowered to 5), the run is refused naming them; no bag left."""
    from rcbf_ros.bag import refilter
    monkeypatch.setattr(refilter, 'HOLD_STRETCH_LIMIT', 5)
    source = _bag(tmp_path / 'run', states_ms=[0.0, 3000.0], proposals_ms=[1.0], state=AWAY)
    params = _params(latency_s=1.0)
    with pytest.raises(RefilterError, match='answered 5 times since the last message.*'
                                            'latency_s = 1, max_proposal_age_s = 0.5'):
        refilter_bag(source, tmp_path / 'out', params)
    assert not (tmp_path / 'out').exists()
    yaml_file = tmp_path / 'p.yaml'
    yaml_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
    assert main([str(source), str(tmp_path / 'out'), '--params-file', str(yaml_file)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'answered 5 times' in err
    assert not (tmp_path / 'out').exists()


# --- the cross-check ------------------------------------------------------------------------

def _node_decisions(params: dict, states_ms: list[float], proposals_ms: list[float]
                    ) -> tuple[list[tuple[float, fl.Decision]], AnswerRules]:
    """The node's rules driven as its unit tests drive them: a timer call every T / 4 from
    the first message, each call made (the ones at a message's time first), each message in
    turn; the calls after a fail-safe answer of the timer and before the next message left out
    (the refilter's documented rule: they repeat it). And the rules, with their counts."""
    active = fl.build_active_filter(params=dict(params))
    rules = AnswerRules()
    period_ns = round(fl.hold_timer_period_s(T) * 1e9)
    events = sorted([(round(t * MS), 0, 'state') for t in states_ms]
                    + [(round(t * MS), 1, 'proposal') for t in proposals_ms])
    out: list[tuple[float, fl.Decision]] = []
    origin, call = events[0][0], 0
    for now, _, kind in events:
        stopped = False
        while origin + call * period_ns <= now:
            tick = origin + call * period_ns
            decision = rules.hold(now_ns=tick, timer_period_s=period_ns / 1e9, active=active)
            if decision is not None and not stopped:
                out.append((tick / MS, decision))
                stopped = decision.fail_safe
            call += 1
        if kind == 'state':
            rules.latest_state = fl.StateSample(received_ns=now, state=np.array(FREE))
            decision = rules.refilter(now_ns=now, active=active)
        else:
            sample = fl.ProposalSample(fl.Proposal(u=np.array(U)))
            decision = rules.propose(sample, now_ns=now, active=active)
        if decision is not None:
            out.append((now / MS, decision))
    return out, rules


def _check_one_for_one(tmp_path: Path, params: dict, states_ms: list[float],
                       proposals_ms: list[float]) -> None:
    source = _bag(tmp_path / 'run', states_ms=states_ms, proposals_ms=proposals_ms)
    summary = refilter_bag(source, tmp_path / 'out', params)
    written = _answers(tmp_path / 'out')
    expected, rules = _node_decisions(params, states_ms, proposals_ms)
    assert (summary.proposals, summary.refilters, summary.holds + summary.hold_repeats) == (
        rules.proposals, rules.refilters, rules.holds)
    assert [t for t, _ in written] == [t for t, _ in expected]
    for (t, info), (_, decision) in zip(written, expected):
        np.testing.assert_array_equal(info['u'], decision.u_safe, err_msg=str(t))
        assert info['fail_safe'][0] == decision.fail_safe, t
        assert _status(info) == fl.status_code(decision), t
    _check_the_fail_safe_is_held(written, params, states_ms, proposals_ms)


def _check_the_fail_safe_is_held(written: list[tuple[float, dict[str, np.ndarray]]],
                                 params: dict, states_ms: list[float],
                                 proposals_ms: list[float]) -> None:
    """What the base is left holding when a proposal goes stale: from each proposal to the
    next (or to the last message), once there was time for the timer's answer after it went
    stale (max_proposal_age_s, then control_period_s T and a call), the last answer of the
    stretch is the fail-safe, whatever stop_pub_timeout and the message times."""
    max_age_ms = params.get('max_proposal_age_s', 0.5) * 1000
    proposals = sorted(proposals_ms)
    ends = proposals[1:] + [max(states_ms + proposals_ms)]
    for start, end in zip(proposals, ends):
        if end <= start + max_age_ms + 2 * T * 1000:
            continue
        stretch = [info for t, info in written if start <= t < end]
        assert stretch and stretch[-1]['fail_safe'][0] == 1, (start, end)


SCENARIOS = {
    'pauses': ([10.0 * k for k in range(16)] + [260.0 + 10 * k for k in range(30)],
               [1.0 + 50 * k for k in range(3)] + [301.0, 351.0]),
    'quiet': ([10.0 * k for k in range(80)], [1.0]),
}
"""(states, proposals) in ms: a controller at 20 Hz that pauses (100 to 300 ms) with states
at 100 Hz that pause (150 to 260 ms); one proposal, then states to 790 ms (the proposal stale
from 501 ms on: status 18)."""


@pytest.mark.parametrize('scenario', sorted(SCENARIOS))
@pytest.mark.parametrize('refilter_on_state', [False, True])
def test_the_node_rules_give_the_same_answers_one_for_one(tmp_path: Path, scenario: str,
                                                          refilter_on_state: bool) -> None:
    """Every answer of the refilter is one the node's rules give, at the same time, with the
    same command and status; and the counts by kind are theirs."""
    states, proposals = SCENARIOS[scenario]
    _check_one_for_one(tmp_path, _params(refilter_on_state=refilter_on_state), states,
                       proposals)
    if scenario == 'quiet':
        statuses = {_status(info) for _, info in _answers(tmp_path / 'out')}
        assert STATUS_CODES['stale proposal'] in statuses


@pytest.mark.parametrize('refilter_on_state', [False, True])
def test_a_quiet_controller_s_fail_safe_stops_after_stop_pub_timeout(
        tmp_path: Path, refilter_on_state: bool) -> None:
    """One proposal at 1 ms, states every 10 ms to 790 ms: the fail-safe from its first
    answer after 501 ms (max_proposal_age_s 0.5), answers for 0.1 s more (stop_pub_timeout),
    then none; the node's rules give the same, and a new proposal is answered at once."""
    states, proposals = SCENARIOS['quiet']
    params = _params(refilter_on_state=refilter_on_state, stop_pub_timeout=0.1)
    _check_one_for_one(tmp_path / 'a', params, states, proposals)
    times = [t for t, _ in _answers(tmp_path / 'a' / 'out')]
    first = min(t for t in times if t > 501.0)  # a state's at 510, or the timer's at 537.5
    assert first == (510.0 if refilter_on_state else 537.5)
    assert first + 100.0 - 37.5 < max(times) <= first + 100.0, times  # the timer: 37.5 ms
    assert {_status(info) for t, info in _answers(tmp_path / 'a' / 'out') if t > 501.0} == {
        STATUS_CODES['stale proposal']}
    _check_one_for_one(tmp_path / 'b', params, states, proposals + [700.5])
    assert [t for t, _ in _answers(tmp_path / 'b' / 'out') if t > max(times)][0] == 700.5


@pytest.mark.parametrize('refilter_on_state', [False, True])
@pytest.mark.parametrize('stop_pub_timeout,min_period_s,period_s', [
    (0.0, 0.01, T), (0.005, 0.01, T), (0.1, 0.3, 0.0)])
def test_the_node_goes_quiet_only_after_the_fail_safe_went_out(
        tmp_path: Path, refilter_on_state: bool, stop_pub_timeout: float,
        min_period_s: float, period_s: float) -> None:
    """One proposal at 1 ms, states every 10 ms to 790 ms, a stop_pub_timeout shorter than
    the time between answers (0; 5 ms; 0.1 s with a re-filter at most every 0.3 s and no
    hold timer): the stale proposal's fail-safe still goes out (status 18) and is the last
    answer, so the base holds a stop, not the quiet controller's command; the node's rules
    give the same."""
    states, proposals = SCENARIOS['quiet']
    params = _params(refilter_on_state=refilter_on_state, stop_pub_timeout=stop_pub_timeout,
                     refilter_min_period_s=min_period_s, control_period_s=period_s,
                     latency_s=L if period_s else 0.0)
    if not (refilter_on_state or period_s):
        pytest.skip('lock-step without a hold timer: a proposal is answered once')
    _check_one_for_one(tmp_path, params, states, proposals)
    answers = _answers(tmp_path / 'out')
    last = answers[-1][1]
    assert last['fail_safe'][0] == 1 and _status(last) == STATUS_CODES['stale proposal']
    assert answers[-1][0] <= 501.0 + 1000 * (T + stop_pub_timeout + min_period_s)


@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(states=st.lists(st.integers(0, 1000), min_size=1, max_size=40),
       proposals=st.lists(st.integers(0, 1000), min_size=1, max_size=10),
       refilter_on_state=st.booleans(), latency_ms=st.sampled_from([0, 7, 20, 60]),
       quiet_ms=st.sampled_from([(500, 2000), (20, 0), (10, 35)]))
def test_any_timing_gives_the_node_rules_answers(tmp_path_factory: Any, states: list[int],
                                                 proposals: list[int], refilter_on_state: bool,
                                                 latency_ms: int,
                                                 quiet_ms: tuple[int, int]) -> None:
    """States and proposals at any times over 200 ms (states on even tenths of a ms,
    proposals on odd ones: no two of them at one log time, whose order a bag does not keep),
    timer calls at a message's time included, a quiet controller's stop after
    max_proposal_age_s + stop_pub_timeout (``quiet_ms``) too: the same answers."""
    params = _params(refilter_on_state=refilter_on_state, latency_s=latency_ms / 1000,
                     max_proposal_age_s=max(quiet_ms[0], 1) / 1000,
                     stop_pub_timeout=quiet_ms[1] / 1000)
    _check_one_for_one(tmp_path_factory.mktemp('any'), params, [t / 5 for t in states],
                       [(2 * t + 1) / 10 for t in proposals])

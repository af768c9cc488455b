"""The safety_filter node re-filtering the proposal in force at each state, over real DDS.

A controller proposes once, full speed at an obstacle, and goes quiet while the robot's states
keep coming closer: with ``refilter_on_state`` the node answers each state, slows the held
command down before the obstacle and, ``max_proposal_age_s`` after the proposal, answers with
the fail-safe (status ``stale proposal``) until a new proposal arrives. Without it (the node's
default, lock-step) the states get no answer: one per proposal.
"""
from __future__ import annotations

import time
from typing import Any

from dds_harness import stop  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import _diagnostic, _sections, _start_filter, _wait_matched, Probe

from rcbf_ros.core.filter_info import STATUS_CODES

pytestmark = pytest.mark.integration

FAIL_SAFE = [0.0, 0.5]
FAR = [-3.0, 0.0, 0.0]          # 2.4 m from the centre obstacle's edge, facing it
NEAR = [-0.85, 0.0, 0.0]        # 0.25 m from it, facing it
AT_OBSTACLE = [2.5, 0.0]        # full speed ahead
MAX_AGE_S = 1.5
"""The proposal's age limit in these runs: long enough that a loaded machine still answers
several states before it, short enough for a test of seconds."""


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def _connect(probe: Probe, process: Any) -> tuple[Any, Any]:
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info', _sections)
    probe.subscribe('diagnostic_msgs/msg/DiagnosticArray', '/diagnostics', _diagnostic)
    state_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/state')
    proposal_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/cmd_proposed')
    probe.start()
    _wait_matched(proposal_pub, process)
    _wait_matched(state_pub, process)
    return state_pub, proposal_pub


def _settled(probe: Probe) -> int:
    """The number of answers once none has come for 0.5 s."""
    settled = -1
    while settled != probe.count('/filter_info'):
        settled = probe.count('/filter_info')
        time.sleep(0.5)
    return settled


def _propose_at(probe: Probe, state_pub: Any, proposal_pub: Any, state: list[float],
                proposal: list[float]) -> float:
    """Publish ``state``, then ``proposal``, until an answer filtered that proposal at that
    state (the first samples of a new writer can be lost until the filter's reader matched);
    when the last proposal was published (monotonic s)."""
    from rcbf_ros.messages.conversions import sections_to_msg
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        before = probe.count('/filter_info')
        state_pub.publish(sections_to_msg({'state': state}))
        time.sleep(0.05)
        proposal_pub.publish(sections_to_msg({'u': proposal}))
        sent = time.monotonic()
        end = sent + 1.0
        while time.monotonic() < end:
            infos = probe.wait_for('/filter_info', 0)[before:]
            if any(info['fail_safe'][0] == 0 and list(info['u_rl']) == proposal
                   and list(info.get('state', [])) == state for info in infos):
                return sent
            time.sleep(0.02)
    raise AssertionError('the safety_filter never filtered a proposal at a state')


def test_a_quiet_controllers_command_is_corrected_then_stopped(ros_domain_id, probe):
    from rcbf_ros.messages.conversions import sections_to_msg
    process = _start_filter(ros_domain_id, '-p', 'safety_filter:refilter_on_state:=true',
                            '-p', f'safety_filter:max_proposal_age_s:={MAX_AGE_S}',
                            '-p', f'safety_filter:fail_safe_action:={FAIL_SAFE}')
    try:
        state_pub, proposal_pub = _connect(probe, process)
        proposed = _propose_at(probe, state_pub, proposal_pub, FAR, AT_OBSTACLE)
        first = probe.count('/filter_info')
        # The controller is quiet; the robot comes closer, then stands 0.25 m from the
        # obstacle, a state every 40 ms, until the answers have been the fail-safe a while.
        path = [[float(x), 0.0, 0.0] for x in np.linspace(FAR[0], NEAR[0], 6)[1:]]
        stale_since = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            state_pub.publish(sections_to_msg({'state': path.pop(0) if path else NEAR}))
            time.sleep(0.04)
            infos = probe.wait_for('/filter_info', 0)
            if stale_since is None and any(info['fail_safe'][0] == 1 for info in infos[first:]):
                stale_since = len(infos)
            if stale_since is not None and len(infos) >= stale_since + 5:
                break
        else:
            raise AssertionError('the re-filtered answers never became the fail-safe')
        stopped = _settled(probe)
        # A new proposal is filtered again at once, and held.
        _propose_at(probe, state_pub, proposal_pub, NEAR, [0.5, 0.0])
    finally:
        output = stop(process, timeout=10)

    with probe.lock:
        timed_infos = list(probe.received['/filter_info'])
    infos = [info for _, info in timed_infos]
    commands = probe.wait_for('/cmd_safe', len(infos))
    assert len(commands) == len(infos)                 # every answer: its command and its info
    for command, info in zip(commands, infos):
        np.testing.assert_array_equal(command['u'], info['u'])
    held = infos[first:stopped]
    assert len(held) >= 10, len(held)                  # the states were answered, no proposal
    assert all(list(info['u_rl']) == AT_OBSTACLE for info in held)
    # Before the age limit: filtered at the states as they came, slowed down near the obstacle.
    filtered = [info for info in held if info['fail_safe'][0] == 0]
    near = [info for info in filtered if list(info['state']) == NEAR]
    assert near and all(0.0 <= info['u'][0] < 2.5 for info in near), near[:1]
    # From the first fail-safe on: every answer the fail-safe, 'stale proposal', no sooner than
    # max_proposal_age_s after the proposal was published (it arrived after that).
    first_stale = next(i for i, info in enumerate(held) if info['fail_safe'][0] == 1)
    assert all(info['fail_safe'][0] == 1 for info in held[first_stale:])
    assert all(info['status'][0] == STATUS_CODES['stale proposal']
               for info in held[first_stale:])
    assert all(list(info['u']) == FAIL_SAFE for info in held[first_stale:])
    assert timed_infos[first + first_stale][0] - proposed >= MAX_AGE_S
    assert len(held) - first_stale >= 5               # it kept coming at the state rate
    diagnostics = probe.wait_for('/diagnostics', 1)
    assert any(message.startswith('stale proposal: ') and message.endswith(
        f'> max_proposal_age_s = {MAX_AGE_S}') for _, message, _ in diagnostics)
    # The new proposal's answer: filtered, not the fail-safe.
    assert infos[-1]['fail_safe'][0] == 0 and list(infos[-1]['u_rl']) == [0.5, 0.0]
    assert 'fail-safe: stale proposal: ' in output and 'Traceback' not in output, output[-3000:]


def test_without_refiltering_a_state_gets_no_answer(ros_domain_id, probe):
    """The node's default: one answer per proposal, whatever states come (lock-step)."""
    from rcbf_ros.messages.conversions import sections_to_msg
    process = _start_filter(ros_domain_id)
    try:
        state_pub, proposal_pub = _connect(probe, process)
        _propose_at(probe, state_pub, proposal_pub, FAR, AT_OBSTACLE)
        answered = _settled(probe)
        for x in np.linspace(FAR[0], NEAR[0], 20):
            state_pub.publish(sections_to_msg({'state': [float(x), 0.0, 0.0]}))
            time.sleep(0.03)
        proposal_pub.publish(sections_to_msg({'u': AT_OBSTACLE}))
        probe.wait_for('/filter_info', answered + 1)
        after = _settled(probe)
    finally:
        output = stop(process, timeout=10)
    assert after == answered + 1                       # the proposal's answer alone
    info = probe.wait_for('/filter_info', after)[-1]
    np.testing.assert_array_equal(info['state'], NEAR)   # at the newest state
    assert 0.0 <= info['u'][0] < 2.5
    assert probe.count('/cmd_safe') == after and 'Traceback' not in output

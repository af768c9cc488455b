"""The safety_filter node's hold timer over real DDS (``control_period_s`` > 0).

A controller proposes once and goes quiet, the state source sends one state and goes quiet
too: the node answers again on its own (no proposal, no state, lock-step ``refilter_on_state``
off), the proposal in force while the state is at most ``latency_s`` old, then the fail-safe,
status ``late state``, its reason naming ``control_period_s``. With ``use_sim_time`` true and no
``/clock`` publisher at all the same happens: the timer runs on the steady clock.
"""
from __future__ import annotations

import time

from dds_harness import stop  # this directory: on sys.path for pytest
import pytest
from test_safety_filter_node import _start_filter
from test_safety_filter_quiet_controller import _connect, _propose_at, _settled, probe  # noqa: F401

from rcbf_ros.core.filter_info import STATUS_CODES

pytestmark = pytest.mark.integration

FAIL_SAFE = [0.0, 0.5]
FAR = [-3.0, 0.0, 0.0]          # 2.4 m from the centre obstacle's edge, facing it
PROPOSAL = [2.5, 0.0]           # full speed ahead (slowed by the margin)
T, L = 0.05, 0.15
"""A state age limit long enough that a loaded machine answers the proposal at its state
(published 50 ms before it), a period whose margin leaves that state a command; the timer
then answers every 37.5-50 ms."""


@pytest.mark.parametrize('clock_args', [
    (),
    ('-p', 'safety_filter:use_sim_time:=true'),   # the node clock stands at 0: no /clock
], ids=['system-time', 'sim-time-without-clock'])
def test_a_quiet_loop_is_answered_by_the_timer_then_fails_safe(
        ros_domain_id, probe, clock_args):  # noqa: F811
    process = _start_filter(ros_domain_id, '-p', f'safety_filter:control_period_s:={T}',
                            '-p', f'safety_filter:latency_s:={L}',
                            '-p', f'safety_filter:fail_safe_action:={FAIL_SAFE}', *clock_args)
    try:
        state_pub, proposal_pub = _connect(probe, process)
        _propose_at(probe, state_pub, proposal_pub, FAR, PROPOSAL)
        first = probe.count('/filter_info')
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:   # nothing more is published to the node
            infos = probe.wait_for('/filter_info', 0)
            late = [i for i in infos[first:] if i['fail_safe'][0] == 1]
            if len(late) >= 3:
                break
            time.sleep(0.1)
        else:
            raise AssertionError('the timer never answered with the fail-safe')
    finally:
        output = stop(process, timeout=10)
    infos = probe.wait_for('/filter_info', 0)
    assert probe.count('/cmd_safe') >= len(infos) - 1
    quiet = infos[first:]
    first_late = next(i for i, info in enumerate(quiet) if info['fail_safe'][0] == 1)
    assert all(info['fail_safe'][0] == 1 for info in quiet[first_late:])
    assert all(info['status'][0] == STATUS_CODES['late state'] for info in quiet[first_late:])
    assert all(list(info['u']) == FAIL_SAFE for info in quiet[first_late:])
    assert all(list(info['u_rl']) == PROPOSAL for info in quiet)
    assert 'fail-safe: late state: ' in output and 'control_period_s = 0.05' in output
    assert 'Traceback' not in output, output[-3000:]

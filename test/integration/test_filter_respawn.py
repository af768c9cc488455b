"""A dead drop-in filter is seen and replaced: ``rcbf_ros launch safety_filter respawn:=true``.

The test is the robot and its controller (Odometry and Twist in, Twist out on the robot's own
names). The filter process is SIGKILLed while commands flow; the launcher starts it again after
``respawn_delay`` and the safe command flows again on ``cmd_out``. What the test measures and
prints is the time from the SIGKILL to the first command the new filter answers (the delay,
the new process's start-up and DDS discovery); it asserts only that the command comes back
within a bound meant to catch a hang, not a speed.
"""
from __future__ import annotations

import os
import signal
import time
from typing import Any

import numpy as np
import pytest
from test_drop_in_filter import _odometry, FIELDS, TOPICS  # this directory: on sys.path
from test_launch_faults import Launch
from test_safety_filter_node import Probe, WAIT_S

pytestmark = pytest.mark.integration

RESPAWN_DELAY_S = 0.5
FREE_STATE = [-2.5, -2.5, -0.75 * np.pi]
"""Far from every obstacle, heading away from them: the filter passes a command through."""
BEFORE, AFTER = [1.0, 0.3], [0.8, -0.2]
"""The controller's command before the kill and after it: only a filter started after the kill
can have answered AFTER, since nobody published it before."""


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def _first_answer(probe: Probe, launch: Launch, odom_pub: Any, twist_pub: Any,
                  proposal: list[float]) -> float:
    """Publish the state and ``proposal`` every 50 ms until ``proposal`` comes out on the
    robot's input unchanged; when it arrived (monotonic s)."""
    from rcbf_ros.messages.conversions import array_to_twist
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        assert launch.process.poll() is None, f'the launch ended:\n{launch.output[-3000:]}'
        odom_pub.publish(_odometry(FREE_STATE))
        twist_pub.publish(array_to_twist(proposal, FIELDS))
        time.sleep(0.05)
        with probe.lock:
            arrived = [t for t, command in probe.received[TOPICS['cmd_out']]
                       if np.array_equal(command, proposal)]
        if arrived:
            return arrived[0]
    raise AssertionError(f'{proposal} never came out on {TOPICS["cmd_out"]} within {WAIT_S} s:'
                         f'\n{launch.output[-3000:]}')


def _gone(pid: int) -> bool:
    """True once ``pid`` has exited (a zombie not yet reaped counts)."""
    try:
        with open(f'/proc/{pid}/stat') as stat:
            return stat.read().rsplit(')', 1)[1].split()[0] == 'Z'
    except OSError:
        return True


def test_a_killed_filter_is_respawned_and_the_safe_command_flows_again(ros_domain_id, probe,
                                                                       record_property):
    from rcbf_ros.messages.conversions import twist_to_array
    launch = Launch(['safety_filter', '--domain-id', str(ros_domain_id), 'respawn:=true',
                     f'respawn_delay:={RESPAWN_DELAY_S}',
                     *(f'{name}:={topic}' for name, topic in TOPICS.items())], ros_domain_id)
    try:
        probe.subscribe('geometry_msgs/msg/Twist', TOPICS['cmd_out'],
                        lambda m: twist_to_array(m, FIELDS))
        odom_pub = probe.publisher('nav_msgs/msg/Odometry', TOPICS['odom'])
        twist_pub = probe.publisher('geometry_msgs/msg/Twist', TOPICS['cmd_in'])
        probe.start()
        _first_answer(probe, launch, odom_pub, twist_pub, BEFORE)
        first = launch.child_pid('rcbf_ros.ros.safety_filter_node')
        killed_at = time.monotonic()
        os.kill(first, signal.SIGKILL)
        while not _gone(first):
            time.sleep(0.001)
        back_at = _first_answer(probe, launch, odom_pub, twist_pub, AFTER)
        second = launch.child_pid('rcbf_ros.ros.safety_filter_node')
        launch.process.send_signal(signal.SIGINT)
    finally:
        code = launch.finish()
    output = launch.output
    respawn_s = back_at - killed_at
    record_property('respawn_s', round(respawn_s, 3))
    print(f'\ncmd_out flowed again {respawn_s:.2f} s after the SIGKILL '
          f'(respawn_delay {RESPAWN_DELAY_S} s)')
    assert second != first
    assert RESPAWN_DELAY_S <= respawn_s < WAIT_S
    assert (f'[launch] safety_filter exited with -9; respawning in {RESPAWN_DELAY_S:g} s'
            in output), output[-3000:]
    assert output.count('[launch] respawning safety_filter') == 1, output[-3000:]
    assert code == 0 and 'Traceback' not in output, output[-3000:]
    assert "respawns {'safety_filter': 1}; exit code 0" in output, output[-3000:]

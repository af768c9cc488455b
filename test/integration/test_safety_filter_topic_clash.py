"""The safety filter node refuses at start two of its names that resolve alike: exit 2, one line
naming both, before any message flows (and so does the drop-in launch around it).

Names are resolved as the runtime resolves them (remaps, namespace): ``cmd_proposed`` onto
``cmd_safe`` would let the controller's commands reach the base unfiltered and the filter
answer its own output; ``state`` on ``/tf`` reads transforms as states.
"""
from __future__ import annotations

import subprocess
import sys

from dds_harness import REPO, spawn, stop, subprocess_env  # this directory: on sys.path
import pytest

UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
LIDAR = str(REPO / 'config' / 'unicycle_lidar.yaml')
WAIT_S = 90.0
"""Upper bound for a start on a loaded machine (a hang, not a speed test)."""

pytestmark = pytest.mark.integration


@pytest.mark.parametrize('params, args, line', [
    (UNICYCLE, ('-r', 'cmd_proposed:=cmd_safe'),
     'cmd_proposed and cmd_safe both resolve to /cmd_safe'),
    (UNICYCLE, ('-r', '__ns:=/robot', '-r', 'cmd_proposed:=/robot/cmd_vel', '-r',
                'cmd_safe:=cmd_vel'), 'cmd_proposed and cmd_safe both resolve to /robot/cmd_vel'),
    (UNICYCLE, ('-r', 'state:=/tf'), '/tf and state both resolve to /tf'),
    (UNICYCLE, ('-r', 'cmd_safe:=/rosout'), '/rosout and cmd_safe both resolve to /rosout'),
    (LIDAR, ('-p', 'state_type:=odometry', '-p', 'command_type:=twist', '-r',
             'cmd_safe:=/tf_static'), '/tf_static and cmd_safe both resolve to /tf_static'),
    (LIDAR, ('-p', 'state_type:=odometry', '-p', 'command_type:=twist', '-r', 'state:=scan'),
     "scan.topic: 'scan' resolves to /scan, the node's own state topic"),
])
def test_names_that_clash_exit_2_in_one_line_naming_both(ros_domain_id, params, args, line):
    process = spawn(ros_domain_id, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
                    '--params-file', params, *args)
    try:
        code = process.wait(timeout=WAIT_S)
    finally:
        output = stop(process, timeout=10)
    assert code == 2, output[-2000:]
    assert f'safety_filter: invalid parameters: {line}' in output, output[-2000:]
    # the one line of the refusal (the node's log line and the program's say the same)
    assert all(len(said.split(line)) == 2 for said in output.splitlines() if line in said)
    assert 'Traceback' not in output


def test_the_drop_in_launch_with_cmd_in_on_cmd_out_fails(ros_domain_id):
    launch = subprocess.run(
        [sys.executable, '-m', 'rcbf_ros.launch.local', 'safety_filter', 'cmd_in:=/cmd_vel'],
        env=subprocess_env(ros_domain_id), cwd=REPO, capture_output=True, text=True,
        timeout=WAIT_S)
    output = launch.stdout + launch.stderr
    assert launch.returncode == 1, output[-3000:]
    assert 'cmd_proposed and cmd_safe both resolve to /cmd_vel' in output
    assert 'safety_filter failed: exited with 2' in output and 'Traceback' not in output

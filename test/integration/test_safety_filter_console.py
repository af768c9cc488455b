"""The safety_filter node with its console on a full disk: it starts, answers every proposal
(the fail-safe with its ERROR too) and stops with status 0, as a node on rclpy does."""
from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys

from dds_harness import subprocess_env  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import _connect, _exchange, _exchange_with_state, _sections, Probe

REPO = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(not Path('/dev/full').exists(), reason='no /dev/full')]


def test_a_console_on_a_full_disk_costs_the_lines_never_an_answer(ros_domain_id):
    from rcbf_ros.messages.conversions import sections_to_msg
    probe = Probe(ros_domain_id)
    with open('/dev/full', 'w') as full:
        process = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
             '--params-file', str(REPO / 'config' / 'unicycle.yaml'),
             '-p', 'diagnostics.min_period_s:=0.0'],
            env=subprocess_env(ros_domain_id), cwd=REPO, stdout=full, stderr=full)
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        proposal_pub, state_pub = _connect(probe, process, 'std_msgs/msg/Float64MultiArray')
        free, (level, _, _) = _exchange_with_state(
            probe, state_pub, [-2.5, -2.5, 0.0], proposal_pub, sections_to_msg({'u': [0.5, 0.0]}))
        assert level == 0
        np.testing.assert_array_equal(free['u'], [0.5, 0.0])
        for _ in range(3):  # each one an ERROR line the console cannot take
            refused, (level, message, _) = _exchange(
                probe, proposal_pub, sections_to_msg({'u': [float('nan'), 0.0]}))
            assert level == 2 and message.startswith('bad proposal: u: contains NaN')
            np.testing.assert_array_equal(refused['u'], [0.0, 0.0])
        assert process.poll() is None
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        probe.close()

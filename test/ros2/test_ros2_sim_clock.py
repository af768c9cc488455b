"""On real rclpy, a ``/clock`` message of negative seconds does not stop the filter.

rclpy's time source raises on it (``Seconds value must not be negative``) inside the spin, which
ended the node with a traceback; every node started through ``node_main`` now drops it with one
WARN and goes on answering.
"""
from __future__ import annotations

from colcon_overlay import wait_for
from filter_on_jazzy import filter_on_jazzy, WAIT_S
import pytest

pytestmark = pytest.mark.ros2
ARRAY = 'std_msgs/msg/Float64MultiArray'


def test_a_clock_of_negative_seconds_is_dropped_and_the_filter_answers(jazzy, tmp_path,
                                                                      ros_domain_id):
    with filter_on_jazzy(jazzy, tmp_path, ros_domain_id, '-p use_sim_time:=true') as run:
        run.ros2('ros2 topic pub --times 3 -r 10 -w 1 --qos-reliability best_effort /clock '
                 'rosgraph_msgs/msg/Clock "{clock: {sec: -1}}"')
        wait_for(lambda: '' if '/clock: message refused' in run.log.read_text() else None,
                 WAIT_S, 'the /clock message refused')
        published = run.ros2(f'ros2 topic pub --once -w 1 /cmd_proposed {ARRAY} '
                             '"{data: [1.0, 0.0]}"')
        wait_for(lambda: '' if 'fail-safe: no state received yet' in run.log.read_text()
                 else None, WAIT_S, 'the proposal answered')
    assert 'publishing #1' in published, published
    assert 'sec -1 is negative' in run.log.read_text()

"""On real rclpy, a ``/clock`` message of negative seconds does not stop the filter.

rclpy's time source raises on it (``Seconds value must not be negative``) inside the spin, which
ended the node with a traceback; every node started through ``node_main`` now drops it with one
WARN and goes on answering.
"""
from __future__ import annotations

from pathlib import Path
import sys

from colcon_overlay import wait_for
import pytest

pytestmark = pytest.mark.ros2
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))
from conftest import stop_group  # noqa: E402

ARRAY = 'std_msgs/msg/Float64MultiArray'
WAIT_S = 90.0


def test_a_clock_of_negative_seconds_is_dropped_and_the_filter_answers(jazzy, tmp_path,
                                                                      ros_domain_id):
    log = tmp_path / 'safety_filter.log'
    node = jazzy.start(jazzy.python_module(
        'rcbf_ros.ros.safety_filter_node',
        f'--ros-args --params-file {REPO / "config" / "unicycle.yaml"} -p use_sim_time:=true'),
        domain_id=ros_domain_id, log=log)

    def ros2(command: str) -> str:
        return jazzy.run(command, domain_id=ros_domain_id, timeout=60).stdout

    try:
        wait_for(lambda: '' if 'barriers on unicycle' in log.read_text() else None,
                 WAIT_S, 'the safety_filter started')
        ros2('ros2 topic pub --times 3 -r 10 -w 1 --qos-reliability best_effort /clock '
             'rosgraph_msgs/msg/Clock "{clock: {sec: -1}}"')
        wait_for(lambda: '' if '/clock: message refused' in log.read_text() else None,
                 WAIT_S, 'the /clock message refused')
        published = ros2(f'ros2 topic pub --once -w 1 /cmd_proposed {ARRAY} '
                         '"{data: [1.0, 0.0]}"')
        wait_for(lambda: '' if 'fail-safe: no state received yet' in log.read_text() else None,
                 WAIT_S, 'the proposal answered')
        assert node.poll() is None, log.read_text()[-3000:]
    finally:
        code = stop_group(node)
    output = log.read_text()
    assert 'publishing #1' in published, published
    assert 'sec -1 is negative' in output
    assert code == 0 and 'Traceback' not in output, output[-3000:]

"""On real rclpy, ``ros2 param set`` and ``ros2 topic pub`` change a running safety_filter.

The node runs under a real Jazzy's rclpy (``RCBF_ROS_RUNTIME=rclpy``; this checkout and its
virtual environment's packages after Jazzy's on the Python path), and rclpy serves its
parameters: a value the filter's validation refuses prints "Setting parameter failed: <reason
naming the key>", a good one is applied, a read-only one is refused by rclpy; an obstacles set
published by ``ros2 topic pub`` replaces ``obstacles.*``, a malformed one is an ERROR.
"""
from __future__ import annotations

from colcon_overlay import wait_for
from filter_on_jazzy import filter_on_jazzy, WAIT_S
import pytest

pytestmark = pytest.mark.ros2

OBSTACLES = ('ros2 topic pub --once -w 1 --qos-durability transient_local --qos-reliability '
             'reliable /obstacles std_msgs/msg/Float64MultiArray')


def test_ros2_param_set_and_topic_pub_change_the_running_filter(jazzy, tmp_path,
                                                                ros_domain_id):
    with filter_on_jazzy(jazzy, tmp_path, ros_domain_id) as run:
        log, ros2 = run.log, run.ros2

        def param(verb: str, rest: str) -> str:
            return ros2(f'ros2 param {verb} --no-daemon /safety_filter {rest}')

        wait_for(lambda: '' if 'Double value is: 2.0' in param('get', 'k_c') else None,
                 WAIT_S, 'the safety_filter answering ros2 param get')
        refused = param('set', 'k_c -1.0')
        accepted = param('set', 'k_c 0.5')
        got = param('get', 'k_c')
        read_only = param('set', 'system pvtol')
        published = ros2(f'{OBSTACLES} "{{data: [2.85, 0.0, 0.6, 1.5, 1.5, 0.4]}}"')
        moved = wait_for(lambda: (lambda out: out if '2.85' in out else None)(
            param('get', 'obstacles.x')), WAIT_S, 'obstacles.x from the obstacles topic')
        ros2(f'{OBSTACLES} "{{data: [1.0, 2.0]}}"')
        wait_for(lambda: '' if 'obstacles message refused' in log.read_text() else None,
                 WAIT_S, 'the ERROR of a malformed obstacles message')
        kept = param('get', 'obstacles.x')
    output = log.read_text()
    assert refused.strip().endswith(
        'Setting parameter failed: Parameter k_c out of range Min: 0.0, Max: inf, value: -1.0'), \
        refused
    assert 'Set parameter successful' in accepted and 'Double value is: 0.5' in got
    assert 'Setting parameter failed: Trying to set a read-only parameter: system.' in read_only
    assert 'publishing #1' in published, published
    assert 'Double values are: [2.85, 1.5]' in moved, moved
    assert '[2.85, 1.5]' in kept
    assert 'filter updated: k_c: 2.0 -> 0.5' in output
    assert 'parameter change refused: k_c: -1.0 is outside its declared range' in output
    assert 'filter updated from the obstacles topic' in output
    assert 'obstacles message refused, the obstacles are unchanged: obstacles: data' in output

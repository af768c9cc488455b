"""On real rclpy, the hold timer keeps answering under ``use_sim_time`` with no ``/clock``.

rclpy's timers follow the node's clock, which under ``use_sim_time`` stands still until a
``/clock`` message comes; the filter's hold timer is on a steady clock instead. One proposal
(``ros2 topic pub``), then nothing: ``ros2 topic echo`` started after it still sees answers,
the hold timer's (every 3/4 T to T).
"""
from __future__ import annotations

from filter_on_jazzy import filter_on_jazzy
import pytest

pytestmark = pytest.mark.ros2
ARRAY = 'std_msgs/msg/Float64MultiArray'


def test_the_hold_timer_answers_under_use_sim_time_without_a_clock(jazzy, tmp_path,
                                                                   ros_domain_id):
    with filter_on_jazzy(jazzy, tmp_path, ros_domain_id, '-p use_sim_time:=true '
                         '-p control_period_s:=0.05 -p latency_s:=0.15') as run:
        published = run.ros2(f'ros2 topic pub --once -w 1 /cmd_proposed {ARRAY} '
                             '"{data: [1.0, 0.0]}"')
        echoed = run.ros2(f'timeout -s INT 5 ros2 topic echo /filter_info {ARRAY} || true')
    assert 'publishing #1' in published, published
    assert echoed.count('layout:') >= 5, echoed[-2000:]   # the timer's, every 37.5-50 ms
    assert 'fail-safe' in run.log.read_text()

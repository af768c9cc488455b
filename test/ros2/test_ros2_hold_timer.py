"""On real rclpy, the hold timer keeps answering under ``use_sim_time`` with no ``/clock``.

rclpy's timers follow the node's clock, which under ``use_sim_time`` stands still until a
``/clock`` message comes; the filter's hold timer is on a steady clock instead. One proposal
(``ros2 topic pub``), then nothing: ``ros2 topic echo`` started after it still sees answers,
the hold timer's (every 3/4 T to T).
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


def test_the_hold_timer_answers_under_use_sim_time_without_a_clock(jazzy, tmp_path,
                                                                   ros_domain_id):
    log = tmp_path / 'safety_filter.log'
    node = jazzy.start(jazzy.python_module(
        'rcbf_ros.ros.safety_filter_node',
        f'--ros-args --params-file {REPO / "config" / "unicycle.yaml"} -p use_sim_time:=true '
        '-p control_period_s:=0.05 -p latency_s:=0.15'), domain_id=ros_domain_id, log=log)

    def ros2(command: str) -> str:
        return jazzy.run(command, domain_id=ros_domain_id, timeout=60).stdout

    try:
        wait_for(lambda: '' if 'barriers on unicycle' in log.read_text() else None,
                 WAIT_S, 'the safety_filter started')
        published = ros2(f'ros2 topic pub --once -w 1 /cmd_proposed {ARRAY} '
                         '"{data: [1.0, 0.0]}"')
        echoed = ros2(f'timeout -s INT 5 ros2 topic echo /filter_info {ARRAY} || true')
        assert node.poll() is None, log.read_text()[-3000:]
    finally:
        code = stop_group(node)
    output = log.read_text()
    assert 'publishing #1' in published, published
    assert echoed.count('layout:') >= 5, echoed[-2000:]   # the timer's, every 37.5-50 ms
    assert 'fail-safe' in output
    assert code == 0 and 'Traceback' not in output, output[-3000:]

"""A node on real rclpy refuses a bad command line with one line and exit 2, as on ours.

rclpy reads ``--ros-args`` itself (rcl's parser); what it raises for a params file it cannot
read or a malformed ``-p`` is ``RCLError``, which the node prints as one line naming the file or
rule, without a traceback.
"""
from __future__ import annotations

from pathlib import Path
import shlex
import sysconfig

import pytest

pytestmark = pytest.mark.ros2
REPO = Path(__file__).resolve().parents[2]


def _node_on_rclpy(jazzy, ros_args: str, *, domain_id: int):
    """The safety filter's main on Jazzy's rclpy, with this checkout and its environment's
    packages (torch, osqp) after Jazzy's own on the path."""
    site = sysconfig.get_paths()['purelib']
    return jazzy.run(
        'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
        f'PYTHONPATH={shlex.quote(str(REPO))}:$PYTHONPATH:{shlex.quote(site)} '
        'RCBF_ROS_RUNTIME=rclpy "$PY" -m rcbf_ros.ros.node_main '
        f'rcbf_ros.ros.safety_filter_node --ros-args {ros_args}',
        domain_id=domain_id, timeout=120)


@pytest.mark.parametrize('case', ['unparsable params file', 'missing params file',
                                  'malformed -p rule'])
def test_bad_ros_arguments_give_one_line(jazzy, tmp_path, ros_domain_id, case):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('a: [\n')
    ros_args, named = {
        'unparsable params file': (f'--params-file {bad}', str(bad)),
        'missing params file': (f'--params-file {tmp_path / "none.yaml"}', 'none.yaml'),
        'malformed -p rule': ('-p bad', "'-p bad'"),
    }[case]
    done = _node_on_rclpy(jazzy, ros_args, domain_id=ros_domain_id)
    assert done.returncode == 2, done.stdout[-2000:]
    assert 'Traceback' not in done.stdout, done.stdout[-2000:]
    lines = [line for line in done.stdout.splitlines() if line.startswith('safety_filter: ')]
    assert len(lines) == 1 and named in lines[0], done.stdout[-2000:]
    assert ', at /' not in lines[0]

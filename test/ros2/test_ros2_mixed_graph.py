"""Stock ROS 2 tools and rclpy talk to our runtime's safety filter, both ways, values checked.

- ``ros2 topic pub`` sends Odometry states and Twist proposals to the filter on our runtime;
  ``ros2 topic echo --once`` reads its Twist on /cmd_safe: passed through exactly where free,
  slowed down in front of an obstacle.
- An rclpy publisher sends Float64MultiArray proposals (with their states) to the filter on our
  runtime; our runtime's recorder takes both sides: every proposal as sent, every answer's
  ``u_rl`` equal to its proposal, ``u`` equal to it where free and slowed where not.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(REPO / 'test'))
sys.path.insert(0, str(HERE))
from conftest import stop_group  # noqa: E402
from test_ros2_record_replay import bag_messages, sections, wait_for_text  # noqa: E402

UNICYCLE = REPO / 'config' / 'unicycle.yaml'
FREE_STATE = [2.0, 0.0, 0.0]       # far from every obstacle
BLOCKED_STATE = [-0.85, 0.0, 0.0]  # facing the centre obstacle
RCLPY_PYTHON = '"$(head -1 "$(command -v ros2)" | cut -c3-)"'
"""The interpreter of the ros2 command: the Jazzy Python, rclpy and nothing of ours."""


def start_ours(module: str, args: list[str], domain_id: int, log: Path) -> subprocess.Popen:
    """A node of ours on our runtime, in its own process group."""
    env = dict(os.environ, RCBF_ROS_RUNTIME='cyclone', ROS_DOMAIN_ID=str(domain_id),
               PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    ensure_loopback(env, force=True)
    return subprocess.Popen([sys.executable, '-m', module, '--ros-args', *args], env=env,
                            cwd=REPO, start_new_session=True, stdout=log.open('w'),
                            stderr=subprocess.STDOUT)


def echo_twist(jazzy, state: list[float], u: list[float], domain_id: int,
               tmp_path: Path) -> dict:
    """``ros2 topic pub`` of the state (Odometry) and then of the proposal (Twist); the Twist
    ``ros2 topic echo --once`` reads on /cmd_safe."""
    x, y, theta = state
    odometry = yaml.safe_dump({'pose': {'pose': {
        'position': {'x': x, 'y': y, 'z': 0.0},
        'orientation': {'x': 0.0, 'y': 0.0, 'z': float(np.sin(theta / 2)),
                        'w': float(np.cos(theta / 2))}}}}, default_flow_style=True).strip()
    twist = yaml.safe_dump({'linear': {'x': u[0]}, 'angular': {'z': u[1]}},
                           default_flow_style=True).strip()
    states = jazzy.start(f"ros2 topic pub --rate 20 /state nav_msgs/msg/Odometry '{odometry}'",
                         domain_id=domain_id, log=tmp_path / 'pub_state.log')
    proposals = None
    try:
        time.sleep(2.0)  # the filter holds this state before the first proposal
        proposals = jazzy.start(
            f"ros2 topic pub --rate 10 /cmd_proposed geometry_msgs/msg/Twist '{twist}'",
            domain_id=domain_id, log=tmp_path / 'pub_twist.log')
        echo = jazzy.run('ros2 topic echo --once /cmd_safe geometry_msgs/msg/Twist',
                         domain_id=domain_id, timeout=90)
    finally:
        for process in (proposals, states):
            if process is not None:
                stop_group(process)
    assert echo.returncode == 0, echo.stdout
    return yaml.safe_load(echo.stdout.split('---')[0])


def test_ros2_topic_pub_and_echo_through_our_filter(jazzy, tmp_path, ros_domain_id):
    log = tmp_path / 'filter.log'
    node = start_ours('rcbf_ros.ros.safety_filter_node', [
        '--params-file', str(UNICYCLE), '-p', 'safety_filter:state_type:=odometry',
        '-p', 'safety_filter:command_type:=twist'], ros_domain_id, log)
    try:
        wait_for_text(log, 'barriers on unicycle', 60)
        free = echo_twist(jazzy, FREE_STATE, [0.4, 0.1], ros_domain_id, tmp_path)
        slowed = echo_twist(jazzy, BLOCKED_STATE, [2.5, 0.0], ros_domain_id, tmp_path)
    finally:
        code = stop_group(node)
    assert code == 0, log.read_text()[-3000:]
    assert free == {'linear': {'x': 0.4, 'y': 0.0, 'z': 0.0},
                    'angular': {'x': 0.0, 'y': 0.0, 'z': 0.1}}, free
    assert 0.0 < slowed['linear']['x'] < 2.5, slowed
    assert slowed['linear']['y'] == slowed['linear']['z'] == 0.0, slowed


def test_rclpy_publisher_to_our_filter_and_our_subscriber(jazzy, tmp_path, ros_domain_id):
    proposals = ([{'u': [0.1 * i, 0.05 * (i % 3)], 'state': FREE_STATE} for i in range(12)]
                 + [{'u': [2.5, 0.0], 'state': BLOCKED_STATE}] * 3)
    spec = tmp_path / 'proposals.json'
    spec.write_text(json.dumps(proposals))
    bag = tmp_path / 'bag'
    filter_log, recorder_log = tmp_path / 'filter.log', tmp_path / 'recorder.log'
    node = start_ours('rcbf_ros.ros.safety_filter_node', ['--params-file', str(UNICYCLE)],
                      ros_domain_id, filter_log)
    recorder = start_ours('rcbf_ros.ros.recorder_node', [
        '-p', f'output:={bag}', '-p', "topics:=['/cmd_proposed', '/filter_info']",
        '-p', 'discovery_period_s:=0.2'], ros_domain_id, recorder_log)
    try:
        wait_for_text(recorder_log, 'recording /filter_info', 60)
        published = jazzy.run(f'{RCLPY_PYTHON} {HERE / "rclpy_proposer.py"} {spec} 2',
                              domain_id=ros_domain_id, timeout=120)
        assert published.returncode == 0, published.stdout
        time.sleep(1.0)  # the last answers reach the recorder
    finally:
        codes = [stop_group(node), stop_group(recorder)]
    assert codes == [0, 0], filter_log.read_text()[-2000:] + recorder_log.read_text()[-2000:]
    recorded = bag_messages(bag)
    sent = [sections(m) for m in recorded['/cmd_proposed']]
    assert [s['u'].tolist() for s in sent] == [p['u'] for p in proposals]
    assert [s['state'].tolist() for s in sent] == [p['state'] for p in proposals]
    answers = [sections(m) for m in recorded['/filter_info']]
    assert len(answers) == len(proposals)
    for proposal, answer in zip(proposals, answers):
        assert answer['u_rl'].tolist() == proposal['u']
        assert answer['state'].tolist() == proposal['state']
        if proposal['state'] == FREE_STATE:
            assert answer['u'].tolist() == proposal['u']  # passed through, bit for bit
        else:
            assert 0.0 < answer['u'][0] < 2.5, answer

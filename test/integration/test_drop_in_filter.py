"""The drop-in safety filter as a user starts it: ``rcbf_ros launch safety_filter`` and the demo.

- ``rcbf_ros launch safety_filter`` with the robot's own topic names (not the defaults): the
  test is the robot and its controller (nav_msgs/Odometry and geometry_msgs/Twist in), and a
  Twist comes out on the robot's velocity input only: unchanged far from the obstacles, slowed
  down heading into one;
- ``rcbf_ros launch unicycle_robot``: the simulated robot moves, the filter corrects the
  go-to-goal controller at least once, and no recorded Odometry lies inside an obstacle of the
  config.
"""
from __future__ import annotations

from pathlib import Path
import subprocess
import time
from typing import Any

from dds_harness import spawn, stop  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import Probe, WAIT_S

from rcbf_ros.bag import read_bag_messages
from rcbf_ros.parameters.rules import find_config, load_params

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
FIELDS = ['linear.x', 'angular.z']
TOPICS = {'cmd_in': '/robot/nav_cmd', 'cmd_out': '/robot/base_cmd', 'odom': '/robot/odometry'}
"""The robot's names, none of them a default of the launch."""


def _odometry(state: list[float]) -> Any:
    from rcbf_ros.messages.conversions import state_to_odometry
    return state_to_odometry(state, system='unicycle', stamp_ns=0, frame_id='map',
                             child_frame_id='base_link')


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def _answer(probe: Probe, odom_pub: Any, twist_pub: Any, state: list[float],
            proposal: list[float]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Publish the state, then the proposal, until the filter answers it having that state;
    the command on cmd_out and the filter_info that goes with it.

    The first samples of a new writer can be lost until the filter's reader has matched it, and
    the filter answers a proposal without a state with the fail-safe; an answer that filtered
    (fail_safe 0) for this proposal at this state proves both arrived. The launch re-filters
    the proposal in force at each Odometry (refilter_on_state): the answers since the state
    was published are searched for that one.
    """
    from rcbf_ros.messages.conversions import array_to_twist
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        before = probe.count(TOPICS['cmd_out'])
        odom_pub.publish(_odometry(state))
        time.sleep(0.05)
        twist_pub.publish(array_to_twist(proposal, FIELDS))
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            infos = probe.wait_for('/filter_info', 0)[before:]
            commands = probe.wait_for(TOPICS['cmd_out'], 0)[before:]
            for command, info in zip(commands, infos):
                if (info['fail_safe'][0] == 0 and np.array_equal(info['u_rl'], proposal)
                        and np.allclose(info['state'], state, atol=1e-9)):
                    return command, info
            time.sleep(0.02)
        time.sleep(0.3)   # let answers still in flight arrive before counting again
    raise AssertionError(f'no filtered answer on {TOPICS["cmd_out"]} within {WAIT_S} s')


def test_the_filter_launch_sits_between_a_robots_own_topics(ros_domain_id, probe):
    from rcbf_ros.messages.conversions import msg_to_sections, twist_to_array
    launch = spawn(ros_domain_id, '-m', 'rcbf_ros.launch.local', 'safety_filter',
                   '--domain-id', str(ros_domain_id),
                   *(f'{name}:={topic}' for name, topic in TOPICS.items()))
    try:
        for topic in (TOPICS['cmd_out'], '/cmd_vel', '/cmd_safe'):
            probe.subscribe('geometry_msgs/msg/Twist', topic, lambda m: twist_to_array(m, FIELDS))
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info',
                        lambda m: {k: v.copy() for k, v in msg_to_sections(m).items()})
        odom_pub = probe.publisher('nav_msgs/msg/Odometry', TOPICS['odom'])
        twist_pub = probe.publisher('geometry_msgs/msg/Twist', TOPICS['cmd_in'])
        probe.start()
        deadline = time.monotonic() + WAIT_S
        while twist_pub.get_subscription_count() == 0 or odom_pub.get_subscription_count() == 0:
            assert launch.poll() is None, stop(launch, timeout=10)
            assert time.monotonic() < deadline, 'the filter never subscribed to the robot'
            time.sleep(0.05)
        # Far from every obstacle, heading away from them: passed through exactly.
        free, _ = _answer(probe, odom_pub, twist_pub, [-2.5, -2.5, -0.75 * np.pi], [1.0, 0.3])
        # 0.25 m from the centre obstacle's edge, full speed at it: slowed down.
        slowed, info = _answer(probe, odom_pub, twist_pub, [-0.85, 0.0, 0.0], [2.5, 0.0])
    finally:
        output = stop(launch, timeout=20)
    np.testing.assert_array_equal(free, [1.0, 0.3])
    assert 0.0 < slowed[0] < 2.5, slowed
    np.testing.assert_array_equal(info['u'], slowed)
    assert probe.count('/cmd_vel') == probe.count('/cmd_safe') == 0   # the robot's names only
    assert launch.returncode == 0 and 'Traceback' not in output, output[-4000:]


def test_the_demo_robot_moves_and_the_filter_keeps_it_out_of_the_obstacles(ros_domain_id,
                                                                          tmp_path):
    steps = 150
    bag = tmp_path / 'bag'
    launch = spawn(ros_domain_id, '-m', 'rcbf_ros.launch.local', 'unicycle_robot',
                   '--domain-id', str(ros_domain_id), 'odom:=/robot/odometry',
                   '-p', 'simulator:max_episodes:=1', '-p', f'simulator:max_steps:={steps}',
                   '-p', f'recorder:output:={bag}')
    try:
        output = ''.join(launch.communicate(timeout=180))
    except subprocess.TimeoutExpired:
        output = stop(launch)   # SIGINT: the launcher stops its nodes, none is left behind
    assert launch.returncode == 0 and 'Traceback' not in output, output[-4000:]

    poses = np.array([[m.pose.pose.position.x, m.pose.pose.position.y]
                      for _, m in read_bag_messages(bag, topics=['/robot/odometry'])])
    infos = [np.asarray(m.data) for _, m in read_bag_messages(bag, topics=['/filter_info'])]
    assert len(infos) >= steps // 2, len(infos)
    # The first episode waited for the recorder: every state the filter answered is in the bag.
    assert len(poses) >= len(infos), (len(poses), len(infos))
    assert np.linalg.norm(poses[-1] - poses[0]) > 1.0, (poses[0], poses[-1])   # it moved
    # filter_info begins with u, u_rl, u_s (n_u = 2 each): the filter corrected some command.
    assert max(float(np.abs(info[4:6]).max()) for info in infos) > 1e-3
    # Every recorded position outside every obstacle of the config (true radius, no margin).
    params = load_params(find_config('unicycle'), 'safety_filter')
    centres = np.stack([params['obstacles.x'], params['obstacles.y']], axis=1)
    distances = np.linalg.norm(poses[:, None, :] - centres[None, :, :], axis=2)
    clearance = distances - np.asarray(params['obstacles.radius'])[None, :]
    assert clearance.min() >= 0.0, clearance.min()

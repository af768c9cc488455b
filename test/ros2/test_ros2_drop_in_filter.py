"""The drop-in safety filter as a ROS 2 user starts it: ``ros2 launch`` from the colcon overlay.

``ros2 launch rcbf_ros safety_filter.launch.py cmd_in:=... cmd_out:=... odom:=...`` on real
launch_ros and rclpy; an rclpy script of the Jazzy install is the robot and its controller
(nav_msgs/Odometry and geometry_msgs/Twist in, the Twist on the robot's velocity input read
back). ``unicycle_robot.launch.py`` runs its episode to the end on real launch_ros (its list
parameter of launch arguments, ``wait_for_publishers``, evaluated as launch_ros does). Both
launchers show the same arguments and refuse the same bad value.
"""
from __future__ import annotations

import json
from pathlib import Path
import re
import textwrap

from colcon_overlay import overlay_fixture, stop_group
import pytest
import yaml

pytestmark = pytest.mark.ros2
overlay = overlay_fixture()

TOPICS = {'cmd_in': '/robot/nav_cmd', 'cmd_out': '/robot/base_cmd', 'odom': '/robot/odometry'}

# The robot and its controller: publishes a state, then a proposal, until the filter answers
# that proposal having that state (filter_info: u, u_rl, u_s, fail_safe, ...); prints the
# commands that arrived on cmd_out as JSON.
_ROBOT = textwrap.dedent("""
    import json, math, sys, time
    import rclpy
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Float64MultiArray
    odom_topic, cmd_in, cmd_out = sys.argv[1:4]
    rclpy.init()
    node = rclpy.create_node('robot')
    odom_pub = node.create_publisher(Odometry, odom_topic, 10)
    twist_pub = node.create_publisher(Twist, cmd_in, 10)
    received = {'cmd': [], 'info': []}
    node.create_subscription(Twist, cmd_out, lambda m: received['cmd'].append(
        [m.linear.x, m.angular.z]), 100)
    node.create_subscription(Float64MultiArray, '/filter_info', lambda m: received['info'].append(
        list(m.data)), 100)

    def answer(state, proposal):
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            odom = Odometry()
            odom.header.frame_id = 'map'
            odom.pose.pose.position.x, odom.pose.pose.position.y = state[0], state[1]
            odom.pose.pose.orientation.z = math.sin(state[2] / 2)
            odom.pose.pose.orientation.w = math.cos(state[2] / 2)
            odom_pub.publish(odom)
            end = time.monotonic() + 0.05
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.01)
            before = len(received['info'])
            twist = Twist()
            twist.linear.x, twist.angular.z = proposal
            twist_pub.publish(twist)
            end = time.monotonic() + 1.0
            while len(received['info']) == before and time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.05)
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.05)
            for info, command in zip(received['info'][before:], received['cmd'][before:]):
                if info[6] == 0.0 and info[2:4] == list(proposal):
                    return command
        sys.exit('no filtered answer on ' + cmd_out)

    free = answer([-2.5, -2.5, -0.75 * math.pi], [1.0, 0.3])
    slowed = answer([-0.85, 0.0, 0.0], [2.5, 0.0])
    print(json.dumps({'free': free, 'slowed': slowed}))
""")


def test_ros2_launch_puts_the_filter_between_a_robots_own_topics(overlay, tmp_path,
                                                                 ros_domain_id):
    arguments = ' '.join(f'{name}:={topic}' for name, topic in TOPICS.items())
    launch = overlay.jazzy.start(overlay.script(
        f'ros2 launch rcbf_ros safety_filter.launch.py {arguments}'),
        domain_id=ros_domain_id, log=tmp_path / 'launch.log')
    robot = tmp_path / 'robot.py'
    robot.write_text(_ROBOT)
    try:
        done = overlay.jazzy.run(overlay.python(robot, TOPICS['odom'], TOPICS['cmd_in'],
                                                TOPICS['cmd_out']),
                                 domain_id=ros_domain_id, timeout=240)
    finally:
        code = stop_group(launch)
    log = (tmp_path / 'launch.log').read_text()
    assert done.returncode == 0, done.stdout[-4000:] + log[-4000:]
    commands = json.loads(done.stdout.strip().splitlines()[-1])
    assert commands['free'] == [1.0, 0.3], commands           # far away: unchanged
    assert 0.0 < commands['slowed'][0] < 2.5, commands         # into the obstacle: slowed
    assert code == 0 and 'Traceback' not in log, log[-4000:]


def test_the_demo_launch_runs_its_episode_on_launch_ros(overlay, tmp_path,
                                                        ros_domain_id):
    params = yaml.safe_load((overlay.share() / 'config' / 'unicycle.yaml').read_text())
    params['/simulator']['ros__parameters'].update(max_steps=60, max_episodes=1)
    params['/recorder'] = {'ros__parameters': {'output': str(tmp_path / 'bag')}}
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump(params))
    launch = overlay.jazzy.start(overlay.script(
        f'ros2 launch rcbf_ros unicycle_robot.launch.py params_file:={params_file} '
        f'cmd_in:=/ctl/cmd_vel'), domain_id=ros_domain_id, log=tmp_path / 'launch.log')
    try:
        launch.wait(timeout=240)
    finally:
        code = stop_group(launch)
    log = (tmp_path / 'launch.log').read_text()
    assert code == 0 and 'Traceback' not in log, log[-4000:]
    info = overlay.jazzy.run(f'ros2 bag info {tmp_path / "bag"}', domain_id=ros_domain_id)
    assert info.returncode == 0, info.stdout
    counts = {topic: int(count) for topic, count in
              re.findall(r'Topic: (\S+) \| Type: \S+ \| Count: (\d+)', info.stdout)}
    # The recorder subscribes to a topic once discovery shows it, which under launch_ros can be
    # tens of steps into the run: streaming topics need only be in the bag. The proof that the
    # episode ran is the simulator's end event on the transient-local `episode` topic, which a
    # late subscriber still receives; it is read with Foxglove's reader, not ours.
    for topic in ('/odom', '/cmd_vel', '/ctl/cmd_vel', '/filter_info', '/episode'):
        assert counts.get(topic, 0) >= 1, info.stdout
    events = _episode_events(tmp_path / 'bag')
    ends = [e for e in events if e['event'] == 'end']
    assert len(ends) == 1, events
    assert ends[0]['steps'] == 60 or ends[0]['goal_reached'], ends
    assert ends[0]['violations'] == 0, ends


def _episode_events(bag: Path) -> list[dict]:
    """The JSON events on ``/episode`` in every MCAP file of ``bag``, decoded by mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    events = []
    for path in sorted(bag.glob('*.mcap')):
        with path.open('rb') as stream:
            for _, _, _, msg in make_reader(
                    stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                        topics=['/episode']):
                events.append(json.loads(msg.data))
    return events


@pytest.mark.parametrize('name', ['safety_filter', 'unicycle_robot'])
def test_both_launchers_show_the_same_arguments(overlay, name, capsys):
    """``ros2 launch ... --show-args`` and ``rcbf_ros launch ... --show-args``: the same names,
    defaults (params_file aside: a path on one, the packaged file named on the other) and
    choices; a value outside the choices refused by both."""
    from rcbf_ros.launch import local as launch_local
    shown = overlay.jazzy.run(overlay.script(f'ros2 launch rcbf_ros {name}.launch.py --show-args'),
                              domain_id=0)
    assert shown.returncode == 0, shown.stdout

    def arguments(text: str) -> dict[str, str]:
        return dict(re.findall(r"'(\w+)':\n(?:.*\n)*?\s+\(default: '([^']*)'\)", text))

    assert launch_local.main([name, '--show-args']) == 0
    ours = arguments(capsys.readouterr().out)
    theirs = arguments(shown.stdout)
    assert theirs.pop('params_file').endswith('/share/rcbf_ros/config/unicycle.yaml')
    assert ours.pop('params_file') == 'config/unicycle.yaml of the package'
    assert ours == theirs and set(ours) == {'cmd_in', 'cmd_out', 'odom', 'command_type',
                                            'respawn', 'respawn_delay'}
    assert "Valid choices are: ['twist', 'twist_stamped', 'array']" in shown.stdout
    refused = overlay.jazzy.run(overlay.script(
        f'ros2 launch rcbf_ros {name}.launch.py command_type:=Twist'), domain_id=0)
    assert 'provided value "Twist" is not valid' in refused.stdout, refused.stdout
    assert launch_local.main([name, 'command_type:=Twist']) == 2

"""``rcbf_ros launch unicycle_lidar`` over real Cyclone DDS (loopback): the drop-in filter on a
laser scan, placed through tf, keeps a blind go-to-goal controller's robot off the posts.

The controller drives from the arena's left straight at a goal whose line passes through the
post at (1.5, -1.5); the test watches the robot pass that post on the filter's commands, stops
the launch, and checks every recorded Odometry against the world's true geometry (the packaged
params file's posts and walls), the robot node's own contact check (a warning on the true
pose) and the bag with ``rcbf_ros bag check``. The bag also holds what a viewer shows: the
scene markers in odom with the scan points that bound the command near the post and the
active rows, and the world's true geometry, once.
"""
from __future__ import annotations

import subprocess
import sys
import time

from dds_harness import REPO, spawn, stop, subprocess_env  # this directory: on sys.path
import numpy as np
import pytest
from test_safety_filter_node import Probe, WAIT_S

from rcbf_ros.bag import read_bag_messages
from rcbf_ros.parameters.rules import load_params
from sim_nodes import lidar_world as lw

pytestmark = pytest.mark.integration

CONFIG = REPO / 'config' / 'unicycle_lidar.yaml'
PAST_THE_POST = 2.1
"""The robot has passed the post at (1.5, -1.5), of radius 0.6 m, once odometry's x is beyond
this (m)."""
DRIFT = 0.05
"""How far (m) odometry may have drifted from the true pose in this short run (slip of a few
per cent over ~4 m)."""


def _world_clearance(positions: np.ndarray) -> np.ndarray:
    """The body's clearance (m) at each position: the distance to the nearest post or wall of
    the packaged world less the robot's radius."""
    params = load_params(CONFIG, 'unicycle_lidar')
    circles = np.stack([params['obstacles.x'], params['obstacles.y'],
                        params['obstacles.radius']], axis=1)
    half = float(params['arena_half_size'])
    world = lw.World(half_size=half, circles=circles,
                     segments=np.array(lw._arena(half), dtype=np.float64),
                     start=np.asarray(params['start'], dtype=np.float64), goal=np.zeros(2),
                     kind='posts', seed=-1)
    return lw.clearance(world, positions) - lw.BaseModel().radius


def test_the_filter_on_the_scan_steers_the_lidar_robot_round_the_post(ros_domain_id, tmp_path):
    from rcbf_ros.messages.conversions import msg_to_sections
    bag = tmp_path / 'bag'
    probe = Probe(ros_domain_id)
    probe.subscribe('nav_msgs/msg/Odometry', '/odom',
                    lambda m: (m.pose.pose.position.x, m.pose.pose.position.y))
    probe.subscribe('geometry_msgs/msg/Twist', '/cmd_vel', lambda m: m.linear.x)
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info',
                    lambda m: float(msg_to_sections(m)['fail_safe'][0]))
    probe.start()
    launch = spawn(ros_domain_id, '-m', 'rcbf_ros.launch.local', 'unicycle_lidar',
                   '--domain-id', str(ros_domain_id), '-p', f'recorder:output:={bag}')
    try:
        deadline = time.monotonic() + 3 * WAIT_S
        while True:
            assert launch.poll() is None, stop(launch, timeout=10)[-4000:]
            with probe.lock:
                odom = [item for _, item in probe.received['/odom']]
            if odom and odom[-1][0] > PAST_THE_POST:
                break
            assert time.monotonic() < deadline, (
                f'the robot did not pass the post: odometry at {odom[-1:]}, '
                f'{probe.count("/cmd_vel")} commands')
            time.sleep(0.1)
    finally:
        probe.close()
        output = stop(launch, timeout=60)
    assert launch.returncode == 0 and 'Traceback' not in output, output[-4000:]
    assert 'the robot touches an obstacle' not in output, output[-4000:]
    # the robot held its start until the recorder listened: the bag holds the first steps
    assert 'the robot starts: every wait_for_subscribers node listens' in output, output[-4000:]
    with probe.lock:
        commands = [item for _, item in probe.received['/cmd_vel']]
        fail_safe = [item for _, item in probe.received['/filter_info']]
    # cmd_safe flowed to the base, the filter answered on the scan (not only its fail-safe)
    assert len(commands) > 50 and max(commands) > 0.1, commands[-10:]
    assert fail_safe.count(0.0) > 50, (len(fail_safe), fail_safe.count(0.0))

    check = subprocess.run([sys.executable, '-m', 'rcbf_ros', 'bag', 'check', str(bag)],
                           env=subprocess_env(ros_domain_id), cwd=REPO, capture_output=True,
                           text=True, timeout=120)
    assert check.returncode == 0 and 'intact' in check.stdout, check.stdout + check.stderr
    poses = np.array([[m.pose.pose.position.x, m.pose.pose.position.y]
                      for _, m in read_bag_messages(bag, topics=['/odom'])])
    assert poses[:, 0].max() > PAST_THE_POST, poses[-1]
    scans = list(read_bag_messages(bag, topics=['/scan']))
    assert scans and scans[-1][1].header.frame_id == 'laser'
    # round the post, not through it: off the straight line from the start to the goal (which
    # passes 0.45 m from the post's centre, inside the body's 0.8 m), clear of every surface
    params = load_params(CONFIG, 'nominal_controller')
    start = np.asarray(load_params(CONFIG, 'unicycle_lidar')['start'][:2])
    along = np.asarray(params['goal']) - start
    along /= np.linalg.norm(along)
    off_line = np.abs((poses - start) @ np.array([-along[1], along[0]]))
    assert off_line.max() > 0.3, off_line.max()
    assert _world_clearance(poses).min() > -DRIFT, _world_clearance(poses).min()

    # what Foxglove shows: the scene in odom, scan points binding by the post, ground truth
    arrays = [m.markers for _, m in read_bag_messages(bag, topics=['/scene_markers'])]
    assert arrays and {k.header.frame_id for a in arrays for k in a} == {'odom'}
    binding = [[(p.x, p.y) for k in a if k.ns == 'binding_points' for p in k.points]
               for a in arrays if any(k.ns == 'active_rows' and k.points for k in a)]
    assert binding, f'no active row drawn in {len(arrays)} scene arrays'
    near = np.array([point for points in binding for point in points])
    assert np.hypot(near[:, 0] - 1.5, near[:, 1] + 1.5).min() < 0.6 + DRIFT + 0.05
    (truth,) = [m.markers for _, m in read_bag_messages(bag, topics=['/world_markers'])]
    assert {(k.header.frame_id, k.ns) for k in truth} == {('odom', 'ground_truth')}

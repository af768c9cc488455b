"""sim_nodes/unicycle_lidar_node.py without middleware: its settings, its world, the command it
holds and drops, its scan cadence, and its --help."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rcbf_ros.parameters.rules import find_config, load_params
from sim_nodes import lidar_world as lw
from sim_nodes import unicycle_lidar_node as node

PACKAGED = load_params(find_config('unicycle'), 'unicycle_lidar')


def robot(**overrides) -> node.LidarRobot:
    settings = node.settings_from_params(overrides)
    return node.LidarRobot(node.build_world(settings, PACKAGED), settings)


def test_the_packaged_world_is_the_filter_s_posts_in_a_walled_arena():
    world = node.build_world(node.settings_from_params({}), PACKAGED)
    np.testing.assert_allclose(world.circles[:, 0], PACKAGED['obstacles.x'])
    np.testing.assert_allclose(world.circles[:, 2], PACKAGED['obstacles.radius'])
    assert len(world.segments) == 4 and world.half_size == 3.5
    np.testing.assert_allclose(world.start, [-2.5, -2.5, 0.0])
    seeded = node.build_world(node.settings_from_params({'world_seed': 4}), PACKAGED)
    np.testing.assert_array_equal(seeded.circles, lw.random_world(4).circles)


@pytest.mark.parametrize('params, key', [
    ({'start': [0.0, 0.0, 0.0]}, 'start'),          # inside the middle post
    ({'start': [3.4, 0.0, 0.0]}, 'start'),          # within the body's radius of the wall
    ({'start': [9.0, 0.0, 0.0]}, 'start'),          # outside the arena
    ({'rate_hz': math.inf}, 'rate_hz'),
    ({'scan_rate_hz': 60.0}, 'scan_rate_hz'),       # faster than the base's 50 Hz
    ({'beams': 10 ** 9}, 'beams'),
    ({'laser_mount': [0.1, 0.0]}, 'laser_mount'),
    ({'range_max': 0.05}, 'range_max'),             # below the lidar's range_min
    ({'range_max': lw.Lidar.range_min}, 'range_max'),
    ({'odom_frame_id': 'base_link'}, 'base_frame_id'),  # a self-parent odom -> base_link
    ({'laser_frame_id': 'base_link'}, 'laser_frame_id'),
    ({'laser_frame_id': 'odom'}, 'laser_frame_id'),
    ({'laser_frame_id': ' '}, 'laser_frame_id'),
    ({'base_frame_id': 'base link'}, 'base_frame_id'),
    ({'odom_frame_id': '/odom'}, 'odom_frame_id'),
    ({'laser_frame_id': 'laser\x07'}, 'laser_frame_id'),
    ({'odom_frame_id': 'o' * 1025}, 'odom_frame_id'),
])
def test_bad_settings_are_refused_naming_the_key(params, key):
    with pytest.raises(ValueError, match=f'^{key}:'):
        node.build_world(node.settings_from_params(params), PACKAGED)


def test_frame_ids_up_to_the_readers_bound_are_taken():
    settings = node.settings_from_params({'odom_frame_id': 'o' * 1024, 'laser_frame_id': 'l/2'})
    assert len(settings.odom_frame_id) == 1024 and settings.laser_frame_id == 'l/2'


@pytest.mark.parametrize('key', ['obstacles.x', 'obstacles.y', 'obstacles.radius'])
@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_a_post_that_is_not_finite_is_refused_naming_its_own_key(key, bad):
    params = {**PACKAGED, key: [*PACKAGED[key][:2], bad, *PACKAGED[key][3:]]}
    with pytest.raises(ValueError, match=f'^{key}: value 2 is '):
        node.build_world(node.settings_from_params({}), params)


def test_posts_that_do_not_line_up_are_refused():
    params = {**PACKAGED, 'obstacles.y': [0.0]}
    with pytest.raises(ValueError, match='^obstacles.x: 5 values, obstacles.y 1'):
        node.build_world(node.settings_from_params({}), params)


def test_a_command_holds_for_its_timeout_then_the_base_stops():
    r = robot(cmd_timeout_s=0.2, rate_hz=50.0)
    assert r.take_command(0.4, 0.0) == ''
    for _ in range(10):  # 0.2 s
        r.step()
    moving = r.state.wheels[0]
    assert moving > 0.25  # 0.4 (1 - exp(-0.2 / 0.15))
    for _ in range(25):  # 0.5 s more: the command is stale, the wheels run down
        r.step()
    assert r.state.wheels[0] < 0.1 * moving


def test_a_command_that_is_not_finite_stops_the_base_and_says_so():
    r = robot()
    r.take_command(0.4, 0.0)
    for _ in range(10):
        r.step()
    reason = r.take_command(math.nan, 0.0)
    assert reason.startswith('cmd_vel: not finite')
    np.testing.assert_array_equal(r.command, [0.0, 0.0])


def test_scans_come_at_their_rate_and_odometry_starts_at_the_start():
    r = robot(rate_hz=50.0, scan_rate_hz=10.0)
    due = []
    for _ in range(50):
        due.append(r.scan_due())
        r.step()
    assert sum(due) == 10 and due[0] and due[5] and not any(due[1:5])
    pose, twist = r.odometry()
    assert pose[0] == pytest.approx(-2.5, abs=1e-9) and twist[0] == 0.0
    ranges = r.scan()
    assert ranges.shape == (360,) and np.isfinite(ranges).sum() > 300


def test_a_rotation_about_z_as_a_quaternion():
    np.testing.assert_allclose(node.yaw_quaternion(math.pi / 2),
                               [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)])


def test_help_needs_no_middleware(capsys):
    assert node.main(['unicycle_lidar', '--help']) == 0
    out = capsys.readouterr().out
    assert 'pub /tf_static' in out and 'sub cmd_vel' in out and 'laser_mount' in out


def test_the_world_markers_are_the_true_posts_and_walls_labelled_ground_truth():
    world = lw.random_world(7, kind='rooms')   # inner walls besides the arena's
    markers = node.world_markers(world, frame_id='odom')
    assert {m['frame_id'] for m in markers} == {'odom'}
    assert {m['ns'] for m in markers} == {'ground_truth'}
    assert len({m['id'] for m in markers}) == len(markers)
    posts = [m for m in markers if m['type'] == node.CYLINDER]
    assert [(m['position'][:2], m['scale'][0] / 2) for m in posts] == [
        ((x, y), r) for x, y, r in world.circles.tolist()]
    walls = [m for m in markers if m['type'] == node.CUBE]
    assert len(walls) == len(world.segments)
    for wall, (x0, y0, x1, y1) in zip(walls, world.segments.tolist()):
        qz, qw = wall['orientation'][2:]
        yaw = 2.0 * math.atan2(qz, qw)
        cx, cy = wall['position'][:2]
        for px, py in ((x0, y0), (x1, y1)):   # both ends of the centre line inside the box
            along = (px - cx) * math.cos(yaw) + (py - cy) * math.sin(yaw)
            across = -(px - cx) * math.sin(yaw) + (py - cy) * math.cos(yaw)
            assert abs(along) <= wall['scale'][0] / 2 and abs(across) < 1e-9
        assert wall['scale'][1] == world.wall_thickness
    (label,) = [m for m in markers if m['type'] == node.TEXT_VIEW_FACING]
    assert 'ground truth' in label['text']


def test_the_world_markers_make_a_marker_array():
    from rcbf_ros.ros.runtime import deserialize_message, get_message, serialize_message
    from rcbf_ros.ros.scene_node import marker_array
    world = node.build_world(node.settings_from_params({}), PACKAGED)
    markers = node.world_markers(world, frame_id='odom')
    back = deserialize_message(serialize_message(marker_array(markers)),
                               get_message('visualization_msgs/msg/MarkerArray')).markers
    assert [(m.header.frame_id, m.ns, m.id, m.type) for m in back] == [
        ('odom', 'ground_truth', m['id'], m['type']) for m in markers]
    assert len(back) == 5 + 4 + 1

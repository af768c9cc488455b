"""Re-filtering a robot's bag: the drop-in launch's topic names, remaps, and scan sources.

A bag as ``ros2 bag record`` writes it around the drop-in launch holds the controller's Twist on
its ``cmd_in`` (``/cmd_vel_nav`` by default), nav_msgs/Odometry on ``odom``, the safe command
on ``cmd_out`` and a LaserScan. The oracle for every re-filtered command is the core filter
given the scan's points as this test places them in the world (ranges cast here against one
post, in closed form), not the sources' own reading.
"""
from __future__ import annotations

from pathlib import Path
import re

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
import yaml

from rcbf_ros.bag import BagWriter
from rcbf_ros.bag.refilter import (
    build_filter,
    DROP_IN_TOPICS,
    LAUNCH_ARGUMENTS,
    main,
    refilter_bag,
    RefilterError,
    resolve_params,
)
from rcbf_ros.launch.table import launch_setup, ROBOT_ARGUMENTS

T0 = 1_700_000_000_000_000_000
STEP_NS = 50_000_000
N_STEPS = 30
POST, POST_RADIUS = np.array([0.0, 0.0]), 0.3
BEAMS = 180
ANGLE_MIN, INCREMENT = -np.pi, 2 * np.pi / BEAMS
# The recorded robot drives along y = 0.05 at 0.8 m/s, from x = -2.0 to -0.84, towards the post.
POSES = [np.array([-2.0 + 0.04 * k, 0.05, 0.0]) for k in range(N_STEPS)]
PROPOSAL = np.array([0.6, 0.0])

PARAMS = {
    'system': 'unicycle', 'alpha': 2.0, 'state_type': 'odometry', 'command_type': 'twist',
    'input_limits': {'min': [-1.0, -2.0], 'max': [1.0, 2.0]},
    'fail_safe_action': [0.0, 0.0],
    'obstacles': {'x': [40.0], 'y': [40.0], 'radius': [0.5], 'margin': 0.1,
                  'lookahead': 0.03, 'heading_index': 2, 'speed_input': 0},
    'footprint': {'radius': 0.2},
    'observation_sources': ['front'],
    'front': {'type': 'scan', 'topic': 'scan', 'timeout_s': 0.5},
}


LASER = np.array([0.15, -0.05])
"""Where a ``laser`` frame sits on base_link (yaw 0), in the bags that carry tf."""


def laser_pose(pose: np.ndarray) -> np.ndarray:
    """The laser's pose in odom for the robot's ``pose``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([pose[0] + c * LASER[0] - s * LASER[1],
                     pose[1] + s * LASER[0] + c * LASER[1], pose[2]])


def post_ranges(pose: np.ndarray) -> np.ndarray:
    """Ranges of the scan's beams from ``pose`` against the post (inf: no return), closed form
    of a ray meeting a circle."""
    angles = ANGLE_MIN + np.arange(BEAMS) * INCREMENT + pose[2]
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    offset = pose[:2] - POST
    b = d @ offset
    disc = b * b - (offset @ offset - POST_RADIUS ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def world_points(pose: np.ndarray) -> np.ndarray:
    """The scan's returns from ``pose``, in the odom frame."""
    ranges = post_ranges(pose)
    hit = np.isfinite(ranges)
    angles = ANGLE_MIN + np.arange(BEAMS)[hit] * INCREMENT + pose[2]
    return pose[:2] + ranges[hit, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def odometry(pose: np.ndarray, stamp_ns: int, child: str = 'base_link') -> dict:
    half = pose[2] / 2
    return {'header': {'stamp': {'sec': stamp_ns // 10**9, 'nanosec': stamp_ns % 10**9},
                       'frame_id': 'odom'},
            'child_frame_id': child,
            'pose': {'pose': {'position': {'x': float(pose[0]), 'y': float(pose[1]), 'z': 0.0},
                              'orientation': {'x': 0.0, 'y': 0.0, 'z': float(np.sin(half)),
                                              'w': float(np.cos(half))}},
                     'covariance': np.zeros(36)},
            'twist': {'twist': {'linear': {'x': 0.0, 'y': 0.0, 'z': 0.0},
                                'angular': {'x': 0.0, 'y': 0.0, 'z': 0.0}},
                      'covariance': np.zeros(36)}}


def stamp(stamp_ns: int) -> dict:
    return {'sec': stamp_ns // 10**9, 'nanosec': stamp_ns % 10**9}


def transform(parent: str, child: str, xy: np.ndarray, yaw: float, stamp_ns: int) -> dict:
    return {'header': {'stamp': stamp(stamp_ns), 'frame_id': parent}, 'child_frame_id': child,
            'transform': {'translation': {'x': float(xy[0]), 'y': float(xy[1]), 'z': 0.0},
                          'rotation': {'x': 0.0, 'y': 0.0, 'z': float(np.sin(yaw / 2)),
                                       'w': float(np.cos(yaw / 2))}}}


def scan(pose: np.ndarray, stamp_ns: int, frame: str = 'base_link') -> dict:
    return {'header': {'stamp': stamp(stamp_ns), 'frame_id': frame},
            'angle_min': ANGLE_MIN, 'angle_max': ANGLE_MIN + INCREMENT * (BEAMS - 1),
            'angle_increment': INCREMENT, 'time_increment': 0.0, 'scan_time': 0.1,
            'range_min': 0.05, 'range_max': 8.0,
            'ranges': post_ranges(pose).astype(np.float32),
            'intensities': np.zeros(0, np.float32)}


def twist(u: np.ndarray) -> dict:
    return {'linear': {'x': float(u[0]), 'y': 0.0, 'z': 0.0},
            'angular': {'x': 0.0, 'y': 0.0, 'z': float(u[1])}}


def write_robot_bag(directory: Path, *, command: str = '/cmd_vel_nav', odom: str = '/odom',
                    scan_until: int = N_STEPS, tf: bool = False,
                    child: str = 'base_link') -> Path:
    """What ``ros2 bag record`` holds around the drop-in launch: Odometry, a LaserScan in
    base_link (up to step ``scan_until``), the controller's Twist, the base's command; with
    ``tf``, the scan in the ``laser`` frame (:data:`LASER`) and /tf_static, /tf placing it."""
    with BagWriter(directory) as bag:
        bag.add_topic(odom, 'nav_msgs/msg/Odometry')
        bag.add_topic('/scan', 'sensor_msgs/msg/LaserScan')
        bag.add_topic(command, 'geometry_msgs/msg/Twist')
        bag.add_topic('/cmd_vel', 'geometry_msgs/msg/Twist')
        if tf:
            bag.add_topic('/tf', 'tf2_msgs/msg/TFMessage')
            bag.add_topic('/tf_static', 'tf2_msgs/msg/TFMessage')
            bag.write_message('/tf_static', {'transforms': [
                transform('base_link', 'laser', LASER, 0.0, T0)]}, T0 - 1)
        for k, pose in enumerate(POSES):
            t = T0 + k * STEP_NS
            bag.write_message(odom, odometry(pose, t, child), t)
            if tf:
                bag.write_message('/tf', {'transforms': [
                    transform('odom', 'base_link', pose[:2], float(pose[2]), t)]}, t)
                bag.write_message('/scan', scan(laser_pose(pose), t, 'laser'), t + 1_000_000)
            elif k < scan_until:
                bag.write_message('/scan', scan(pose, t), t + 1_000_000)
            bag.write_message(command, twist(PROPOSAL), t + 2_000_000)
            bag.write_message('/cmd_vel', twist(PROPOSAL), t + 3_000_000)
    return directory


def commands(path: Path) -> list[np.ndarray]:
    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.topic == '/refilter/cmd_safe']
        assert [c.msgtype for c in connections] == ['geometry_msgs/msg/Twist']
        return [np.array([m.linear.x, m.angular.z]) for m in (
            reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections))]


def expected_commands(tf: bool = False) -> list[np.ndarray]:
    """The core filter at each pose with the scan's points set by this test's geometry."""
    _, _, safety_filter = build_filter(resolve_params(PARAMS))
    out = []
    for pose in POSES:
        safety_filter.set_points(world_points(laser_pose(pose) if tf else pose))
        out.append(safety_filter.filter(pose, PROPOSAL).u_safe)
    return out


def test_a_drop_in_bag_is_refiltered_on_its_scan_under_the_launch_defaults(
        tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot')
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    assert summary.topics['cmd_proposed'] == '/cmd_vel_nav'
    assert summary.topics['state'] == '/odom' and summary.topics['front'] == '/scan'
    assert summary.proposals == summary.processed == N_STEPS
    got, want = commands(tmp_path / 'out'), expected_commands()
    assert len(got) == N_STEPS
    np.testing.assert_allclose(np.stack(got), np.stack(want), atol=1e-6)
    # the post makes the filter act near it, and only there
    assert summary.active > 0 and not np.allclose(got[-1], PROPOSAL)
    assert np.allclose(got[0], PROPOSAL)


def test_a_scan_in_its_own_frame_is_placed_through_the_bags_tf(tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    assert summary.processed == N_STEPS and summary.active > 0, summary.skipped
    np.testing.assert_allclose(np.stack(commands(tmp_path / 'out')),
                               np.stack(expected_commands(tf=True)), atol=1e-6)
    # the same scan placed as if it were at base_link's origin answers otherwise
    assert not np.allclose(np.stack(expected_commands(tf=True)), np.stack(expected_commands()),
                           atol=1e-6)


def test_an_odometry_of_another_child_frame_than_the_robot_s_gives_the_fail_safe(
        tmp_path: Path) -> None:
    # base_footprint's pose taken for base_link's would place the scan where the robot is not
    source = write_robot_bag(tmp_path / 'robot', child='base_footprint')
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    assert summary.skipped == {'bad state': N_STEPS} and summary.processed == 0
    assert all(np.array_equal(u, [0.0, 0.0]) for u in commands(tmp_path / 'out'))
    # a message naming no child frame is taken as the robot's
    summary = refilter_bag(write_robot_bag(tmp_path / 'unnamed', child=''), tmp_path / 'b',
                           PARAMS)
    assert summary.processed == N_STEPS and not summary.skipped


def test_remaps_name_the_topics_as_the_launch_was_given_them(tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot', command='/ctrl/cmd', odom='/robot/odom')
    with pytest.raises(RefilterError, match=r'no /cmd_proposed topic.*cmd_in:='):
        refilter_bag(source, tmp_path / 'none', PARAMS)
    summary = refilter_bag(source, tmp_path / 'out', PARAMS,
                           remaps={'cmd_in': 'ctrl/cmd', 'state': '/robot/odom'})
    assert (summary.topics['cmd_proposed'], summary.topics['state']) == ('/ctrl/cmd',
                                                                          '/robot/odom')
    np.testing.assert_allclose(np.stack(commands(tmp_path / 'out')),
                               np.stack(expected_commands()), atol=1e-6)


def test_a_scan_that_stops_leaves_the_later_proposals_unfiltered(tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot', scan_until=10)
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    stale = sum(n for reason, n in summary.skipped.items() if 'source front' in reason)
    # the last scan is stamped at step 9; proposal k comes 2 ms after its step: fresh while
    # (k - 9) * 50 ms + 2 ms <= timeout_s 0.5 s, so up to step 18
    assert summary.processed == 19 and stale == N_STEPS - 19, summary.skipped


@pytest.mark.parametrize('change, needle', [
    ({'front': {'type': 'scan', 'topic': 'laser'}}, 'front.topic: the source bag has no /laser'),
    ({'front': {'type': 'pointcloud', 'topic': 'scan'}},
     'front.topic: /scan holds sensor_msgs/msg/LaserScan'),
    ({'front': {'type': 'scan', 'topic': 'odom'}},
     "front.topic: 'odom' resolves to /odom, the node's own state topic"),
    ({'front': {'type': 'scan', 'topic': '/tf'}},
     "front.topic: '/tf' resolves to /tf, the node's own /tf topic"),
])
def test_a_source_the_bag_cannot_feed_is_refused_naming_it(change: dict, needle: str,
                                                           tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot')
    with pytest.raises(RefilterError, match=needle.replace('/', '/')):
        refilter_bag(source, tmp_path / 'out', dict(PARAMS, **change))
    assert not (tmp_path / 'out').exists()


def test_the_command_line_takes_the_launch_arguments(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture) -> None:
    source = write_robot_bag(tmp_path / 'robot', command='/ctrl/cmd')
    params = tmp_path / 'robot.yaml'
    params.write_text(yaml.safe_dump({'safety_filter': {'ros__parameters': PARAMS}}))
    assert main([str(source), str(tmp_path / 'out'), '--params-file', str(params),
                 'cmd_in:=/ctrl/cmd']) == 0
    assert 'cmd_proposed /ctrl/cmd' in capsys.readouterr().out
    for bad, needle in (('cmd_in=/x', 'not NAME:=TOPIC'), ('speed:=/x', 'unknown topic name'),
                        ('cmd_in:=9/x', 'is not a topic name'), ('odom:=', 'is not a topic'),
                        ('cmd_in:=/a/../b', 'is not a topic name')):
        assert main([str(source), str(tmp_path / 'bad'), '--params-file', str(params),
                     bad]) == 2, bad
        err = capsys.readouterr().err
        assert needle in err and len(err.strip().splitlines()) == 1, err
    assert main([str(source), str(tmp_path / 'bad'), '--params-file', str(params),
                 'cmd_in:=/a', 'cmd_proposed:=/b']) == 2
    assert 'remapped twice' in capsys.readouterr().err
    assert not (tmp_path / 'bad').exists()


def test_a_launch_argument_fills_the_others_with_the_launchs_defaults(tmp_path: Path) -> None:
    """``cmd_in:=X`` alone reads odom from /odom, as the launch given only cmd_in does."""
    source = write_robot_bag(tmp_path / 'robot', command='/ctrl/cmd')
    summary = refilter_bag(source, tmp_path / 'out', PARAMS, remaps={'cmd_in': '/ctrl/cmd'})
    assert summary.topics['state'] == '/odom' and summary.processed == N_STEPS


@pytest.mark.parametrize('remaps, needle', [
    ({'cmd_in': '/cmd_vel_nav', 'odom': '/cmd_vel_nav'},
     'state and cmd_proposed both resolve to /cmd_vel_nav'),
    ({'cmd_in': '/odom'}, 'state and cmd_proposed both resolve to /odom'),
    ({'cmd_proposed': '/cmd_vel_nav'}, 'has no /state topic, and its proposals'),
    ({'cmd_in': '/cmd_vel_nav', 'odom': '/robot/odom'}, 'has no /robot/odom topic'),
])
def test_topics_that_cannot_be_read_as_named_are_refused_before_the_run(
        remaps: dict, needle: str, tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot')
    with pytest.raises(RefilterError, match=needle):
        refilter_bag(source, tmp_path / 'out', PARAMS, remaps=remaps)
    assert not (tmp_path / 'out').exists()


def test_the_drop_in_names_are_the_launch_tables() -> None:
    """The bag layer cannot import the launch table: its copy of the defaults is checked
    here."""
    defaults = {argument.name: argument.default for argument in ROBOT_ARGUMENTS}
    for argument, node_topic in LAUNCH_ARGUMENTS.items():
        assert DROP_IN_TOPICS[node_topic] == '/' + defaults[argument]
    remapped = dict(next(node for node in launch_setup('safety_filter').nodes).remappings)
    assert {node_topic: remapped[node_topic].name
            for node_topic in LAUNCH_ARGUMENTS.values()} == {
        node_topic: argument for argument, node_topic in LAUNCH_ARGUMENTS.items()}


# -- a filter whose only obstacles are the scan's points -------------------------------------

SOURCES_ONLY = {**PARAMS, 'obstacles': {k: v for k, v in PARAMS['obstacles'].items()
                                        if k not in ('x', 'y', 'radius')}}
"""The robot's filter with no static obstacle: the lidar's points are its only rows."""


def test_a_sources_only_filter_refilters_on_the_scan(tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    summary = refilter_bag(source, tmp_path / 'out', SOURCES_ONLY)
    assert summary.barrier_names == [] and summary.min_h == {}
    assert summary.processed == N_STEPS and summary.active > 0, summary.skipped
    _, _, safety_filter = build_filter(resolve_params(SOURCES_ONLY))
    want = []
    for pose in POSES:
        safety_filter.set_points(world_points(laser_pose(pose)))
        want.append(safety_filter.filter(pose, PROPOSAL).u_safe)
    np.testing.assert_allclose(np.stack(commands(tmp_path / 'out')), np.stack(want), atol=1e-6)
    assert 'new filter: unicycle, 0 barriers' in summary.format()


def test_the_lidar_demo_and_readme_params_refilter_a_robot_bag(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The command lines a user runs on a bag of the drop-in launch (the lidar demo's params,
    the README's robot params): exit 0 and a bag of one answer per proposal, and with the
    README's control_period_s 0.05 one of the hold timer between two proposals: they come
    50 ms apart (2 ms after each Odometry), the timer calls every 12.5 ms from the first
    message (/tf_static, 1 ns before the first Odometry) and answers 37.5 ms or more after the
    latest answer, at 50 ms - 1 ns after it, within latency_s 0.05 of its Odometry."""
    from test_readme_robot_params import robot_yaml
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    readme = tmp_path / 'robot.yaml'
    readme.write_text(robot_yaml())
    for index, params in enumerate(('config/unicycle_lidar.yaml', str(readme))):
        out = tmp_path / f'out{index}'
        code = main([str(source), str(out), '--params-file',
                     str(Path(__file__).resolve().parents[2] / params)
                     if params.startswith('config') else params, 'cmd_in:=/cmd_vel_nav'])
        captured = capsys.readouterr()
        assert code == 0, captured.err
        assert 'Traceback' not in captured.err and '0 barriers' in captured.out
        assert len(commands(out)) == N_STEPS + (N_STEPS - 1 if index else 0)


class _Boom(RuntimeError):
    """A defect partway through the run."""


@pytest.mark.parametrize('params', [PARAMS, SOURCES_ONLY])
def test_a_run_that_fails_after_the_output_opened_leaves_no_bag(
        params: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import rcbf_ros.bag.refilter as refilter
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    real, calls = refilter._account, []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise _Boom('defect')
        return real(*args, **kwargs)
    monkeypatch.setattr(refilter, '_account', failing)
    with pytest.raises(_Boom):
        refilter_bag(source, tmp_path / 'new' / 'deeper' / 'out', params)
    assert not (tmp_path / 'new').exists()  # nor the directories made for it


def test_a_failure_in_the_summary_after_the_last_message_leaves_no_bag(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import rcbf_ros.bag.refilter as refilter
    source = write_robot_bag(tmp_path / 'robot', tf=True)

    def failing(*args, **kwargs):
        raise _Boom('defect')
    monkeypatch.setattr(refilter, '_barrier_statistics', failing)
    with pytest.raises(_Boom):
        refilter_bag(source, tmp_path / 'out', PARAMS)
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('inside', ['out', 'a/b'])
def test_an_output_inside_the_source_bag_is_refused(inside: str, tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot')
    before = sorted(p.name for p in source.iterdir())
    with pytest.raises(RefilterError, match='^output: .* is inside the source bag'):
        refilter_bag(source, source / inside, PARAMS)
    assert sorted(p.name for p in source.iterdir()) == before


# -- the node's topic rule and its params file section ------------------------------------


@pytest.mark.parametrize('remaps, needle', [
    ({'odom': '/tf'}, '/tf and state both resolve to /tf'),
    ({'cmd_in': '/rosout'}, '/rosout and cmd_proposed both resolve to /rosout'),
    ({'cmd_out': '/tf_static'}, '/tf_static and cmd_safe both resolve to /tf_static'),
    ({'cmd_in': '/cmd_vel', 'cmd_out': '/cmd_vel'},
     'cmd_proposed and cmd_safe both resolve to /cmd_vel'),
    ({'odom': '/scan'}, "front.topic: 'scan' resolves to /scan, the node's own state topic"),
])
def test_the_nodes_topic_clash_rule_holds_in_the_refilter(remaps: dict, needle: str,
                                                           tmp_path: Path) -> None:
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    with pytest.raises(RefilterError) as caught:
        refilter_bag(source, tmp_path / 'out', PARAMS, remaps=remaps)
    assert needle in str(caught.value) and '\n' not in str(caught.value)
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('node, needle', [
    ('nope', "--node 'nope': no section of .* names it \\(sections: /\\*\\*, /unicycle_lidar, "
             '/nominal_controller, /safety_filter, /recorder\\)'),
    ('unicycle_lidar', "--node 'unicycle_lidar': section /unicycle_lidar of .* is not a safety "
                       "filter's: arena_half_size, laser_mount, start are not"),
    ('recorder', "is not a safety filter's: best_effort_topics is not a safety_filter"),
])
def test_a_node_section_that_is_not_the_filters_is_refused(
        node: str, needle: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    source = write_robot_bag(tmp_path / 'robot', tf=True)
    params = str(Path(__file__).resolve().parents[2] / 'config' / 'unicycle_lidar.yaml')
    assert main([str(source), str(tmp_path / 'out'), '--params-file', params, '--node', node,
                 'cmd_in:=/cmd_vel_nav']) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and re.search(needle, err), err
    assert not (tmp_path / 'out').exists()


def test_a_params_file_of_wildcards_only_serves_any_node_name(tmp_path: Path) -> None:
    params = tmp_path / 'all.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': PARAMS}}))
    assert resolve_params(params, node='any_name')['system'] == 'unicycle'


# -- a sonar: sensor_msgs/Range ----------------------------------------------------------------

def test_a_range_source_is_refiltered_from_the_bag(tmp_path: Path) -> None:
    from rcbf_ros.messages.sensor import range_points
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    params = {**SOURCES_ONLY, 'observation_sources': ['sonar'],
              'sonar': {'type': 'range', 'topic': 'sonar'}}
    readings = [float(post_ranges(pose)[BEAMS // 2]) for pose in POSES]  # straight ahead
    readings = [r if np.isfinite(r) else 4.5 for r in readings]  # beyond max_range: nothing
    with BagWriter(tmp_path / 'robot') as bag:
        bag.add_topic('/odom', 'nav_msgs/msg/Odometry')
        bag.add_topic('/sonar', 'sensor_msgs/msg/Range')
        bag.add_topic('/cmd_vel_nav', 'geometry_msgs/msg/Twist')
        for k, (pose, reading) in enumerate(zip(POSES, readings)):
            t = T0 + k * STEP_NS
            bag.write_message('/odom', odometry(pose, t), t)
            bag.write_message('/sonar', {
                'header': {'stamp': stamp(t), 'frame_id': 'base_link'}, 'radiation_type': 0,
                'field_of_view': 0.4, 'min_range': 0.02, 'max_range': 4.0, 'range': reading,
                'variance': 0.0}, t + 1_000_000)
            bag.write_message('/cmd_vel_nav', twist(PROPOSAL), t + 2_000_000)
    summary = refilter_bag(tmp_path / 'robot', tmp_path / 'out', params)
    assert summary.topics['sonar'] == '/sonar'
    assert summary.processed == N_STEPS and summary.active > 0, summary.skipped
    _, _, safety_filter = build_filter(resolve_params(params))
    want = []
    for pose, reading in zip(POSES, readings):
        msg = store.types['sensor_msgs/msg/Range'](
            header=store.types['std_msgs/msg/Header'](
                stamp=store.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                frame_id='base_link'),
            radiation_type=0, field_of_view=0.4, min_range=0.02, max_range=4.0, range=reading,
            variance=0.0)
        read = range_points(bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/Range')))
        c, s = np.cos(pose[2]), np.sin(pose[2])
        placed = pose[:2] + read.points @ np.array([[c, s], [-s, c]])
        safety_filter.set_points(placed, read.spread)
        want.append(safety_filter.filter(pose, PROPOSAL).u_safe)
    np.testing.assert_allclose(np.stack(commands(tmp_path / 'out')), np.stack(want), atol=1e-6)

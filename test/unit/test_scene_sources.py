"""The scene of a filter whose only obstacles are sensor points: the lidar demo's.

Oracles: the params file (the frames, the footprint, the look-ahead), the lidar world's true
geometry (a binding point of a noise-free scan lies on a post's surface) and the Unicycle's
pose (the arrow's yaw, the guarded point ahead of it). The filter_info the scene reads is made
by the safety filter's own edge from a real answer, or has no ``binding_points`` section, no
row, or the most rows an answer holds.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from repo_files import REPO

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import BINDING_POINTS
from rcbf_ros.core.scene import scene_geometry
from rcbf_ros.messages.conversions import sections_to_cdr
from rcbf_ros.node_logic import safety_filter as filter_logic
from rcbf_ros.node_logic.filter_edge import FilterEdge
from rcbf_ros.node_logic.scene import (
    ACTIVE_ROW_VALUE,
    ARROW,
    info_binding_points,
    marker_frame,
    scene_markers,
    SPHERE,
)
from rcbf_ros.parameters.rules import load_params
from sim_nodes import lidar_world as lw
from sim_nodes.unicycle_lidar_node import build_world, settings_from_params

CONFIG = REPO / 'config' / 'unicycle_lidar.yaml'
FILTER = load_params(CONFIG, 'safety_filter')
SCENE = load_params(CONFIG, 'scene_markers')


def _by(markers, ns):
    return [m for m in markers if m['ns'] == ns]


def _info(**sections) -> bytes:
    return sections_to_cdr({'u': np.array([0.3, 0.0]), 'u_rl': np.array([0.5, 0.0]),
                            'u_s': np.array([-0.2, 0.0]), 'fail_safe': np.array([0.0]),
                            'status': np.array([0.0]), **sections})


def _draw(data: bytes, state=(0.0, 0.0, 0.0)):
    """What the scene node draws from one filter_info sample (its frame: the default's)."""
    geometry = scene_geometry(SCENE)
    return scene_markers(geometry=geometry, state=state, h={},
                         frame_id=marker_frame('', geometry), points=info_binding_points(data))


def test_the_scene_reads_the_filter_s_sources_footprint_and_guarded_point():
    geometry = scene_geometry(SCENE)
    assert geometry == scene_geometry(FILTER)   # the scene's keys are the filter's (/**)
    assert (geometry.obstacles, geometry.barrier_names) == ((), ())
    assert geometry.sensor_points and geometry.odom_frame_id == 'odom'
    assert (geometry.position_indices, geometry.heading_index) == ((0, 1), 2)
    assert (geometry.lookahead, geometry.footprint_radius) == (0.03, 0.2)
    assert marker_frame('', geometry) == 'odom' == marker_frame('odom', geometry)
    renamed = scene_geometry({**SCENE, 'odom_frame_id': 'wheel_odom'})
    assert marker_frame('', renamed) == 'wheel_odom'


def test_a_frame_other_than_the_points_is_refused_naming_both():
    with pytest.raises(ValueError, match=r"^frame_id: 'map' is not odom_frame_id 'odom'") as e:
        marker_frame('map', scene_geometry(SCENE))
    assert '\n' not in str(e.value)


def test_the_robot_footprint_and_guarded_point_at_the_pose():
    x, y, yaw = 1.0, -0.5, 0.7
    markers = scene_markers(geometry=scene_geometry(SCENE), state=[x, y, yaw], h={},
                            frame_id='odom')
    assert {m['frame_id'] for m in markers} == {'odom'}
    (robot,) = _by(markers, 'robot')
    assert robot['type'] == ARROW and robot['position'][:2] == (x, y)
    np.testing.assert_allclose(robot['orientation'],
                               [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)], atol=1e-15)
    (ring,) = _by(markers, 'footprint')
    points = np.array(ring['points'])
    np.testing.assert_allclose(np.hypot(points[:, 0] - x, points[:, 1] - y), 0.2, rtol=1e-12)
    (ahead,) = _by(markers, 'lookahead')
    np.testing.assert_allclose(ahead['position'][:2],
                               [x + 0.03 * math.cos(yaw), y + 0.03 * math.sin(yaw)], atol=1e-15)
    assert not _by(markers, 'barriers') and not _by(markers, 'obstacles')


def test_without_a_heading_the_robot_is_a_sphere_and_no_point_is_ahead():
    geometry = scene_geometry({**SCENE, 'obstacles.heading_index': -1,
                               'obstacles.lookahead': 0.0, 'obstacles.speed_input': -1})
    assert geometry.heading_index is None
    markers = scene_markers(geometry=geometry, state=[1.0, 2.0, 3.0], h={}, frame_id='odom',
                            points=np.array([[1.5, 2.0, 0.0, 0.1]]))
    (robot,) = _by(markers, 'robot')
    assert robot['type'] == SPHERE and robot['position'][:2] == (1.0, 2.0)
    assert not _by(markers, 'lookahead')
    (lines,) = _by(markers, 'active_rows')  # from the position itself
    assert lines['points'] == [(1.0, 2.0, 0.05), (1.5, 2.0, 0.05)]


def _scan_points(world: lw.World, pose: np.ndarray, lidar: lw.Lidar) -> np.ndarray:
    """A noise-free scan's returns in the world's frame (odom: no drift yet), (N, 2)."""
    at = lw.laser_pose(pose, lidar)
    ranges = lw.scan_ranges(world, pose, lidar).astype(np.float64)
    keep = np.isfinite(ranges)
    angles = lidar.angles[keep] + at[2]
    return at[:2] + ranges[keep, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def test_a_robot_driving_at_a_post_is_drawn_with_the_post_s_points_binding():
    """The demo's world and filter in one process: the robot 0.35 m from the post at
    (1.5, -1.5) drives at it; the scene of that answer's filter_info, made by the filter's
    own edge, draws in odom the points the filter named, on the post's true surface, with a
    line from the guarded point to each binding one."""
    robot = load_params(CONFIG, 'unicycle_lidar')
    settings = settings_from_params(robot)
    world = build_world(settings, robot)
    post = np.array([1.5, -1.5])
    pose = np.array([post[0] - 0.6 - 0.2 - 0.15, post[1], 0.0])
    lidar = lw.Lidar(mount=tuple(settings.laser_mount))
    config = filter_config_from_params(FILTER)
    safety_filter = SafetyFilter(config.problem, footprint=config.footprint)
    safety_filter.set_points(_scan_points(world, pose, lidar))
    decision = filter_logic.decide(
        safety_filter=safety_filter, proposal=filter_logic.Proposal(u=np.array([0.5, 0.0])),
        latest_state=filter_logic.StateSample(0, pose), now_ns=0, max_state_age_s=1.0)
    assert not decision.fail_safe and decision.u_safe[0] < 0.5 - 1e-3  # it brakes
    edge = FilterEdge(state_type='odometry', command_type='twist', system='unicycle', n_x=3,
                      n_u=2)
    markers = _draw(edge.info_cdr(decision), state=pose)
    assert {m['frame_id'] for m in markers} == {'odom'}
    (spheres,) = _by(markers, 'binding_points')
    drawn = np.array(spheres['points'])
    assert len(drawn) == BINDING_POINTS
    np.testing.assert_allclose(np.hypot(*(drawn[:, :2] - post).T), 0.6, atol=1e-6)
    (lines,) = _by(markers, 'active_rows')
    assert lines['points'], 'no active row while braking for the post'
    starts = np.array(lines['points'][0::2])
    np.testing.assert_allclose(starts[:, :2], np.tile(pose[:2] + [0.03, 0.0], (len(starts), 1)),
                               atol=1e-12)
    assert {tuple(p) for p in lines['points'][1::2]} <= {tuple(p) for p in drawn}


@pytest.mark.parametrize('rows', [0, 1, BINDING_POINTS])
def test_any_number_of_rows_up_to_the_most_an_answer_holds(rows):
    points = np.array([[2.0 + i, -1.0, ACTIVE_ROW_VALUE * (i % 2 * 4 - 1), 0.1]
                       for i in range(rows)]).reshape(-1, 4)
    data = _info(binding_points=points.reshape(-1)) if rows else _info()
    markers = _draw(data)
    assert {m['frame_id'] for m in markers} == {'odom'}
    (spheres,) = _by(markers, 'binding_points')
    assert spheres['points'] == [(x, y, 0.05) for x, y in points[:, :2].tolist()]
    (lines,) = _by(markers, 'active_rows')
    assert lines['points'][1::2] == [(x, y, 0.05) for x, y, v, _ in points.tolist()
                                     if v <= ACTIVE_ROW_VALUE]


def test_filter_info_without_the_optional_sections_draws_empty_lists():
    """A fail-safe answer before any row was evaluated: only the five fixed sections."""
    markers = _draw(_info())
    assert [m['points'] for m in _by(markers, 'binding_points') + _by(markers, 'active_rows')
            ] == [[], []]
    assert _by(markers, 'footprint') and _by(markers, 'robot')


# the node ----------------------------------------------------------------------------------
@pytest.fixture
def lidar_scene(ros_domain_id, monkeypatch):
    """The scene node as the lidar launch starts it: the demo's params file, odometry in."""
    from rcbf_ros.ros import scene_node as module
    from rcbf_ros.ros.dds import rclpy_compat
    nodes = []

    def start(*extra: str):
        rclpy_compat.init(args=['prog', '--ros-args', '--params-file', str(CONFIG), '-p',
                                'state_type:=odometry', *extra], domain_id=ros_domain_id)
        node = module.SceneNode()
        nodes.append(node)
        monkeypatch.setattr(module, 'time', SimpleNamespace(monotonic_ns=lambda: 0))
        published, warnings = [], []
        monkeypatch.setattr(node._publisher, 'publish', published.append)
        monkeypatch.setattr(node, 'get_logger', lambda: SimpleNamespace(
            warning=warnings.append, error=warnings.append, info=lambda *_: None))
        node.published_arrays, node.warnings = published, warnings
        return node

    yield start
    for node in nodes:
        node.destroy_node()
    rclpy_compat.try_shutdown()


def _odometry(frame_id: str, pose) -> bytes:
    from rcbf_ros.messages.conversions import state_to_odometry
    from rcbf_ros.ros.runtime import serialize_message
    return serialize_message(state_to_odometry(pose, system='unicycle', stamp_ns=0,
                                               frame_id=frame_id, child_frame_id='base_link'))


def _diagnostics(message: str, values: dict[str, str]) -> bytes:
    from rcbf_ros.ros.runtime import get_message, serialize_message
    array = get_message('diagnostic_msgs/msg/DiagnosticArray')()
    status = get_message('diagnostic_msgs/msg/DiagnosticStatus')(
        level=b'\x01', name='safety_filter', message=message)
    key_value = get_message('diagnostic_msgs/msg/KeyValue')
    status.values = [key_value(key=k, value=v) for k, v in values.items()]
    array.status = [status]
    return serialize_message(array)


def test_the_node_draws_the_lidar_scene_in_odom(lidar_scene):
    node = lidar_scene()
    assert node.frame_id == 'odom'
    node._on_state(_odometry('odom', [1.0, -0.5, 0.7]))
    node._on_diagnostics(_diagnostics('source scan: no message yet', {'min_h': '',
                                                                      'status': 'x'}))
    node._on_filter_info(_info(binding_points=np.array([1.5, -0.5, 0.0, 0.1])))
    node._on_timer()
    (array,) = node.published_arrays
    assert {m.header.frame_id for m in array.markers} == {'odom'}
    by_ns = {m.ns: m for m in array.markers}
    assert by_ns['robot'].pose.position.x == 1.0
    assert [(p.x, p.y) for p in by_ns['binding_points'].points] == [(1.5, -0.5)]
    assert len(by_ns['active_rows'].points) == 2
    assert by_ns['status'].text == 'source scan: no message yet'   # with sensor rows only
    assert not node.warnings


def test_the_node_skips_an_odometry_in_another_frame(lidar_scene):
    node = lidar_scene()
    node._on_state(_odometry('odom', [1.0, -0.5, 0.7]))
    node._on_state(_odometry('map', [3.0, 3.0, 0.0]))
    np.testing.assert_array_equal(node.state, [1.0, -0.5, 0.7])
    assert len(node.warnings) == 1 and "header.frame_id: 'map'" in node.warnings[0]


def test_the_node_refuses_a_frame_the_points_are_not_in(lidar_scene):
    with pytest.raises(ValueError, match='frame_id'):
        lidar_scene('-p', 'frame_id:=map')


def _obstacle_rows(count: int) -> bytes:
    from rcbf_ros.ros.runtime import get_message, serialize_message
    rng = np.random.default_rng(0)
    rows = np.column_stack([rng.uniform(5, 500, count), rng.uniform(5, 500, count),
                            np.full(count, 0.1)])
    array = get_message('std_msgs/msg/Float64MultiArray')()
    dim = get_message('std_msgs/msg/MultiArrayDimension')
    array.data = rows.reshape(-1).tolist()
    array.layout.dim = [dim(label='obstacles', size=count, stride=3 * count),
                        dim(label='xyr', size=3, stride=3)]
    return serialize_message(array)


def test_the_node_draws_a_bounded_scene_of_a_huge_obstacle_set_and_says_so_once(
        lidar_scene, monkeypatch):
    """A 20,000-row obstacles message took 14 s and 38 MB per array: max_obstacles are drawn,
    each array replaces the whole scene (the nearest change as the robot moves), and the
    number left out is said once per obstacle set."""
    from rcbf_ros.node_logic.scene import CYLINDER
    from rcbf_ros.ros.scene_node import MARKER_DELETEALL
    node = lidar_scene('-p', 'max_obstacles:=50')
    said = []
    monkeypatch.setattr(node, 'get_logger', lambda: SimpleNamespace(
        warning=node.warnings.append, error=node.warnings.append, info=said.append))
    node._on_obstacles(_obstacle_rows(20_000))
    assert len(node.geometry.obstacles) == 20_000 and not node.warnings
    assert said == [_omitted(50, 20_000)]
    for pose in ([0.0, 0.0, 0.0], [400.0, 400.0, 0.0]):
        node._on_state(_odometry('odom', pose))
        node._on_timer()
    assert len(said) == 1
    for array in node.published_arrays:
        assert array.markers[0].action == MARKER_DELETEALL
        assert sum(m.type == CYLINDER and m.ns == 'obstacles' for m in array.markers) == 50
        assert len(array.markers) < 200
    first, second = ({m.id for m in array.markers if m.ns == 'obstacles'}
                     for array in node.published_arrays)
    assert first != second   # the nearest to where the robot is


def _omitted(drawn: int, count: int) -> str:
    from rcbf_ros.node_logic.scene import omitted_text
    return omitted_text(drawn, count)


def test_a_huge_frame_id_makes_one_short_warning(lidar_scene):
    from rcbf_ros.node_logic.filter_edge import REASON_LIMIT
    node = lidar_scene()
    node._on_state(_odometry('x' * 1_000_000, [1.0, -0.5, 0.7]))
    assert node.state is None
    node._throttle = type(node._throttle)(0.0)   # every warning said
    node._on_state(_odometry('y' * 1024, [1.0, -0.5, 0.7]))   # within the bound, not odom
    first, second = node.warnings
    assert first.startswith('state skipped: header.frame_id: 1000000 characters')
    assert second.startswith("state skipped: header.frame_id: 'yyy")
    assert second.endswith('characters more)')
    assert max(len(first), len(second)) <= REASON_LIMIT

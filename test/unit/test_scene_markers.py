"""The scene markers as plain data (no DDS): geometry from the filter config, markers per state."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rcbf_ros.core.scene import scene_geometry
from rcbf_ros.launch.table import CLOSED_LOOPS
from rcbf_ros.node_logic import scene as logic
from rcbf_ros.node_logic.scene import (
    AMBER,
    ARROW,
    CUBE,
    CYLINDER,
    GREEN,
    GREY,
    LINE_STRIP,
    RED,
    ROBOT,
    scene_markers,
    SPHERE,
    TEXT_VIEW_FACING,
)
from rcbf_ros.parameters.rules import find_config, load_params


def _geometry(system: str):
    return scene_geometry(load_params(find_config(system), 'safety_filter'))


def _by(markers, ns):
    return sorted((m for m in markers if m['ns'] == ns), key=lambda m: m['id'])


def _yaw_of(quaternion) -> float:
    x, y, z, w = quaternion
    assert x == pytest.approx(0.0) and y == pytest.approx(0.0)
    return 2.0 * math.atan2(z, w)


def test_geometry_is_the_filter_config_of_the_params_file():
    params = load_params(find_config('unicycle'), 'safety_filter')
    geometry = scene_geometry(params)
    assert [(d.x, d.y, d.radius, d.margin) for d in geometry.obstacles] == [
        (x, y, r, 0.1) for x, y, r in zip(params['obstacles.x'], params['obstacles.y'],
                                          params['obstacles.radius'])]
    assert geometry.barrier_names == tuple(f'obstacle_{i}' for i in range(5))
    assert geometry.heading_index == 2 and geometry.lookahead == 0.03
    with pytest.raises(ValueError, match='obstacles.y'):
        scene_geometry({**params, 'obstacles.y': [0.0]})


def test_unicycle_markers_count_place_and_colour():
    geometry = _geometry('unicycle')
    state = [-0.5, -1.0, 0.7]
    h = {'obstacle_0': -0.2, 'obstacle_1': 0.05, 'obstacle_2': 3.0, 'obstacle_3': float('nan')}
    markers = scene_markers(geometry=geometry, state=state, h=h, frame_id='odom',
                            caution=0.1, status=(0, 'filtering'))
    counts = {ns: len(_by(markers, ns)) for ns in {m['ns'] for m in markers}}
    assert counts == {'obstacles': 5, 'margins': 5, 'barriers': 5, 'robot': 1, 'lookahead': 1,
                      'status': 1}
    assert {m['frame_id'] for m in markers} == {'odom'}
    assert len({(m['ns'], m['id']) for m in markers}) == len(markers)  # ids unique per ns

    for disc, cylinder, ring in zip(geometry.obstacles, _by(markers, 'obstacles'),
                                    _by(markers, 'margins')):
        assert cylinder['type'] == CYLINDER
        assert cylinder['position'][:2] == (disc.x, disc.y)
        assert cylinder['scale'][:2] == (2 * disc.radius, 2 * disc.radius)  # the true radius
        assert ring['type'] == LINE_STRIP and ring['color'][3] < 1.0  # translucent
        points = np.array(ring['points'])
        distance = np.hypot(points[:, 0] - disc.x, points[:, 1] - disc.y)
        np.testing.assert_allclose(distance, disc.radius + disc.margin, rtol=1e-12)
        np.testing.assert_allclose(points[0], points[-1], atol=1e-12)  # closed
    rings = [m['color'][:3] for m in _by(markers, 'margins')]
    assert rings == [RED[:3], AMBER[:3], GREEN[:3], GREY[:3], GREY[:3]]  # 4: not reported

    texts = _by(markers, 'barriers')
    assert [t['type'] for t in texts] == [TEXT_VIEW_FACING] * 5
    assert texts[0]['text'] == 'obstacle_0  h = -0.200' and texts[0]['color'] == RED
    assert texts[1]['color'] == AMBER and texts[2]['color'] == GREEN
    assert texts[3]['text'] == 'obstacle_3  h = ?' and texts[3]['color'] == GREY
    assert texts[0]['position'][:2] == (geometry.obstacles[0].x, geometry.obstacles[0].y)

    (arrow,) = _by(markers, 'robot')
    assert arrow['type'] == ARROW and arrow['position'][:2] == (-0.5, -1.0)
    assert _yaw_of(arrow['orientation']) == pytest.approx(0.7)
    (point,) = _by(markers, 'lookahead')
    assert point['type'] == SPHERE
    np.testing.assert_allclose(point['position'][:2],
                               [-0.5 + 0.03 * math.cos(0.7), -1.0 + 0.03 * math.sin(0.7)])
    assert point['color'] == RED  # the worst obstacle value (obstacle_3's NaN: unknown)
    (status,) = _by(markers, 'status')
    assert status['text'] == 'filtering'


def test_without_a_state_the_scene_has_no_robot():
    markers = scene_markers(geometry=_geometry('unicycle'), state=None, h={})
    assert {m['ns'] for m in markers} == {'obstacles', 'margins', 'barriers'}
    assert {m['frame_id'] for m in markers} == {'map'}


@pytest.mark.parametrize('state, frame_id, match', [
    ([0.0, 0.0], 'map', 'state: expected 3 values, got 2'),
    ([0.0, float('nan'), 0.0], 'map', 'state: contains NaN'),
    ([0.0, 0.0, 0.0], '', 'frame_id'),
])
def test_bad_state_or_frame_is_refused_naming_it(state, frame_id, match):
    with pytest.raises(ValueError, match=match):
        scene_markers(geometry=_geometry('unicycle'), state=state, h={}, frame_id=frame_id)


def test_pvtol_lies_in_the_x_z_plane_with_its_tilt_and_the_operator_band():
    geometry = _geometry('pvtol')
    theta, thrust = 0.3, 1.2
    state = [-2.0, 1.0, 0.0, 0.0, theta, thrust, -1.8]
    markers = scene_markers(geometry=geometry, state=state,
                            h={'operator_upper': 0.4, 'operator_lower': -0.01, 'tilt': 0.05})
    for disc, cylinder in zip(geometry.obstacles, _by(markers, 'obstacles')):
        assert (cylinder['position'][0], cylinder['position'][2]) == (disc.x, disc.y)
    body, thrust_arrow = _by(markers, 'robot')
    assert body['type'] == CUBE and body['position'] == (-2.0, 0.0, 1.0)
    # the body's own z (up) turned to the thrust direction (-sin theta, 0, cos theta)
    x, y, z, w = body['orientation']
    up = (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    np.testing.assert_allclose(up, [-math.sin(theta), 0.0, math.cos(theta)], atol=1e-12)
    start, end = np.array(thrust_arrow['points'])
    np.testing.assert_allclose(end - start, 0.3 * thrust * np.array(
        [-math.sin(theta), 0.0, math.cos(theta)]))
    (band,) = _by(markers, 'bands')
    assert band['position'][0] == -1.8 and band['scale'][0] == pytest.approx(1.0)  # 2 * 0.5
    assert band['color'][:3] == RED[:3]  # the worse of its two sides
    # one side not reported (yet): the other still colours the band
    for h in ({'operator_lower': -0.01}, {'operator_upper': float('nan'), 'operator_lower': -1}):
        (band,) = _by(scene_markers(geometry=geometry, state=state, h=h), 'bands')
        assert band['color'][:3] == RED[:3], h
    texts = {t['text'].split()[0]: t for t in _by(markers, 'barriers')}
    assert len(texts) == len(geometry.barrier_names) == 17
    assert texts['tilt']['color'] == AMBER and texts['thrust']['color'] == GREY


def test_car_following_cars_on_a_line_and_gaps_coloured_by_h():
    geometry = _geometry('car_following')
    positions = [40.0, 33.0, 27.0, 22.0, 17.5]
    state = np.zeros(10)
    state[0::2], state[1::2] = positions, 30.0
    markers = scene_markers(geometry=geometry, state=state,
                            h={'gap_4_6': -1.0, 'gap_8_6': 20.0})
    cars = _by(markers, 'robot')
    assert [c['position'][0] for c in cars] == positions
    assert {c['position'][1] for c in cars} == {0.0}
    assert [c['color'] == ROBOT for c in cars] == [False, False, False, True, False]  # car 4
    front, rear = _by(markers, 'gaps')
    assert [p[0] for p in front['points']] == [27.0, 22.0] and front['color'] == RED
    assert [p[0] for p in rear['points']] == [17.5, 22.0] and rear['color'] == GREEN
    texts = _by(markers, 'barriers')
    assert texts[0]['position'][0] == pytest.approx(24.5)  # between the cars of its gap


def test_h_colour_thresholds():
    assert logic.h_colour(-1e-9, caution=0.1) == RED
    assert logic.h_colour(0.0, caution=0.1) == AMBER
    assert logic.h_colour(0.0999, caution=0.1) == AMBER
    assert logic.h_colour(0.1, caution=0.1) == GREEN
    assert logic.h_colour(float('nan')) == GREY


def test_barrier_values_from_diagnostic_key_values():
    values = {'h.obstacle_0': '0.25', 'h.obstacle_1': 'nan', 'h.obstacle_2': 'garbage',
              'min_h': '0.25', 'constraint.obstacle_0': '1.0', 'h.': '3'}
    h = logic.barrier_values(values)
    assert set(h) == {'obstacle_0', 'obstacle_1', 'obstacle_2'}
    assert h['obstacle_0'] == 0.25 and math.isnan(h['obstacle_1']) and math.isnan(
        h['obstacle_2'])


@pytest.mark.parametrize('params, match', [
    ({'frame_id': 3}, 'frame_id'), ({'frame_id': ['map']}, 'frame_id'),
    ({'rate_hz': 0.0}, 'rate_hz'), ({'rate_hz': 'fast'}, 'rate_hz'),
    ({'caution_h': -0.1}, 'caution_h'),
    ({'max_obstacles': -1}, 'max_obstacles'), ({'max_obstacles': 10 ** 6}, 'max_obstacles'),
    ({'max_obstacles': 2.5}, 'max_obstacles'),
    ({'frame_id': '/map'}, 'frame_id: .*starts with /'),
    ({'frame_id': 'my map'}, 'frame_id: .*white space'),
    ({'frame_id': 'm' * 1025}, 'frame_id: 1025 characters'),
])
def test_scene_settings_refuse_bad_values_naming_the_key(params, match):
    with pytest.raises(ValueError, match=match):
        logic.scene_settings(params)


def test_scene_settings_defaults():
    settings = logic.scene_settings({})
    assert (settings.frame_id, settings.rate_hz, settings.caution_h) == ('', 10.0, 0.1)
    # '' is the filter's state frame: map without observation sources
    assert logic.marker_frame(settings.frame_id, _geometry('unicycle')) == 'map'
    assert logic.marker_frame('odom', _geometry('unicycle')) == 'odom'


def test_marker_constants_and_message_round_trip():
    from rcbf_ros.ros.runtime import deserialize_message, get_message, serialize_message
    from rcbf_ros.ros.scene_node import marker_array
    marker = get_message('visualization_msgs/msg/Marker')
    assert (marker.ARROW, marker.CUBE, marker.SPHERE, marker.CYLINDER, marker.LINE_STRIP,
            marker.TEXT_VIEW_FACING) == (ARROW, CUBE, SPHERE, CYLINDER, LINE_STRIP,
                                         TEXT_VIEW_FACING)
    markers = scene_markers(geometry=_geometry('unicycle'), state=[0.0, -1.0, 1.0],
                            h={'obstacle_0': 0.5}, frame_id='map', status=(2, 'stale state'))
    array_type = get_message('visualization_msgs/msg/MarkerArray')
    back = deserialize_message(serialize_message(marker_array(markers)), array_type).markers
    assert len(back) == len(markers)
    for msg, item in zip(back, markers):
        assert (msg.header.frame_id, msg.ns, msg.id, msg.type, msg.action) == (
            item['frame_id'], item['ns'], item['id'], item['type'], 0)
        assert (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) == \
            item['position']
        orientation = msg.pose.orientation
        assert (orientation.x, orientation.y, orientation.z, orientation.w) == \
            item['orientation']
        assert (msg.color.r, msg.color.g, msg.color.b, msg.color.a) == pytest.approx(
            item['color'], abs=1e-6)  # float32
        assert [(p.x, p.y, p.z) for p in msg.points] == item.get('points', [])
        assert msg.text == item.get('text', '')


def test_every_closed_loop_launch_starts_the_scene_and_records_it():
    for setup in CLOSED_LOOPS:
        names = [n.name for n in setup.nodes]
        assert 'scene_markers' in names, setup.name
        assert not setup.node('scene_markers').required  # a picture never fails a launch
        recorder = load_params(find_config(setup.config.removesuffix('.yaml')), 'recorder')
        recorder.update(dict(setup.node('recorder').parameters))
        topics = recorder.get('topics') or []
        assert not topics or '/scene_markers' in topics, setup.name  # empty: every topic


def test_foxglove_layout_shows_the_scene_the_barriers_and_the_command():
    import json
    from pathlib import Path
    layout = json.loads((Path(__file__).resolve().parents[2] / 'config'
                         / 'foxglove_layout.json').read_text())
    panels = layout['configById']

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node['first']) + leaves(
            node['second'])
    assert sorted(leaves(layout['layout'])) == sorted(panels)  # every panel placed, once
    (scene,) = [config for name, config in panels.items() if name.startswith('3D!')]
    assert scene['followTf'] == 'map' and scene['topics']['/scene_markers']['visible']
    plotted = [p['value'] for name, config in panels.items() if name.startswith('Plot!')
               for p in config['paths']]
    names = _geometry('unicycle').barrier_names
    for name in names:
        assert any(f'{{key=="h.{name}"}}' in value for value in plotted), name
    assert all(v.startswith(('/diagnostics.status[:]{name=="safety_filter"}', '/cmd_safe.data[',
                             '/filter_info.data[')) for v in plotted)
    # cmd_safe holds the command alone (n_u = 2 values); the correction u_S is filter_info's
    # third section, data[4:6] for the Unicycle.
    from rcbf_ros.core.filter_info import INFO_SECTIONS
    assert [label for label, _, _ in INFO_SECTIONS[:3]] == ['u', 'u_rl', 'u_s']
    command = {int(v[len('/cmd_safe.data['):-1]) for v in plotted if v.startswith('/cmd_safe')}
    correction = {int(v[len('/filter_info.data['):-1]) for v in plotted
                  if v.startswith('/filter_info')}
    assert command == {0, 1} and correction == {4, 5}


def test_marker_arrays_go_into_a_bag_that_rosbags_reads_back(tmp_path):
    from rosbags.highlevel import AnyReader

    from rcbf_ros.bag import BagWriter
    from rcbf_ros.ros.scene_node import MARKER_ARRAY, marker_array
    markers = scene_markers(geometry=_geometry('pvtol'),
                            state=[-2.0, 1.0, 0.0, 0.0, 0.3, 1.0, -1.8], h={'tilt': 0.5})
    writer = BagWriter(tmp_path / 'bag')
    writer.add_topic('/scene_markers', MARKER_ARRAY)
    writer.write_message('/scene_markers', marker_array(markers), 1_000)
    writer.close()
    with AnyReader([tmp_path / 'bag']) as reader:
        (connection,) = reader.connections
        assert connection.msgtype == MARKER_ARRAY
        ((_, _, raw),) = list(reader.messages(connections=[connection]))
        back = reader.deserialize(raw, connection.msgtype).markers
    assert [(m.ns, m.id, m.text) for m in back] == [
        (m['ns'], m['id'], m.get('text', '')) for m in markers]


def _many_obstacles(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    params = load_params(find_config('unicycle'), 'safety_filter')
    x, y = rng.uniform(-500.0, 500.0, count), rng.uniform(-500.0, 500.0, count)
    radius = rng.uniform(0.05, 2.0, count)
    return scene_geometry({**params, 'obstacles.x': x.tolist(), 'obstacles.y': y.tolist(),
                           'obstacles.radius': radius.tolist()}), np.stack([x, y, radius], 1)


@pytest.mark.parametrize('limit', [0, 1, 37, 200])
def test_a_huge_obstacle_set_draws_the_nearest_up_to_the_bound_and_says_how_many_are_not(limit):
    """20,000 obstacles took 14 s and 38 MB an array: at most max_obstacles are drawn, the
    nearest to the robot by the distance to their edge (a brute-force sort is the oracle)."""
    geometry, discs = _many_obstacles(20_000)
    state = np.array([3.0, -4.0, 0.3])
    h = {f'obstacle_{k}': 1.0 for k in range(20_000)}
    markers = scene_markers(geometry=geometry, state=state, h=h, frame_id='odom',
                            max_obstacles=limit)
    gap = np.hypot(discs[:, 0] - 3.0, discs[:, 1] + 4.0) - discs[:, 2]
    nearest = sorted(np.argsort(gap, kind='stable')[:limit].tolist())
    assert [m['id'] for m in _by(markers, 'obstacles')] == nearest   # ids: the obstacle's own
    assert [m['id'] for m in _by(markers, 'margins')] == nearest
    labels = [m['text'].split()[0] for m in _by(markers, 'barriers')]
    assert labels == [f'obstacle_{k}' for k in nearest]
    omitted = _by(markers, 'omitted')
    assert len(omitted) == 1 and omitted[0]['text'] == logic.omitted_text(limit, 20_000)
    assert omitted[0]['text'].startswith(f'{20_000 - limit} of 20000 obstacles not drawn')
    assert len(markers) <= 3 * limit + 10


def test_without_a_state_the_first_obstacles_are_drawn_and_a_small_set_whole():
    geometry, _ = _many_obstacles(300)
    markers = scene_markers(geometry=geometry, state=None, h={}, max_obstacles=10)
    assert [m['id'] for m in _by(markers, 'obstacles')] == list(range(10))
    assert len(_by(markers, 'omitted')) == 1
    markers = scene_markers(geometry=geometry, state=[0.0, 0.0, 0.0], h={}, max_obstacles=300)
    assert len(_by(markers, 'obstacles')) == 300 and _by(markers, 'omitted') == []
    assert logic.scene_settings({}).max_obstacles == 200

"""The scene's footprint, binding points and active rows, and how filter_info is read for them.

Closed forms: a known point set gives spheres at the points, coloured by the barrier values'
rule, and a line from the guarded point (the look-ahead point of the state) to each point
whose row binds; the footprint is a closed ring of its radius around the robot's position.
Hostile filter_info bytes (anything, truncated, bit-flipped, wrong sections, NaN, too long):
a one-line ValueError from the reader, never an exception out of the node's callbacks.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from repo_files import REPO

from rcbf_ros.core.filter_info import BINDING_POINTS
from rcbf_ros.core.scene import scene_geometry
from rcbf_ros.messages.conversions import sections_to_cdr
from rcbf_ros.node_logic.scene import (
    ACTIVE_ROW_VALUE,
    AMBER,
    GREEN,
    info_binding_points,
    LINE_LIST,
    LINE_STRIP,
    MAX_INFO_BYTES,
    RED,
    scene_markers,
    SPHERE_LIST,
)
from rcbf_ros.parameters.rules import find_config, load_params

ROWS = np.array([[1.0, 0.5, -0.02, 0.01],   # needs slack: active, red
                 [1.2, -0.3, 0.0, 0.2],     # binds: active, amber (0 <= v < caution)
                 [0.0, 2.0, 0.05, 0.4],     # close: amber, not active
                 [-3.0, 1.0, 0.7, 2.0]])    # far: green
"""[x, y, row value, h] of four points, least row value first."""


def _geometry(**changes):
    params = load_params(find_config('unicycle'), 'safety_filter')
    return scene_geometry({**params, **changes})


def _by(markers, ns):
    return [m for m in markers if m['ns'] == ns]


def _info(**sections) -> bytes:
    return sections_to_cdr({'u': np.array([0.1, 0.0]), 'u_rl': np.array([0.3, 0.0]),
                            'u_s': np.array([-0.2, 0.0]), 'fail_safe': np.array([0.0]),
                            'status': np.array([0.0]), **sections})


def test_footprint_is_a_closed_ring_of_its_radius_around_the_position():
    state = [0.4, -1.2, 2.0]
    markers = scene_markers(geometry=_geometry(**{'footprint.radius': 0.3}), state=state, h={})
    (ring,) = _by(markers, 'footprint')
    assert ring['type'] == LINE_STRIP
    points = np.array(ring['points'])
    np.testing.assert_allclose(np.hypot(points[:, 0] - 0.4, points[:, 1] + 1.2), 0.3,
                               rtol=1e-12)
    np.testing.assert_allclose(points[0], points[-1], atol=1e-12)
    # no radius (the shipped unicycle.yaml), or no state: no ring
    assert not _by(scene_markers(geometry=_geometry(), state=state, h={}), 'footprint')
    assert not _by(scene_markers(geometry=_geometry(**{'footprint.radius': 0.3}), state=None,
                                 h={}), 'footprint')


def test_binding_points_and_active_rows_closed_form():
    geometry = _geometry(**{'footprint.radius': 0.2})
    x, y, theta = -0.5, 0.25, 0.6
    markers = scene_markers(geometry=geometry, state=[x, y, theta], h={}, caution=0.1,
                            points=ROWS)
    (spheres,) = _by(markers, 'binding_points')
    assert spheres['type'] == SPHERE_LIST and spheres['id'] == 0
    assert spheres['points'] == [(1.0, 0.5, 0.05), (1.2, -0.3, 0.05), (0.0, 2.0, 0.05),
                                 (-3.0, 1.0, 0.05)]
    assert spheres['colors'] == [RED, AMBER, AMBER, GREEN]
    (lines,) = _by(markers, 'active_rows')
    assert lines['type'] == LINE_LIST
    guarded = (x + 0.03 * math.cos(theta), y + 0.03 * math.sin(theta), 0.05)  # lookahead 0.03
    np.testing.assert_allclose(lines['points'], [guarded, (1.0, 0.5, 0.05), guarded,
                                                 (1.2, -0.3, 0.05)], atol=1e-15)
    assert lines['colors'] == [RED, RED, AMBER, AMBER]
    assert len({(m['ns'], m['id']) for m in markers}) == len(markers)


def test_active_row_threshold_and_empty_lists():
    geometry = _geometry()
    just = np.array([[1.0, 1.0, ACTIVE_ROW_VALUE, 0.1], [2.0, 2.0, 2 * ACTIVE_ROW_VALUE, 0.1]])
    (lines,) = _by(scene_markers(geometry=geometry, state=[0.0, 0.0, 0.0], h={}, points=just),
                   'active_rows')
    assert len(lines['points']) == 2 and lines['points'][1] == (1.0, 1.0, 0.05)
    # an answer without points: both lists there, empty (the last points are replaced)
    markers = scene_markers(geometry=geometry, state=[0.0, 0.0, 0.0], h={},
                            points=np.empty((0, 4)))
    assert [m['points'] for m in _by(markers, 'binding_points') + _by(markers, 'active_rows')
            ] == [[], []]
    # no filter_info read: nothing for them; no state: the spheres without lines
    assert not _by(scene_markers(geometry=geometry, state=None, h={}), 'binding_points')
    markers = scene_markers(geometry=geometry, state=None, h={}, points=ROWS)
    assert len(_by(markers, 'binding_points')[0]['points']) == 4
    assert _by(markers, 'active_rows')[0]['points'] == []
    for bad in (np.full((1, 4), np.nan), np.zeros((2, 3)), np.zeros(4)):
        with pytest.raises(ValueError, match='points'):
            scene_markers(geometry=geometry, state=None, h={}, points=bad)


def test_markers_with_colours_round_trip_as_messages():
    from rcbf_ros.ros.runtime import deserialize_message, get_message, serialize_message
    from rcbf_ros.ros.scene_node import marker_array
    marker = get_message('visualization_msgs/msg/Marker')
    assert (marker.LINE_LIST, marker.SPHERE_LIST) == (LINE_LIST, SPHERE_LIST)
    markers = scene_markers(geometry=_geometry(**{'footprint.radius': 0.2}),
                            state=[0.0, 0.0, 0.0], h={}, points=ROWS)
    array_type = get_message('visualization_msgs/msg/MarkerArray')
    back = deserialize_message(serialize_message(marker_array(markers)), array_type).markers
    for msg, item in zip(back, markers):
        assert [(p.x, p.y, p.z) for p in msg.points] == item.get('points', [])
        colours = [(c.r, c.g, c.b, c.a) for c in msg.colors]
        np.testing.assert_allclose(np.reshape(colours, (-1, 4)),
                                   np.reshape(item.get('colors', []), (-1, 4)), atol=1e-6)
    assert [len(m.colors) for m in back if m.ns == 'binding_points'] == [len(ROWS)]


# reading filter_info ------------------------------------------------------------------------
def test_info_binding_points_reads_the_section_or_none():
    np.testing.assert_array_equal(info_binding_points(_info(binding_points=ROWS.reshape(-1))),
                                  ROWS)
    assert info_binding_points(_info()).shape == (0, 4)
    assert info_binding_points(sections_to_cdr({'': np.zeros(3)})).shape == (0, 4)


@pytest.mark.parametrize('data, match', [
    (_info(binding_points=np.zeros(5)), 'rows of 4'),
    (_info(binding_points=np.zeros(4 * BINDING_POINTS + 4)), 'rows of 4'),
    (_info(binding_points=np.array([0.0, 1.0, np.nan, 0.0])), 'NaN'),
    (_info(binding_points=np.array([0.0, np.inf, 0.0, 0.0])), 'NaN'),
    (b'\x00\x01\x00\x00' + b'\xff' * 40, 'filter_info'),
    (b'', 'filter_info'),
    (b'\x00' * (MAX_INFO_BYTES + 1), 'more than'),
    ('not bytes', 'CDR bytes'),
    (None, 'CDR bytes'),
])
def test_info_binding_points_refuses_in_one_line(data, match):
    with pytest.raises(ValueError, match=match) as caught:
        info_binding_points(data)
    assert str(caught.value).startswith('filter_info') and '\n' not in str(caught.value)


GOOD = _info(binding_points=ROWS.reshape(-1), state=np.array([0.0, 1.0, 2.0]))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.one_of(
    st.binary(max_size=400),
    st.integers(0, len(GOOD)).map(lambda n: GOOD[:n]),
    st.tuples(st.integers(0, len(GOOD) - 1), st.integers(0, 7)).map(
        lambda ib: GOOD[:ib[0]] + bytes([GOOD[ib[0]] ^ (1 << ib[1])]) + GOOD[ib[0] + 1:]),
    st.tuples(st.integers(4, len(GOOD) - 4), st.binary(min_size=4, max_size=4)).map(
        lambda ib: GOOD[:ib[0]] + ib[1] + GOOD[ib[0] + 4:])))
def test_hostile_filter_info_gives_rows_or_one_line(data):
    try:
        rows = info_binding_points(data)
    except ValueError as exc:
        assert '\n' not in str(exc) and str(exc).startswith('filter_info')
        return
    assert rows.ndim == 2 and rows.shape[1] == 4 and rows.shape[0] <= BINDING_POINTS
    assert np.isfinite(rows).all()


# the node ----------------------------------------------------------------------------------
@pytest.fixture
def scene_node(ros_domain_id, monkeypatch):
    from rcbf_ros.ros import scene_node as module
    from rcbf_ros.ros.dds import rclpy_compat
    rclpy_compat.init(args=['prog', '--ros-args', '--params-file',
                            str(REPO / 'config' / 'unicycle.yaml'), '-p',
                            'footprint.radius:=0.2'], domain_id=ros_domain_id)
    node = module.SceneNode()
    monkeypatch.setattr(module, 'time', SimpleNamespace(monotonic_ns=lambda: 0))  # no clock
    published, warnings = [], []
    monkeypatch.setattr(node._publisher, 'publish', published.append)
    monkeypatch.setattr(node, 'get_logger', lambda: SimpleNamespace(
        warning=warnings.append, error=warnings.append, info=lambda *_: None))
    node.published_arrays, node.warnings = published, warnings
    yield node
    node.destroy_node()
    rclpy_compat.try_shutdown()


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(data=st.one_of(st.binary(max_size=300), st.integers(0, len(GOOD)).map(
    lambda n: GOOD[:n])))
def test_hostile_filter_info_into_the_node_never_raises(scene_node, data):
    """Any bytes on filter_info: the node draws the last good points or none, warns at most
    once a second (the clock stands still here: once), and keeps publishing."""
    scene_node.state = np.array([0.5, 0.0, 0.0])
    scene_node._on_filter_info(GOOD)
    scene_node._on_timer()
    np.testing.assert_array_equal(scene_node.points, ROWS)
    scene_node._on_filter_info(data)
    scene_node._on_timer()
    assert scene_node.points.shape[1] == 4 and np.isfinite(scene_node.points).all()
    drawn = scene_node.points
    scene_node._on_filter_info(b'\x00\x01\x00\x00')  # never a sample: the last points stay
    scene_node._on_timer()
    assert scene_node.points is drawn
    assert len(scene_node.warnings) == 1 and '\n' not in scene_node.warnings[0]
    assert 'filter_info' in scene_node.warnings[0]
    last = scene_node.published_arrays[-1]
    assert {m.ns for m in last.markers} >= {'footprint', 'binding_points', 'active_rows'}



def test_the_foxglove_3d_panel_shows_the_scan_with_the_scene():
    import json
    layout = json.loads((REPO / 'config' / 'foxglove_layout.json').read_text())
    (scene,) = [config for name, config in layout['configById'].items()
                if name.startswith('3D!')]
    assert scene['topics']['/scene_markers']['visible'] and scene['topics']['/scan']['visible']

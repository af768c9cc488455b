"""Observation sources: freshness, frames, counts, and the decision they feed
(rcbf_ros.node_logic.sources; messages encoded by rosbags)."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_messages import cloud_bytes as _cloud_bytes
from sensor_messages import scan_bytes as _scan_bytes

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.messages import sensor
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.sources import ObservationSources

S = 1_000_000_000
_PARAMS = {
    'system': 'unicycle', 'alpha': 2.0, 'input_weight': [1.0, 0.01],
    'input_limits.min': [-2.5, -2.5], 'input_limits.max': [2.5, 2.5],
    'obstacles.x': [0.0], 'obstacles.y': [40.0], 'obstacles.radius': [0.5],
    'obstacles.margin': 0.1, 'obstacles.lookahead': 0.03, 'obstacles.heading_index': 2,
    'obstacles.speed_input': 0, 'footprint.radius': 0.2,
    'observation_sources': ['front', 'cloud'],
    'front.type': 'scan', 'front.topic': 'scan', 'front.timeout_s': 0.5,
    'cloud.type': 'pointcloud', 'cloud.topic': 'points', 'cloud.timeout_s': 1.0,
    'cloud.min_height': 0.0, 'cloud.max_height': 1.0,
}


def _sources(**changes):
    params = dict(_PARAMS)
    params.update(changes)
    config = filter_config_from_params(params)
    return config, ObservationSources(config.sources)


def _scan(ranges, frame_id='base_link', sec=10, **kwargs):
    data = bytearray(_scan_bytes(ranges, frame_id=frame_id, **kwargs))
    # the stamp: rosbags encodes the header written by the helper (sec 12); set ours
    data[4:8] = int(sec).to_bytes(4, 'little', signed=True)
    data[8:12] = (0).to_bytes(4, 'little')
    return bytes(data)


def _cloud(points, frame_id='odom', sec=10):
    data = bytearray(_cloud_bytes(np.asarray(points, dtype=np.float64), frame_id=frame_id))
    data[4:8] = int(sec).to_bytes(4, 'little', signed=True)
    data[8:12] = (0).to_bytes(4, 'little')
    return bytes(data)


def test_points_in_the_robot_frame_go_through_the_pose():
    _, sources = _sources()
    assert sources.read('front', _scan([2.0], angle_min=0.5), received_ns=0) == ''
    assert sources.read('cloud', _cloud([[3.0, 4.0, 0.5], [1.0, 1.0, 5.0]]),
                        received_ns=0) == ''
    state = np.array([1.0, -2.0, math.pi / 2])
    assert sources.note_state(state, stamp_ns=10 * S) == ''  # the pose at the scan's stamp
    points, spread = sources.points(state, now_ns=0, stamp_now_ns=10 * S)
    beam = np.float32(0.5)
    expected_scan = [1.0 - 2.0 * math.sin(beam), -2.0 + 2.0 * math.cos(beam)]
    np.testing.assert_allclose(points, [expected_scan, [3.0, 4.0]], atol=1e-6)
    assert spread == 0.0


@pytest.mark.parametrize(('setup', 'words'), [
    ('none', 'source front: no message yet on scan'),
    ('old', 'source front: latest message 0.600 s old > front.timeout_s 0.5'),
    ('late', 'source front: latest message 0.700 s old'),
    ('frame', "source front: frame 'laser' is placed neither in the state's 'odom' nor in the "
              "robot's 'base_link' by tf (no transform from 'laser' to 'odom'"),
    ('refused', 'source front: latest message refused: sensor_msgs/msg/LaserScan: range_min'),
])
def test_a_source_that_cannot_be_used_gives_a_reason_naming_it(setup, words):
    _, sources = _sources()
    sources.read('cloud', _cloud([[1.0, 1.0, 0.5]], sec=10), received_ns=0)
    if setup == 'old':
        sources.read('front', _scan([1.0], sec=10), received_ns=0)
        now, stamp_now = 0, 10 * S + 600_000_000
    elif setup == 'late':  # the stamp is fresh; received long ago on the monotonic clock
        sources.read('front', _scan([1.0], sec=10), received_ns=0)
        now, stamp_now = 700_000_000, 10 * S
    elif setup == 'frame':
        sources.read('front', _scan([1.0], frame_id='laser'), received_ns=0)
        now, stamp_now = 0, 10 * S
    elif setup == 'refused':
        sources.read('front', _scan([1.0]), received_ns=0)
        sources.read('front', _scan([1.0], range_min=math.nan), received_ns=0)
        now, stamp_now = 0, 10 * S
    else:
        now, stamp_now = 0, 10 * S
    reason = sources.points(np.zeros(3), now_ns=now, stamp_now_ns=stamp_now)
    assert isinstance(reason, str) and reason.startswith(words), reason
    counts = sources.counts()['front']
    assert counts['stale'] == (1 if setup in ('none', 'old', 'late') else 0)
    assert counts['refused'] == (1 if setup == 'refused' else 0)
    assert counts['untransformed'] == (1 if setup == 'frame' else 0)


def test_a_good_message_after_a_refused_one_clears_the_refusal():
    _, sources = _sources()
    sources.read('cloud', _cloud([[1.0, 1.0, 0.5]]), received_ns=0)
    sources.read('front', b'\x00\x01\x00\x00garbage', received_ns=0)
    sources.note_state(np.zeros(3), stamp_ns=10 * S)
    assert isinstance(sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S), str)
    sources.read('front', _scan([1.0]), received_ns=0)
    assert not isinstance(sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S), str)
    assert sources.counts()['front'] == {'messages': 2, 'refused': 1, 'stale': 0,
                                              'untransformed': 0}


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=300), name=st.sampled_from(['front', 'cloud']))
def test_hostile_bytes_never_raise_and_give_a_reason(data, name):
    _, sources = _sources()
    reason = sources.read(name, b'\x00\x01\x00\x00' + data, received_ns=0)
    out = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=0)
    assert isinstance(out, str) and '\n' not in out and '\n' not in reason


def test_a_scan_of_a_wall_ahead_slows_the_decision_and_a_stale_one_stops_it():
    config, sources = _sources(observation_sources=['front'])
    active = logic.build_safety_filter(config=config,
                                       settings=logic.node_settings_from_params({}))
    state = logic.StateSample(received_ns=0, state=np.array([0.0, 0.0, 0.0]), error='')
    proposal = logic.Proposal(u=np.array([2.0, 0.0]))
    angles = np.linspace(-0.5, 0.5, 101)
    sources.read('front', _scan(0.8 / np.cos(angles), angle_min=-0.5, increment=0.01),
                 received_ns=0)
    sources.note_state(state.state, stamp_ns=10 * S)

    def decide(stamp_now_ns):
        return logic.decide(
            safety_filter=active, proposal=proposal, latest_state=state, now_ns=0,
            max_state_age_s=1.0, sense=lambda x: sources.sense(
                active, x, now_ns=0, stamp_now_ns=stamp_now_ns))

    fresh = decide(10 * S)
    assert not fresh.fail_safe and fresh.u_safe[0] < 1.0, fresh.reason
    stale = decide(11 * S)
    assert stale.fail_safe and stale.reason.startswith('source front: latest message')
    assert filter_edge.status_code(stale) == STATUS_CODES['source unusable'] == 17
    assert active.point_count == 0
    assert sensor.MAX_POINTS >= 100_000


@pytest.mark.parametrize('x', [0.0, 10_001.0, 250_000.0])
def test_a_cloud_in_odom_slows_the_robot_however_far_it_is_from_the_origin(x):
    config, sources = _sources(observation_sources=['cloud'])
    active = logic.build_safety_filter(config=config,
                                       settings=logic.node_settings_from_params({}))
    wall = [[x + 0.5, y, 0.2] for y in np.linspace(-0.5, 0.5, 21)]
    assert sources.read('cloud', _cloud(wall, frame_id='odom'), received_ns=0) == ''
    decision = logic.decide(
        safety_filter=active, proposal=logic.Proposal(u=np.array([2.5, 0.0])),
        latest_state=logic.StateSample(received_ns=0, state=np.array([x, 0.0, 0.0]), error=''),
        now_ns=0, max_state_age_s=1.0,
        sense=lambda state: sources.sense(active, state, now_ns=0, stamp_now_ns=10 * S))
    assert not decision.fail_safe and decision.u_safe[0] < 1.0, decision.reason
    assert active.point_count == 21


def test_points_are_bounded_by_their_distance_from_the_robot_not_the_origin():
    from rcbf_ros.node_logic.sources import MAX_RANGE
    _, sources = _sources(observation_sources=['cloud'])
    far = [[MAX_RANGE + 1.0, 0.0, 0.2], [5.0, 0.0, 0.2], [-MAX_RANGE, 3.0, 0.2]]
    assert sources.read('cloud', _cloud(far, frame_id='odom'), received_ns=0) == ''
    points, _ = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    np.testing.assert_allclose(points, [[5.0, 0.0]])  # (-1e4, 3) is 1e4 + 4.5e-4 m away
    points, _ = sources.points(np.array([MAX_RANGE, 0.0, 0.0]), now_ns=0,
                               stamp_now_ns=10 * S)
    np.testing.assert_allclose(points, [[MAX_RANGE + 1.0, 0.0], [5.0, 0.0]])


def test_more_points_than_the_bound_over_all_sources_give_the_fail_safe_naming_them(
        monkeypatch):
    from rcbf_ros.node_logic import sources as module
    monkeypatch.setattr(module, 'MAX_POINTS', 10)
    _, sources = _sources()
    sources.read('front', _scan(np.ones(6)), received_ns=0)
    sources.read('cloud', _cloud([[1.0, k, 0.5] for k in range(4)]), received_ns=0)
    sources.note_state(np.zeros(3), stamp_ns=10 * S)
    points, _ = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert len(points) == 10
    sources.read('cloud', _cloud([[1.0, k, 0.5] for k in range(5)]), received_ns=0)
    reason = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert reason == ('sources front (6 points), cloud (5 points): 11 points in all, more '
                      'than the bound 10')


_SCAN_ONLY = {key: value for key, value in _PARAMS.items()
              if key not in ('obstacles.x', 'obstacles.y', 'obstacles.radius')}
"""A robot with a lidar and no static obstacle: no family but the scan's points."""


def _rows_at(config, points: np.ndarray, state, u) -> np.ndarray:
    """The oracle: every point's RCBF row at the command u, from the autograd assembly of a
    problem holding the points as a static circle family (the filter never takes it)."""
    from point_oracle import point_family
    import torch

    from rcbf_ros.core.rcbf import RCBFProblem
    problem = RCBFProblem(system=config.problem.system,
                          families=(point_family(config, points),),
                          alpha=config.problem.alpha, use_input_limits=False)
    qp = problem.qp(torch.tensor([state], dtype=torch.float64),
                    torch.tensor([u], dtype=torch.float64))
    return qp.h[0].numpy()  # G z <= h at z = 0 (u_S = 0, no slack): each row's value


@pytest.mark.parametrize('params', ['inline', 'unicycle.yaml'])
def test_a_scan_only_filter_builds_and_slows_down_before_a_wall(params):
    if params == 'inline':
        params = dict(_SCAN_ONLY, observation_sources=['front'])
    else:  # the shipped config without any static obstacle, with one source
        from pathlib import Path

        from rcbf_ros.parameters.rules import load_params
        params = load_params(Path(__file__).parents[2] / 'config' / 'unicycle.yaml',
                             'safety_filter')
        params = {key: value for key, value in params.items()
                  if not key.startswith(('obstacles.x', 'obstacles.y', 'obstacles.radius'))}
        params.update({'observation_sources': ['front'], 'front.type': 'scan',
                       'front.topic': 'scan', 'front.timeout_s': 0.5,
                       'footprint.radius': 0.2})
    config = filter_config_from_params(params)
    assert config.problem.families == ()
    sources = ObservationSources(config.sources)
    active = logic.build_safety_filter(config=config,
                                       settings=logic.node_settings_from_params({}))
    assert active.barrier_names == ['sensor_points']
    state = logic.StateSample(received_ns=0, state=np.array([0.0, 0.0, 0.0]), error='')
    sources.note_state(state.state, stamp_ns=10 * S)  # the robot's pose at the scans' stamp
    proposal = logic.Proposal(u=np.array([2.0, 0.0]))

    def decide():
        return logic.decide(
            safety_filter=active, proposal=proposal, latest_state=state, now_ns=0,
            max_state_age_s=1.0, sense=lambda x: sources.sense(
                active, x, now_ns=0, stamp_now_ns=10 * S))

    before = decide()  # no scan yet: the source's fail-safe, as with static families
    assert before.fail_safe and before.reason.startswith('source front: no message yet')
    sources.read('front', _scan([math.inf] * 50, angle_min=-0.5, increment=0.02),
                 received_ns=0)
    open_space = decide()  # a scan without a point in range: nothing to avoid
    assert not open_space.fail_safe and open_space.u_safe.tolist() == [2.0, 0.0]
    angles = np.linspace(-0.5, 0.5, 101)
    sources.read('front', _scan(0.8 / np.cos(angles), angle_min=-0.5, increment=0.01),
                 received_ns=0)
    wall = decide()
    assert not wall.fail_safe and 0.0 < wall.u_safe[0] < 1.0, wall.reason
    points = sources.points(state.state, now_ns=0, stamp_now_ns=10 * S)[0]
    assert len(points) == 101
    rows = _rows_at(config, points, state.state.tolist(), wall.u_safe.tolist())
    assert rows.min() >= -1e-5  # every point's row holds (up to the QP's slack tolerance)
    assert _rows_at(config, points, state.state.tolist(), [2.0, 0.0]).min() < 0


def test_without_static_family_or_source_the_config_is_refused():
    with pytest.raises(ValueError, match='^barriers: .*observation_sources'):
        filter_config_from_params(dict(_SCAN_ONLY, observation_sources=[]))


_OWN_TOPICS = ('state', 'cmd_proposed', 'cmd_safe', 'filter_info', 'diagnostics', 'obstacles')


def _resolver(namespace: str = '/', remaps: dict | None = None):
    """A node's resolve_topic_name in ``namespace`` with ``remaps`` (the dds layer's)."""
    from rcbf_ros.parameters.arguments import RemapRule, resolve_topic_name
    rules = [RemapRule(match, replacement) for match, replacement in (remaps or {}).items()]
    return lambda topic: resolve_topic_name(topic, 'safety_filter', namespace, rules)


@pytest.mark.parametrize('own', [*_OWN_TOPICS, '/diagnostics', '/cmd_safe', '/rosout',
                                 'parameter_events', 'tf', '/tf_static',
                                 '/safety_filter/describe_parameters', '~/list_parameters',
                                 '~/get_parameter_types', '~/get_type_description'])
def test_a_source_on_one_of_the_node_topics_is_refused_naming_both(own):
    from rcbf_ros.node_logic.sources import topic_refusal
    config, _ = _sources(**{'front.topic': own})
    why = topic_refusal(config.sources, _OWN_TOPICS, _resolver())
    assert why.startswith('front.topic: ') and "the node's own" in why and '\n' not in why


def test_names_are_compared_as_the_node_resolves_them():
    from rcbf_ros.node_logic.sources import topic_refusal
    config, _ = _sources(**{'front.topic': 'scan', 'cloud.topic': '/scan'})
    assert topic_refusal(config.sources, _OWN_TOPICS, _resolver()).startswith(
        "cloud.topic: '/scan' resolves to /scan, the topic of front.topic")
    config, _ = _sources(**{'front.topic': 'scan', 'cloud.topic': '/scan'})
    assert topic_refusal(config.sources, _OWN_TOPICS, _resolver('/robot')) == ''
    config, _ = _sources(**{'front.topic': '/robot/state'})
    assert topic_refusal(config.sources, _OWN_TOPICS, _resolver('/robot')).startswith(
        'front.topic: ')
    config, _ = _sources(**{'front.topic': 'lidar'})
    assert 'own state topic' in topic_refusal(config.sources, _OWN_TOPICS,
                                              _resolver(remaps={'lidar': 'state'}))
    assert 'own cmd_safe topic' in topic_refusal(config.sources, _OWN_TOPICS,
                                                 _resolver(remaps={'cmd_safe': '/lidar'}))


@pytest.mark.parametrize('topic', ['scan', '/scan', 'front/scan', '/a/b'])
def test_distinct_topics_pass(topic):
    from rcbf_ros.node_logic.sources import topic_refusal
    config, _ = _sources(**{'front.topic': topic})
    assert topic_refusal(config.sources, _OWN_TOPICS, _resolver()) == ''


def test_a_topic_name_the_runtime_refuses_is_refused_in_one_line():
    from rcbf_ros.node_logic.sources import topic_refusal
    config, _ = _sources(**{'front.topic': 'bad name!'})
    why = topic_refusal(config.sources, _OWN_TOPICS, _resolver())
    assert why.startswith("front.topic: 'bad name!' is not a valid topic name") and '\n' not in why


@pytest.mark.parametrize('frame, refusal', [('', None), ('odom', None), ('map', 'map')])
def test_the_state_frame_with_sources_is_odom_frame_id_in_the_node_and_the_refilter(frame,
                                                                                   refusal):
    from rcbf_ros.bag.refilter import build_filter, RefilterError
    params = dict(_PARAMS, state_type='odometry', state_frame_id=frame)
    if refusal:
        with pytest.raises(ValueError, match="^state_frame_id: 'map' is not odom_frame_id"):
            logic.build_active_filter(params=params)
        with pytest.raises(RefilterError, match="^params: state_frame_id: 'map' is not"):
            build_filter(params)
        return
    assert logic.build_active_filter(params=params).settings.state_frame_id == 'odom'
    assert build_filter(params)[1].state_frame_id == 'odom'
    without = {k: v for k, v in params.items() if k != 'observation_sources'}
    assert logic.build_active_filter(params=without).settings.state_frame_id == frame

"""Observation sources through tf (rcbf_ros.node_logic.sources with /tf and /tf_static):
points of a frame other than the state's placed at the message's stamp, against closed forms;
a transform missing or too old gives the fail-safe naming both frames."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_messages import scan_bytes
from tf_messages import tf_bytes, transform_stamped, yaw_quaternion

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.sources import ObservationSources

S = 1_000_000_000
_PARAMS = {
    'system': 'unicycle', 'alpha': 2.0, 'input_weight': [1.0, 0.01],
    'input_limits.min': [-2.5, -2.5], 'input_limits.max': [2.5, 2.5],
    'obstacles.margin': 0.1, 'obstacles.lookahead': 0.03, 'obstacles.heading_index': 2,
    'obstacles.speed_input': 0, 'footprint.radius': 0.2,
    'observation_sources': ['front'],
    'front.type': 'scan', 'front.topic': 'scan', 'front.timeout_s': 0.5,
}
MOUNT = (0.3, -0.1, 0.25), 0.4
"""The laser on base_link: (x, y, z) and yaw."""


def _sources(**changes):
    config = filter_config_from_params(dict(_PARAMS, **changes))
    return config, ObservationSources(config.sources)


def _scan(ranges, *, frame_id='laser', stamp_ns=10 * S, **kwargs):
    data = bytearray(scan_bytes(ranges, frame_id=frame_id, **kwargs))
    sec, nanosec = divmod(stamp_ns, S)
    data[4:8] = int(sec).to_bytes(4, 'little', signed=True)
    data[8:12] = int(nanosec).to_bytes(4, 'little')
    return bytes(data)


def _mount(sources):
    (x, y, z), yaw = MOUNT
    assert sources.read_tf(tf_bytes(transform_stamped(
        'base_link', 'laser', translation=(x, y, z), rotation=yaw_quaternion(yaw))),
        static=True) == ''


def _odom(sources, stamp_ns, x, y, yaw):
    return sources.read_tf(tf_bytes(transform_stamped(
        'odom', 'base_link', stamp_ns=stamp_ns, translation=(x, y, 0.0),
        rotation=yaw_quaternion(yaw))), static=False)


def _decide_at_the_origin(config, sources, *, stamp_now_ns):
    """The decision on 2 m/s ahead at the state 0 with the sources' points."""
    active = logic.build_safety_filter(config=config,
                                       settings=logic.node_settings_from_params({}))
    return logic.decide(
        safety_filter=active, proposal=logic.Proposal(u=np.array([2.0, 0.0])),
        latest_state=logic.StateSample(received_ns=0, state=np.zeros(3), error=''), now_ns=0,
        max_state_age_s=1.0,
        sense=lambda x: sources.sense(active, x, now_ns=0, stamp_now_ns=stamp_now_ns))


def _expected(beam_ranges, angles, pose):
    """Closed form: beam (r, a) of the laser, mounted at MOUNT on a base at pose (x, y, yaw)."""
    (mx, my, _), mount_yaw = MOUNT
    x, y, yaw = pose
    out = []
    for r, a in zip(beam_ranges, angles):
        bx = mx + r * math.cos(mount_yaw + a)  # in base_link
        by = my + r * math.sin(mount_yaw + a)
        out.append((x + bx * math.cos(yaw) - by * math.sin(yaw),
                    y + bx * math.sin(yaw) + by * math.cos(yaw)))
    return np.array(out)


def test_a_laser_on_the_base_lands_where_the_closed_form_puts_it():
    _, sources = _sources()
    _mount(sources)
    assert _odom(sources, 9 * S, 1.0, 2.0, 0.2) == ''
    assert _odom(sources, 11 * S, 3.0, 0.0, 0.6) == ''
    assert sources.read('front', _scan([1.0, 2.0, 0.5], angle_min=-0.2, increment=0.1,
                                       stamp_ns=10 * S), received_ns=0) == ''
    # the state's pose is elsewhere: tf places the points at the scan's stamp (10 s: the
    # midpoint of the two odom samples, x 2, y 1, yaw 0.4)
    points, spread = sources.points(np.array([50.0, 50.0, 0.0]), now_ns=0,
                                    stamp_now_ns=10 * S)
    beams = [np.float32(-0.2) + k * np.float32(0.1) for k in range(3)]
    np.testing.assert_allclose(points, _expected([1.0, 2.0, 0.5], beams, (2.0, 1.0, 0.4)),
                               atol=1e-6)
    assert spread == 0.0


def test_without_odom_on_tf_the_mount_and_the_state_pose_place_the_points():
    _, sources = _sources()
    _mount(sources)  # only base_link -> laser: the robot's pose comes from the state
    sources.read('front', _scan([2.0], angle_min=0.0), received_ns=0)
    sources.note_state(np.array([1.0, -1.0, math.pi / 2]), stamp_ns=10 * S)
    points, _ = sources.points(np.array([1.0, -1.0, math.pi / 2]), now_ns=0,
                               stamp_now_ns=10 * S)
    np.testing.assert_allclose(points, _expected([2.0], [0.0], (1.0, -1.0, math.pi / 2)),
                               atol=1e-6)


def test_base_link_points_follow_tf_when_it_has_odom_to_base_link_else_the_state():
    _, sources = _sources()
    sources.read('front', _scan([1.0], frame_id='base_link', angle_min=0.0), received_ns=0)
    state = np.array([5.0, 5.0, 0.0])
    sources.note_state(state, stamp_ns=10 * S)
    without, _ = sources.points(state, now_ns=0, stamp_now_ns=10 * S)
    np.testing.assert_allclose(without, [[6.0, 5.0]], atol=1e-6)
    _odom(sources, 10 * S, -1.0, 0.0, math.pi)
    with_tf, _ = sources.points(state, now_ns=0, stamp_now_ns=10 * S)
    np.testing.assert_allclose(with_tf, [[-2.0, 0.0]], atol=1e-6)


@pytest.mark.parametrize(('odom_stamp', 'words'), [
    (9 * S, "source front: no transform from 'laser' to 'odom' at 10.000 s: 'odom' -> "
            "'base_link' too old: its newest is at 9.000 s, 1.000 s before (tolerance "
            '0.100 s)'),
    (10 * S + 200_000_000, "'odom' -> 'base_link' too new: its oldest is at 10.200 s"),
])
def test_a_stale_transform_gives_the_fail_safe_naming_both_frames(odom_stamp, words):
    config, sources = _sources()
    _mount(sources)
    _odom(sources, odom_stamp, 0.0, 0.0, 0.0)
    sources.read('front', _scan(np.full(20, 0.5), angle_min=-0.2, increment=0.02),
                 received_ns=0)
    reason = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert isinstance(reason, str) and words in reason, reason
    assert sources.counts()['front']['untransformed'] == 1
    decision = _decide_at_the_origin(config, sources, stamp_now_ns=10 * S)
    assert decision.fail_safe and words in decision.reason
    assert filter_edge.status_code(decision) == STATUS_CODES['source unusable']


def test_transform_tolerance_holds_the_newest_sample_that_long():
    _, sources = _sources(transform_tolerance=0.5)
    _mount(sources)
    _odom(sources, 9 * S + 600_000_000, 1.0, 0.0, 0.0)
    sources.read('front', _scan([1.0], angle_min=0.0), received_ns=0)
    out = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert not isinstance(out, str), out
    np.testing.assert_allclose(out[0], _expected([1.0], [0.0], (1.0, 0.0, 0.0)), atol=1e-6)


def test_refused_tf_messages_and_transforms_are_counted_and_said_in_one_line():
    _, sources = _sources()
    why = sources.read_tf(tf_bytes(
        transform_stamped('odom', 'base_link', rotation=(0, 0, 0, 0)),
        transform_stamped('base_link', 'laser', translation=(math.nan, 0, 0)),
        transform_stamped('base_link', 'ok')), static=False)
    assert why.startswith("transforms[0] 'odom' -> 'base_link': rotation (0, 0, 0, 0) is not "
                          'a unit quaternion') and why.endswith('(and 1 more)'), why
    assert sources.read_tf(b'\x00\x01\x00\x00\xff', static=True).startswith(
        'tf2_msgs/msg/TFMessage: transforms')
    assert sources.tf_counts == {'messages': 2, 'refused': 1, 'transforms_refused': 2}
    assert sources.tf.frames == {'base_link', 'ok'}


def test_transform_tolerance_is_bounded():
    with pytest.raises(ValueError, match='transform_tolerance'):
        filter_config_from_params(dict(_PARAMS, transform_tolerance=11.0))
    with pytest.raises(ValueError, match='transform_tolerance'):
        filter_config_from_params(dict(_PARAMS, transform_tolerance=-0.1))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.lists(st.binary(max_size=120), max_size=4), static=st.booleans(),
       frame=st.sampled_from(['laser', 'base_link', 'odom', 'x']))
def test_hostile_tf_bytes_never_raise_and_leave_a_reason_or_points(data, static, frame):
    _, sources = _sources()
    _mount(sources)
    for chunk in data:
        why = sources.read_tf(b'\x00\x01\x00\x00' + chunk, static=static)
        assert '\n' not in why
    sources.read('front', _scan([1.0], frame_id=frame), received_ns=0)
    out = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert (isinstance(out, str) and '\n' not in out) or np.all(np.isfinite(out[0]))


_CLOUD = {'observation_sources': ['cloud'], 'cloud.type': 'pointcloud', 'cloud.topic': 'points',
          'cloud.timeout_s': 1.0, 'cloud.min_height': -0.2, 'cloud.max_height': 0.4}


def _cloud(points, *, frame_id='camera', stamp_ns=10 * S):
    from sensor_messages import cloud_bytes
    data = bytearray(cloud_bytes(np.asarray(points, dtype=np.float64), frame_id=frame_id))
    sec, nanosec = divmod(stamp_ns, S)
    data[4:8] = int(sec).to_bytes(4, 'little', signed=True)
    data[8:12] = int(nanosec).to_bytes(4, 'little')
    return bytes(data)


@pytest.mark.parametrize('pitch', [0.0, 0.3, -0.7])
def test_a_cloud_in_a_tilted_frame_is_widened_to_cover_every_point(pitch):
    # camera on base_link at (0.2, 0, 0.5), pitched about y and turned 0.25 rad: each point is
    # placed at z = 0 of its frame, within |z| sin(tilt) of the true 3-D point (scipy's
    # Rotation is the oracle of the true point)
    from scipy.spatial.transform import Rotation
    _, sources = _sources(**_CLOUD)
    mount = Rotation.from_euler('ZY', [0.25, pitch])
    assert sources.read_tf(tf_bytes(transform_stamped(
        'base_link', 'camera', translation=(0.2, 0.0, 0.5), rotation=mount.as_quat())),
        static=True) == ''
    assert _odom(sources, 10 * S, 1.0, -1.0, 0.5) == ''
    points = np.array([[1.0, 0.5, 0.35], [2.0, -1.0, -0.15], [0.5, 0.0, 0.1], [3.0, 3.0, 0.0]])
    assert sources.read('cloud', _cloud(points), received_ns=0) == ''
    placed, spread = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    base = Rotation.from_euler('Z', 0.5)
    true = base.apply(mount.apply(points) + [0.2, 0.0, 0.5]) + [1.0, -1.0, 0.0]
    assert spread == pytest.approx(0.4 * abs(math.sin(pitch)), abs=1e-12)
    distance = np.hypot(*(placed - true[:, :2]).T)
    assert np.all(distance <= spread + 1e-6), (distance, spread)
    # each point is off by its own |z| sin(tilt): the band's bound covers the highest
    np.testing.assert_allclose(distance, np.abs(points[:, 2]) * abs(math.sin(pitch)),
                               atol=1e-6)


def test_a_cloud_frame_too_tilted_for_its_band_is_refused_naming_it():
    _, sources = _sources(**dict(_CLOUD, **{'cloud.max_height': 2.0}))
    assert sources.read_tf(tf_bytes(transform_stamped(
        'base_link', 'camera', rotation=(0.0, math.sin(0.4), 0.0, math.cos(0.4)))),
        static=True) == ''  # pitched 0.8 rad: 2 m x sin(0.8) > 0.5 m
    sources.read('cloud', _cloud([[1.0, 0.0, 0.1]]), received_ns=0)
    reason = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S)
    assert reason == ("source cloud: frame 'camera' is tilted 45.8 deg from 'base_link''s "
                      'vertical: its points, up to 2 m high (cloud.min_height, .max_height), '
                      'would lie up to 1.43 m from where they are placed (at most 0.5)')


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ranges=st.lists(st.floats(-2e4, 2e4, width=32) | st.sampled_from([math.inf, math.nan]),
                       min_size=1, max_size=30),
       range_min=st.sampled_from([0.0, 0.05, -3e4]),
       range_max=st.sampled_from([10.0, 600.0, 3e4, math.inf]),
       position=st.tuples(st.floats(-1e20, 1e20), st.floats(-1e20, 1e20))
       | st.tuples(st.floats(-50.0, 50.0), st.floats(-50.0, 50.0)),
       yaw=st.floats(-4.0, 4.0), frame=st.sampled_from(['laser', 'base_link']))
def test_points_placed_through_the_robot_frame_are_those_the_range_test_keeps(
        ranges, range_min, range_max, position, yaw, frame):
    """A scan placed through the robot's frame skips the per-point range test where its
    largest range bounds the points near the robot: the same points, bit for bit, as the
    test gives (far ranges, negative ones, far positions included)."""
    from rcbf_ros.node_logic import sources as module
    _, sources = _sources()
    _mount(sources)  # laser -> base_link only: the pose comes from the state
    assert sources.read('front', _scan(ranges, frame_id=frame, range_min=range_min,
                                       range_max=range_max), received_ns=0) == ''
    state = np.array([*position, yaw])
    kept = sources.points(state, now_ns=0, stamp_now_ns=10 * S)
    skip = module._NEAR_REACH
    try:
        module._NEAR_REACH = -math.inf  # every point through the range test
        tested = sources.points(state, now_ns=0, stamp_now_ns=10 * S)
    finally:
        module._NEAR_REACH = skip
    assert type(kept) is type(tested)
    if isinstance(kept, str):
        assert kept == tested
        return
    assert kept[0].shape == tested[0].shape
    assert kept[0].tobytes() == tested[0].tobytes()
    assert kept[1] == tested[1]
    if max(map(abs, position)) <= 1e6:  # the range itself, where rounding is far below it
        from rcbf_ros.node_logic.sources import MAX_RANGE
        beams = np.asarray(ranges, np.float32).astype(np.float64)
        valid = beams[(beams >= max(np.float32(range_min), 0.0))  # REP 117: r >= 0
                      & (beams <= np.float32(range_max)) & np.isfinite(beams)]
        distance = np.hypot(*(kept[0] - position).T)
        assert (distance <= MAX_RANGE * (1 + 1e-9)).all()
        mounted = 1.0 if frame == 'laser' else 1e-6  # the mount's offset, or rounding
        assert len(distance) >= np.count_nonzero(np.abs(valid) <= MAX_RANGE - mounted)
        assert len(distance) <= np.count_nonzero(np.abs(valid) <= MAX_RANGE + mounted)


def test_without_odom_on_tf_a_scan_is_placed_with_the_pose_at_its_stamp():
    """A robot turning from yaw -1 to 0 in 0.5 s, its scan taken at the start: the points lie
    where the robot saw them (the pose at the scan's stamp), not turned with the robot; a
    stamp between two states takes the pose interpolated between them."""
    _, sources = _sources()
    sources.read('front', _scan([1.5], frame_id='base_link', angle_min=0.0,
                                stamp_ns=10 * S), received_ns=0)
    assert sources.note_state(np.array([0.0, 0.0, -1.0]), stamp_ns=10 * S) == ''
    now = np.array([0.2, 0.0, 0.0])
    assert sources.note_state(now, stamp_ns=10 * S + S // 2) == ''
    points, _ = sources.points(now, now_ns=0, stamp_now_ns=10 * S + S // 2)
    np.testing.assert_allclose(points, [[1.5 * math.cos(-1.0), 1.5 * math.sin(-1.0)]],
                               atol=1e-9)
    sources.read('front', _scan([1.5], frame_id='base_link', angle_min=0.0,
                                stamp_ns=10 * S + S // 4), received_ns=0)
    points, _ = sources.points(now, now_ns=0, stamp_now_ns=10 * S + S // 2)
    np.testing.assert_allclose(points, [[0.1 + 1.5 * math.cos(-0.5), 1.5 * math.sin(-0.5)]],
                               atol=1e-9)


@pytest.mark.parametrize(('state_stamp', 'words'), [
    (None, 'no state yet'),
    (10 * S - S // 2, 'the newest state is 0.500 s older than the message (tolerance 0.100 s)'),
    (10 * S + S // 2, 'the oldest state kept is 0.500 s newer than the message'),
])
def test_without_a_pose_near_the_scans_stamp_the_fail_safe_says_so(state_stamp, words):
    config, sources = _sources()
    sources.read('front', _scan([1.0], frame_id='base_link', angle_min=0.0), received_ns=0)
    if state_stamp is not None:
        sources.note_state(np.zeros(3), stamp_ns=state_stamp)
    reason = sources.points(np.zeros(3), now_ns=0, stamp_now_ns=10 * S + S // 2)
    assert isinstance(reason, str) and reason.startswith(
        "source front: no pose of the robot ('base_link' in 'odom') at the message's stamp "
        'from the states: ' + words), reason
    assert config.sources.transform_tolerance == 0.1
    decision = _decide_at_the_origin(config, sources, stamp_now_ns=10 * S + S // 2)
    assert decision.fail_safe and decision.reason == reason


def test_the_answer_rules_give_the_sources_each_states_pose_at_its_stamp():
    """An Odometry's header stamp, or for an array state its receipt on the stamp clock."""
    from rcbf_ros.node_logic.answer_rules import AnswerRules
    _, sources = _sources()
    clock = [7 * S]
    rules = AnswerRules(sources, stamp_clock=lambda: clock[0])
    rules.latest_state = logic.StateSample(received_ns=1, state=np.array([1.0, 2.0, 0.5]),
                                           stamp_ns=5 * S)
    rules.latest_state = logic.StateSample(received_ns=2, state=np.array([3.0, 2.0, 0.5]))
    rules.latest_state = logic.StateSample(received_ns=3, state=None, error='bad')
    assert sources.poses.at(5 * S, tolerance_ns=0) == (1.0, 2.0, 0.5)
    assert sources.poses.at(6 * S, tolerance_ns=0) == (2.0, 2.0, 0.5)
    assert sources.poses.at(7 * S, tolerance_ns=0) == (3.0, 2.0, 0.5)
    assert len(sources.poses) == 2


@pytest.mark.parametrize('stamp', [0, 200 * S])
def test_an_odometry_stamp_unset_or_on_another_clock_is_taken_at_its_receipt(stamp):
    """A driver leaving the stamp at 0, or a base stamping on its boot clock: the pose is
    kept at the state's receipt on the node's clock, as the scans' stamps are aged on it."""
    from rcbf_ros.node_logic.answer_rules import AnswerRules
    _, sources = _sources()
    rules = AnswerRules(sources, stamp_clock=lambda: 10 * S)
    rules.latest_state = logic.StateSample(received_ns=1, state=np.array([1.0, 2.0, 0.5]),
                                           stamp_ns=stamp)
    assert sources.poses.at(10 * S, tolerance_ns=0) == (1.0, 2.0, 0.5)


def test_a_proposals_own_state_is_a_pose_at_its_receipt_among_the_state_messages():
    """The decision takes a proposal's own state as the robot's at the proposal's receipt:
    that is where its pose goes, in order beside the poses of the state messages."""
    from rcbf_ros.node_logic.answer_rules import AnswerRules
    from rcbf_ros.node_logic.filter_edge import ProposalSample
    _, sources = _sources()
    active = logic.build_active_filter(params=_PARAMS)
    clock = [10 * S]
    rules = AnswerRules(sources, stamp_clock=lambda: clock[0])

    def propose(x):
        sample = ProposalSample(proposal=logic.Proposal(u=np.array([0.5, 0.0]),
                                                        state=np.array([x, 0.0, 0.0])))
        rules.propose(sample, now_ns=clock[0], active=active)
    propose(1.0)
    clock[0] = 12 * S
    rules.latest_state = logic.StateSample(received_ns=2, state=np.array([2.0, 0.0, 0.0]),
                                           stamp_ns=11 * S)
    propose(3.0)
    assert len(sources.poses) == 3 and sources.poses.clears == 0
    assert [sources.poses.at(k * S, tolerance_ns=0)[0] for k in (10, 11, 12)] == [1.0, 2.0, 3.0]

"""The transform buffer (rcbf_ros.node_logic.tf_buffer) against closed forms, against scipy's
Rotation and Slerp (a second implementation), and as Hypothesis properties."""
from __future__ import annotations

import math

from hypothesis import assume, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp
from tf_messages import yaw_quaternion

from rcbf_ros.messages.tf import StampedTransform
from rcbf_ros.node_logic import tf_buffer
from rcbf_ros.node_logic.tf_buffer import NoTransform, Rigid, TransformBuffer

S = 1_000_000_000


def _t(parent, child, stamp_ns=0, translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0)):
    return StampedTransform(parent, child, stamp_ns, tuple(translation), tuple(rotation))


def _buffer(*transforms, static=False):
    buffer = TransformBuffer()
    for transform in transforms:
        assert buffer.set_transform(transform, static=static) == ''
    return buffer


def _points(rigid: Rigid, points) -> np.ndarray:
    """(N, 3) points through ``rigid`` by its matrix."""
    return np.asarray(points) @ rigid.matrix().T + rigid.translation


def test_a_laser_on_a_moving_base_is_placed_by_composing_the_two_links():
    # laser at (0.3, 0.1, 0.2) on base_link, turned 0.5 rad; base_link at (1, 2) in odom,
    # turned pi/2: a point 1 m ahead of the laser is, in closed form, at
    # (1, 2) + R(pi/2) ((0.3, 0.1) + (cos 0.5, sin 0.5))
    buffer = _buffer(_t('base_link', 'laser', 0, (0.3, 0.1, 0.2), yaw_quaternion(0.5)),
                     static=True)
    assert buffer.set_transform(_t('odom', 'base_link', 5 * S, (1.0, 2.0, 0.0),
                                   yaw_quaternion(math.pi / 2)), static=False) == ''
    rigid = buffer.lookup_transform('odom', 'laser', 5 * S)
    assert isinstance(rigid, Rigid), rigid
    bx, by = 0.3 + math.cos(0.5), 0.1 + math.sin(0.5)
    np.testing.assert_allclose(rigid.apply_planar(np.array([[1.0, 0.0]])),
                               [[1.0 - by, 2.0 + bx]], atol=1e-12)
    np.testing.assert_allclose(rigid.translation, (1.0 - 0.1, 2.0 + 0.3, 0.2), atol=1e-12)
    # the other way: odom's origin seen from the laser, by the inverse
    back = buffer.lookup_transform('laser', 'odom', 5 * S)
    np.testing.assert_allclose(_points(back, _points(rigid, [[0.7, -0.4, 0.1]])),
                               [[0.7, -0.4, 0.1]], atol=1e-12)


def test_the_midpoint_between_two_samples_is_the_slerp_midpoint_and_the_mean_position():
    buffer = _buffer(_t('odom', 'base_link', 1 * S, (0.0, 0.0, 0.0), yaw_quaternion(0.0)),
                     _t('odom', 'base_link', 3 * S, (2.0, 4.0, 0.0), yaw_quaternion(1.2)))
    rigid = buffer.lookup_transform('odom', 'base_link', 2 * S)
    assert isinstance(rigid, Rigid)
    np.testing.assert_allclose(rigid.translation, (1.0, 2.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(rigid.rotation, yaw_quaternion(0.6), atol=1e-12)
    quarter = buffer.lookup_transform('odom', 'base_link', int(1.5 * S))
    np.testing.assert_allclose(quarter.rotation, yaw_quaternion(0.3), atol=1e-12)


def test_slerp_takes_the_shorter_arc_between_q_and_minus_q():
    # yaw 170 deg and yaw -170 deg written with opposite signs: the short way is through 180
    a = yaw_quaternion(math.radians(170))
    b = tuple(-v for v in yaw_quaternion(math.radians(-170)))
    mid = tf_buffer.slerp(a, b, 0.5)
    assert abs(mid[2]) == pytest.approx(1.0, abs=1e-12)  # yaw 180 deg


_QUATERNIONS = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: 0.1 < math.sqrt(sum(v * v for v in q)))
_VECTORS = st.lists(st.floats(-100, 100), min_size=3, max_size=3)


def _unit(q):
    n = math.sqrt(sum(v * v for v in q))
    return tuple(v / n for v in q)


@settings(max_examples=100, deadline=None)
@given(qa=_QUATERNIONS, qb=_QUATERNIONS, ta=_VECTORS, tb=_VECTORS, s=st.floats(0, 1))
def test_composition_and_interpolation_agree_with_scipy(qa, qb, ta, tb, s):
    qa, qb = _unit(qa), _unit(qb)
    a, b = Rigid(qa, tuple(ta)), Rigid(qb, tuple(tb))
    both = a.compose(b)
    ra, rb = Rotation.from_quat(qa), Rotation.from_quat(qb)
    np.testing.assert_allclose(both.matrix(), (ra * rb).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(both.translation, ra.apply(tb) + ta, atol=1e-9)
    # q and -q are one rotation: at a dot product of 0 both arcs are the shorter one
    assume(abs(sum(p * q for p, q in zip(qa, qb))) > 1e-3)
    mid = tf_buffer.slerp(qa, qb, s)
    expected = Slerp([0.0, 1.0], Rotation.from_quat([qa, qb]))([s])[0]
    np.testing.assert_allclose(Rotation.from_quat(mid).as_matrix(), expected.as_matrix(),
                               atol=1e-6)


def _chain_buffer(links):
    """frames f0 <- f1 <- ... (each link static), from (rotation, translation) pairs."""
    buffer = TransformBuffer()
    for k, (q, t) in enumerate(links):
        assert buffer.set_transform(_t(f'f{k}', f'f{k + 1}', 0, t, q), static=True) == ''
    return buffer


_LINKS = st.lists(st.tuples(_QUATERNIONS.map(_unit), _VECTORS), min_size=1, max_size=5)


@settings(max_examples=100, deadline=None)
@given(links=_LINKS, pick=st.data())
def test_a_lookup_and_its_reverse_compose_to_the_identity_and_chains_compose(links, pick):
    buffer = _chain_buffer(links)
    n = len(links) + 1
    a, b, c = (pick.draw(st.integers(0, n - 1)) for _ in range(3))
    ab = buffer.lookup_transform(f'f{a}', f'f{b}', 0)
    ba = buffer.lookup_transform(f'f{b}', f'f{a}', 0)
    identity = ab.compose(ba)
    np.testing.assert_allclose(identity.matrix(), np.eye(3), atol=1e-9)
    np.testing.assert_allclose(identity.translation, (0, 0, 0), atol=1e-7)
    bc = buffer.lookup_transform(f'f{b}', f'f{c}', 0)
    ac = buffer.lookup_transform(f'f{a}', f'f{c}', 0)
    np.testing.assert_allclose(ab.compose(bc).matrix(), ac.matrix(), atol=1e-9)
    np.testing.assert_allclose(ab.compose(bc).translation, ac.translation, atol=1e-7)
    # against scipy: f0 <- fn is the product of the links in order
    rotation, translation = Rotation.identity(), np.zeros(3)
    for q, t in links:
        translation = translation + rotation.apply(t)
        rotation = rotation * Rotation.from_quat(q)
    whole = buffer.lookup_transform('f0', f'f{n - 1}', 0)
    np.testing.assert_allclose(whole.matrix(), rotation.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(whole.translation, translation, atol=1e-7)


def test_time_zero_is_the_latest_time_the_whole_chain_is_known():
    buffer = _buffer(_t('odom', 'base_link', 1 * S, (0.0, 0.0, 0.0)),
                     _t('odom', 'base_link', 3 * S, (2.0, 0.0, 0.0)),
                     _t('base_link', 'arm', 1 * S, (0.0, 0.0, 0.0)),
                     _t('base_link', 'arm', 2 * S, (0.0, 1.0, 0.0)))
    rigid = buffer.lookup_transform('odom', 'arm', 0)  # arm known until 2 s: base at 2 s
    np.testing.assert_allclose(rigid.translation, (1.0, 1.0, 0.0), atol=1e-12)
    latest = buffer.lookup_transform('odom', 'base_link', 0)  # base alone: its newest
    np.testing.assert_allclose(latest.translation, (2.0, 0.0, 0.0), atol=1e-12)


def test_data_past_the_newest_sample_is_held_within_the_tolerance_and_refused_beyond():
    buffer = _buffer(_t('odom', 'base_link', 1 * S, (1.0, 0.0, 0.0)),
                     _t('odom', 'base_link', 2 * S, (2.0, 0.0, 0.0)))
    held = buffer.lookup_transform('odom', 'base_link', 2 * S + 50_000_000,
                                   tolerance_ns=100_000_000)
    np.testing.assert_allclose(held.translation, (2.0, 0.0, 0.0))
    late = buffer.lookup_transform('odom', 'base_link', 2 * S + 150_000_000,
                                   tolerance_ns=100_000_000)
    assert isinstance(late, NoTransform) and late.kind == tf_buffer.EXTRAPOLATION
    assert late.reason == ("no transform from 'base_link' to 'odom' at 2.150 s: 'odom' -> "
                           "'base_link' too old: its newest is at 2.000 s, 0.150 s before "
                           '(tolerance 0.100 s)')
    early = buffer.lookup_transform('base_link', 'odom', S - 200_000_000,
                                    tolerance_ns=100_000_000)
    assert isinstance(early, NoTransform) and 'too new: its oldest is at 1.000 s' in early.reason
    assert isinstance(buffer.lookup_transform('odom', 'base_link', S - 50_000_000,
                                              tolerance_ns=100_000_000), Rigid)


@pytest.mark.parametrize(('target', 'source', 'kind', 'words'), [
    ('odom', 'laser', tf_buffer.FRAME, "frame 'laser' does not exist"),
    ('odom', 'camera', tf_buffer.CONNECTIVITY,
     "two unconnected trees (of roots 'mount' and 'odom')"),
    ('odom', 'a', tf_buffer.LOOP, 'the tree has a loop through'),
    ('', 'a', tf_buffer.FRAME, 'empty frame id'),
])
def test_lookups_without_an_answer_say_why_naming_both_frames(target, source, kind, words):
    buffer = _buffer(_t('odom', 'base_link'), _t('mount', 'camera'), _t('b', 'a'),
                     _t('a', 'b'), static=True)
    out = buffer.lookup_transform(target, source, 0)
    assert isinstance(out, NoTransform) and out.kind == kind, out
    assert out.reason.startswith(f'no transform from {source!r} to {target!r}')
    assert words in out.reason and '\n' not in out.reason


def test_a_new_parent_replaces_the_old_and_static_replaces_dynamic():
    buffer = _buffer(_t('odom', 'base_link', 1 * S, (1.0, 0.0, 0.0)))
    assert buffer.set_transform(_t('map', 'base_link', 2 * S, (5.0, 0.0, 0.0)),
                                static=False) == ''
    assert buffer.parent('base_link') == 'map'
    assert isinstance(buffer.lookup_transform('odom', 'base_link', 0), NoTransform)
    assert buffer.set_transform(_t('odom', 'base_link', 0, (7.0, 0.0, 0.0)), static=True) == ''
    for time_ns in (0, 1, 100 * S):  # static: at every time
        out = buffer.lookup_transform('odom', 'base_link', time_ns)
        np.testing.assert_allclose(out.translation, (7.0, 0.0, 0.0))


def test_the_cache_keeps_ten_seconds_behind_the_newest_and_refuses_older_data():
    buffer = TransformBuffer()
    for k in range(30):
        assert buffer.set_transform(_t('odom', 'base_link', k * S, (float(k), 0.0, 0.0)),
                                    static=False) == ''
    assert isinstance(buffer.lookup_transform('odom', 'base_link', 19 * S), Rigid)
    old = buffer.lookup_transform('odom', 'base_link', 18 * S)
    assert isinstance(old, NoTransform) and 'too new: its oldest is at 19.000 s' in old.reason
    # with a clock: older than the cache behind the link's newest (tf2's TF_OLD_DATA), or
    # behind the clock, refused
    why = buffer.set_transform(_t('odom', 'base_link', 18 * S), static=False, now_ns=25 * S)
    assert why == ("'odom' -> 'base_link': stamp 18.000 s is older than the cache (10.000 s "
                   'behind the newest, 29.000 s)')
    why = buffer.set_transform(_t('odom', 'base_link', 5 * S), static=False, now_ns=29 * S)
    assert why == ("'odom' -> 'base_link': stamp 5.000 s is older than the cache (10.000 s "
                   'behind the clock, 29.000 s)')
    assert isinstance(buffer.lookup_transform('odom', 'base_link', 19 * S), Rigid)
    capped = TransformBuffer(max_samples=3)
    for k in range(5):
        capped.set_transform(_t('odom', 'base_link', k * S), static=False)
    assert isinstance(capped.lookup_transform('odom', 'base_link', S), NoTransform)
    assert isinstance(capped.lookup_transform('odom', 'base_link', 2 * S), Rigid)


def test_samples_past_the_total_bound_are_refused_and_a_replaced_link_frees_its_own():
    buffer = TransformBuffer(max_total_samples=4)
    for k in range(3):
        assert buffer.set_transform(_t('odom', 'base_link', k * S), static=False) == ''
    assert buffer.set_transform(_t('base_link', 'laser'), static=True) == ''
    why = buffer.set_transform(_t('odom', 'base_link', 3 * S), static=False)
    assert why == "'odom' -> 'base_link': refused, the buffer holds 4 samples (at most 4)"
    assert buffer.set_transform(_t('base_link', 'laser', 0, (1.0, 0.0, 0.0)), static=True) == ''
    # a new parent drops the old link's three samples: room again
    assert buffer.set_transform(_t('map', 'base_link', 3 * S), static=False) == ''
    assert buffer.set_transform(_t('map', 'base_link', 4 * S), static=False) == ''


def test_frames_past_the_bound_are_refused():
    buffer = TransformBuffer(max_frames=3)
    assert buffer.set_transform(_t('a', 'b'), static=True) == ''
    assert buffer.set_transform(_t('b', 'c'), static=True) == ''
    why = buffer.set_transform(_t('c', 'd'), static=True)
    assert 'holds 3 frames (at most 3)' in why
    assert buffer.frames == {'a', 'b', 'c'}


_HOSTILE = st.one_of(st.none(), st.text(max_size=3), st.integers(), st.floats(),
                     st.booleans(), st.lists(st.floats(), max_size=5))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(entries=st.lists(st.tuples(st.sampled_from(['odom', 'base_link', 'laser', 'x', '']),
                                  st.sampled_from(['odom', 'base_link', 'laser', 'x', '']),
                                  st.one_of(st.integers(-3 * S, 3 * S), _HOSTILE),
                                  st.one_of(_VECTORS, _HOSTILE),
                                  st.one_of(_QUATERNIONS.map(_unit), _QUATERNIONS, _HOSTILE),
                                  st.booleans()),
                        max_size=8),
       target=st.one_of(st.sampled_from(['odom', 'laser', 'x']), _HOSTILE),
       source=st.one_of(st.sampled_from(['odom', 'laser', 'base_link']), _HOSTILE),
       time_ns=st.one_of(st.integers(-3 * S, 3 * S), _HOSTILE),
       tolerance=st.one_of(st.integers(0, S), _HOSTILE), small=st.booleans())
def test_hostile_transforms_and_lookups_never_raise(entries, target, source, time_ns,
                                                    tolerance, small):
    buffer = (TransformBuffer(cache_s=1.0, max_samples=3, max_total_samples=5) if small
              else TransformBuffer())
    for parent, child, stamp, translation, rotation, static in entries:
        why = buffer.set_transform(StampedTransform(parent, child, stamp, translation, rotation),
                                   static=static)
        assert isinstance(why, str) and '\n' not in why
    held = sum(len(link.stamps) for link in buffer._links.values())
    assert buffer._samples == held <= buffer.max_total_samples
    out = buffer.lookup_transform(target, source, time_ns, tolerance_ns=tolerance)
    if isinstance(out, NoTransform):
        assert '\n' not in out.reason
    else:
        assert np.all(np.isfinite(out.matrix())) and np.all(np.isfinite(out.translation))


@settings(max_examples=200, deadline=None)
@given(stream=st.lists(st.tuples(st.sampled_from(['odom', 'map']),
                                 st.sampled_from(['base_link', 'laser']),
                                 st.integers(0, 4 * S), st.booleans()), max_size=40))
def test_the_cache_stays_sorted_within_its_bounds_under_any_stream(stream):
    buffer = TransformBuffer(cache_s=1.0, max_samples=4, max_total_samples=6)
    for parent, child, stamp, static in stream:
        buffer.set_transform(_t(parent, child, stamp), static=static)
        links = buffer._links.values()
        assert buffer._samples == sum(len(link.stamps) for link in links) <= 6
        for link in links:
            assert link.stamps == sorted(set(link.stamps)) and len(link.stamps) <= 4
            assert link.stamps[-1] - link.stamps[0] <= buffer.cache_ns
            assert len(link.poses) == len(link.stamps) and (not link.static
                                                            or len(link.stamps) == 1)

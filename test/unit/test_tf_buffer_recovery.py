"""No input leaves tf's bookkeeping where good data cannot recover it (rcbf_ros.node_logic.
tf_buffer's TransformBuffer, and rcbf_ros.ros.tf2_buffer's Tf2Feed over a model of tf2's
cache): after a flood, a far-future stamp or time going back, a good stream is taken again
within the cache time (at once on a jump back), with the bounds held at every step.

The model of tf2 (:class:`Tf2Store`) follows tf2's cache.cpp: a link drops its samples older
than the cache behind its newest before it takes one, refuses one older than that, keeps
every frame name for good; ``clear()`` empties the dynamic links and keeps the static ones.
"""
from __future__ import annotations

import bisect
from types import SimpleNamespace

from hypothesis import example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from tf_messages import tf_bytes, transform_stamped

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.messages.tf import StampedTransform
from rcbf_ros.node_logic.sources import ObservationSources
from rcbf_ros.node_logic.tf_buffer import JUMP_BACK_S, NoTransform, Rigid, TransformBuffer
from rcbf_ros.ros.tf2_buffer import Tf2Feed

S = 1_000_000_000
MS = 1_000_000
UNIT = (0.0, 0.0, 0.0, 1.0)
COUNTS = ('messages', 'refused', 'transforms_refused')


def _t(parent, child, stamp_ns=0, x=0.0):
    return StampedTransform(parent, child, stamp_ns, (x, 0.0, 0.0), UNIT)


def _held(buffer: TransformBuffer) -> int:
    """The samples the links hold, counted afresh (the buffer's own count must agree)."""
    return sum(len(link.stamps) for link in buffer._links.values())


def _bounded(buffer: TransformBuffer) -> None:
    assert buffer._samples == _held(buffer) <= buffer.max_total_samples
    assert len(buffer.frames) <= buffer.max_frames
    named = {frame for child, link in buffer._links.items() for frame in (child, link.parent)}
    assert named == buffer.frames


def _odom_at(buffer: TransformBuffer, stamp_ns: int, x: float) -> None:
    """laser -> odom at ``stamp_ns`` is the good tree's: base_link at x, laser 0.1 m ahead."""
    out = buffer.lookup_transform('odom', 'laser', stamp_ns)
    assert isinstance(out, Rigid), out
    np.testing.assert_allclose(out.translation, (x + 0.1, 0.0, 0.0), atol=1e-12)


@pytest.mark.parametrize('clock', [True, False])
def test_a_flood_that_filled_the_sample_bound_is_refused_only_while_it_lasts(clock):
    # the reported robot, ten times smaller: odom -> base_link at 50 Hz and 11 joints at
    # 100 Hz fill 1,000 samples within the 1 s cache; then the joints stop
    buffer = TransformBuffer(cache_s=1.0, max_total_samples=1_000)
    assert buffer.set_transform(_t('base_link', 'laser', 0, 0.1), static=True) == ''
    refused = []
    for k in range(400):  # 4 s at 100 Hz
        t = 10 * S + k * 10 * MS
        now = t if clock else None
        if k < 150:
            for j in range(11):
                buffer.set_transform(_t('base_link', f'joint_{j}', t), static=False, now_ns=now)
        if k % 2 == 0:
            why = buffer.set_transform(_t('odom', 'base_link', t, k / 100), static=False,
                                       now_ns=now)
            if why:
                refused.append((t, why))
        _bounded(buffer)
    assert refused, 'the flood never reached the bound'
    assert all(t < 10 * S + 150 * 10 * MS for t, _ in refused), refused[-1]
    assert refused[0][1] == ("'odom' -> 'base_link': refused, the buffer holds 1000 samples (at "
                             'most 1000)')
    # the joints' links expired, their frames forgotten; the robot is placed again
    assert buffer.frames == {'odom', 'base_link', 'laser'}
    _odom_at(buffer, t - 10 * MS, 3.98)


def test_the_reported_flood_at_full_size_recovers_once_it_stops():
    # odom -> base_link at 50 Hz, 101 moving frames at 100 Hz (some 101,000 samples in 10 s)
    buffer = TransformBuffer()
    assert buffer.set_transform(_t('base_link', 'laser', 0, 0.1), static=True) == ''
    for k in range(2_510):  # 25.1 s at 100 Hz, the joints for the first 15
        t = 10 * S + k * 10 * MS
        if k < 1_500:
            for j in range(101):
                buffer.set_transform(_t('base_link', f'joint_{j}', t), static=False, now_ns=t)
        if k % 2 == 0:
            why = buffer.set_transform(_t('odom', 'base_link', t, 1.0), static=False, now_ns=t)
            assert why == '' or k < 1_500, why
    assert buffer._samples <= buffer.max_total_samples
    assert buffer.frames == {'odom', 'base_link', 'laser'}
    _odom_at(buffer, t - 10 * MS, 1.0)


@pytest.mark.parametrize('clock', [True, False])
def test_frames_whose_links_expired_are_forgotten_and_new_ones_taken_again(clock):
    buffer = TransformBuffer(cache_s=1.0, max_frames=10)
    assert buffer.set_transform(_t('base_link', 'laser', 0, 0.1), static=True) == ''
    refused = [buffer.set_transform(_t('base_link', f'f{k}', 5 * S), static=False,
                                    now_ns=5 * S if clock else None) for k in range(50)]
    assert refused[:8] == [''] * 8 and refused[8] == (
        "'base_link' -> 'f8': refused, the buffer holds 10 frames (at most 10)")
    assert all(why.endswith('holds 10 frames (at most 10)') for why in refused[8:])
    assert len(buffer.frames) == 10
    # a cache later the dynamic frames are gone, the static ones stay; new names are taken
    later = 6 * S + 1
    assert buffer.set_transform(_t('odom', 'base_link', later, 2.0), static=False,
                                now_ns=later if clock else None) == ''
    assert buffer.frames == {'odom', 'base_link', 'laser'}
    assert buffer.set_transform(_t('base_link', 'g', later), static=False,
                                now_ns=later if clock else None) == ''
    _odom_at(buffer, later, 2.0)


@pytest.mark.parametrize('future_s', [2**31 - 1, 3_600 + 10])
def test_a_far_future_stamp_is_refused_against_the_clock_and_counted(future_s):
    config = filter_config_from_params({
        'system': 'unicycle', 'obstacles.heading_index': 2, 'observation_sources': ['front'],
        'front.type': 'scan', 'front.topic': 'scan', 'footprint.radius': 0.2})
    sources = ObservationSources(config.sources)

    def odom(stamp_ns, now_ns, x):
        return sources.read_tf(tf_bytes(transform_stamped(
            'odom', 'base_link', stamp_ns=stamp_ns, translation=(x, 0.0, 0.0))), static=False,
            now_ns=now_ns)

    assert sources.read_tf(tf_bytes(transform_stamped('base_link', 'laser',
                                                      translation=(0.1, 0.0, 0.0))),
                           static=True, now_ns=10 * S) == ''
    assert odom(10 * S, 10 * S, 1.0) == ''
    assert odom(future_s * S, 10 * S, 9.0) == (
        f"'odom' -> 'base_link': stamp {future_s}.000 s is more than the cache (10.000 s) "
        'after the clock (10.000 s)')
    assert sources.tf_counts == {'messages': 3, 'refused': 0, 'transforms_refused': 1}
    assert odom(10 * S + 20 * MS, 10 * S + 20 * MS, 1.5) == ''
    _odom_at(sources.tf, 10 * S + 20 * MS, 1.5)


@pytest.mark.parametrize('future_s', [2**31 - 1, 3_600 + 10])
def test_without_a_clock_a_far_future_stamp_blocks_nothing_beyond_the_next_good_sample(
        future_s):
    buffer = TransformBuffer()
    assert buffer.set_transform(_t('base_link', 'laser', 0, 0.1), static=True) == ''
    assert buffer.set_transform(_t('odom', 'base_link', 10 * S, 1.0), static=False) == ''
    assert buffer.set_transform(_t('odom', 'base_link', future_s * S, 9.0), static=False) == ''
    # the data's time went back by more than the cache: the dynamic links start again
    assert buffer.set_transform(_t('odom', 'base_link', 10 * S + 20 * MS, 1.5),
                                static=False) == ''
    assert buffer.clears == 1 and buffer._samples == 2
    _odom_at(buffer, 10 * S + 20 * MS, 1.5)


@pytest.mark.parametrize('clock', [True, False])
def test_time_going_back_clears_the_dynamic_links_and_keeps_the_static_ones(clock):
    # a simulator restarted: stamps (and ROS time) go from 100 s back to 5 s
    buffer = TransformBuffer()
    assert buffer.set_transform(_t('base_link', 'laser', 0, 0.1), static=True) == ''
    assert buffer.set_transform(_t('map', 'odom', 100 * S), static=False,
                                now_ns=100 * S if clock else None) == ''
    for k in range(10):
        t = 99 * S + k * 100 * MS
        assert buffer.set_transform(_t('odom', 'base_link', t, 1.0), static=False,
                                    now_ns=t if clock else None) == ''
    assert buffer.set_transform(_t('odom', 'base_link', 5 * S, 2.0), static=False,
                                now_ns=5 * S if clock else None) == ''
    assert buffer.clears == 1
    assert buffer.frames == {'odom', 'base_link', 'laser'}  # map's link went with the rest
    _odom_at(buffer, 5 * S, 2.0)
    assert isinstance(buffer.lookup_transform('odom', 'base_link', 99 * S), NoTransform)


def test_the_clock_going_back_by_less_than_the_jump_keeps_the_data():
    buffer = TransformBuffer()
    assert buffer.set_transform(_t('odom', 'base_link', 10 * S), static=False,
                                now_ns=10 * S) == ''
    back = 10 * S - int(JUMP_BACK_S * S)  # two threads reading the clock out of order
    assert buffer.set_transform(_t('odom', 'base_link', back), static=False, now_ns=back) == ''
    assert buffer.clears == 0 and buffer._samples == 2


def test_a_first_clock_behind_data_taken_without_one_clears_them():
    buffer = TransformBuffer()
    assert buffer.set_transform(_t('odom', 'base_link', 3_600 * S), static=False) == ''
    assert buffer.set_transform(_t('odom', 'base_link', 10 * S, 1.0), static=False,
                                now_ns=10 * S) == ''
    assert buffer.clears == 1 and buffer._samples == 1


# hostile streams, then a good one --------------------------------------------------------
CACHE_S = 1.0
PERIOD = 50 * MS
POOL = ['odom', 'base_link', 'laser', 'x'] + [f'f{k}' for k in range(12)]
STATIC_CHILDREN = ['base_link', 'laser', 'x']
"""The children a hostile static transform may name: a static link holds for good, as in tf2,
so statics of other children could fill the frame bound for good (what stays refused), and
one naming the good tree's root as its child would need a good static to replace it."""
_TIMES = st.one_of(st.sampled_from([0, 5 * S, 30 * S, 59 * S]), st.integers(-S, 60 * S))
"""Clocks, and where the good stream starts (0: no clock yet)."""
_OFFSETS = st.one_of(st.integers(-S, S), st.integers(-3 * S, 3 * S),
                     st.integers(-2**62, 2**62), st.sampled_from([(2**31 - 1) * S, 3_600 * S]))
"""A stamp from the clock: near it (the cache is 1 s), anywhere, or far ahead."""
_LINKS = st.one_of(st.sampled_from([('odom', 'base_link'), ('base_link', 'laser'),
                                    ('laser', 'odom')]),
                   st.tuples(st.sampled_from(POOL), st.sampled_from(POOL)))
"""The good tree's links (and one closing a loop) often, any two frames of the pool else."""
_ENTRY = st.tuples(_LINKS, _OFFSETS, st.booleans(), _TIMES, st.integers(1, 12))
"""(parent, child), stamp - clock, static, clock, repeat (that many samples, 1 ms apart)."""


def _hostile(entries, clock: bool):
    """The transforms of ``entries`` and their clocks (None without one); static only where
    the child is one of :data:`STATIC_CHILDREN`."""
    for (parent, child), offset, static, now, repeat in entries:
        static = static and child in STATIC_CHILDREN
        for r in range(1 if static else repeat):
            yield _t(parent, child, now + offset + r * MS), static, (now if clock else None)


def _recovery_ns(good_ns: int) -> int:
    """When a good stream from ``good_ns`` is taken again at the latest: the clock may lead it
    by up to JUMP_BACK_S, a stamp the cache more, and that one lives a cache more."""
    return good_ns + int(JUMP_BACK_S * S) + 2 * int(CACHE_S * S) + 2 * PERIOD


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(entries=st.lists(_ENTRY, max_size=30), clock=st.booleans(),
       good_ns=_TIMES.filter(lambda t: t >= 0))
@example(entries=[(('odom', 'base_link'), S // 2, False, 50 * S, 1)], clock=True, good_ns=0)
@example(entries=[(('odom', 'base_link'), 3_600 * S, False, 50 * S, 1)], clock=False,
         good_ns=50 * S)
def test_after_any_hostile_stream_a_good_one_is_taken_again_within_the_bounds(
        entries, clock, good_ns):
    buffer = TransformBuffer(cache_s=CACHE_S, max_frames=8, max_samples=10,
                             max_total_samples=40)
    for transform, static, now in _hostile(entries, clock):
        assert '\n' not in buffer.set_transform(transform, static=static, now_ns=now)
        _bounded(buffer)
    t, k = good_ns, 0
    while t <= _recovery_ns(good_ns) + 3 * PERIOD:
        now = t if clock else None
        kept = (buffer.set_transform(_t('base_link', 'laser', t, 0.1), static=True, now_ns=now),
                buffer.set_transform(_t('odom', 'base_link', t, k / 100), static=False,
                                     now_ns=now))
        _bounded(buffer)
        if t > _recovery_ns(good_ns):
            assert kept == ('', ''), (t, kept)
            _odom_at(buffer, t, k / 100)
        t, k = t + PERIOD, k + 1


# the feed of tf2_ros ----------------------------------------------------------------------
class Tf2Store:
    """tf2's BufferCore as far as memory goes (module docstring)."""

    def __init__(self, cache_ns: int) -> None:
        self.cache_ns = cache_ns
        self.dynamic: dict[str, list[int]] = {}
        self.static: set[str] = set()
        self.names: set[str] = set()

    def set_transform(self, transform, authority) -> None:
        child = transform.child_frame_id
        self.names.update((transform.header.frame_id, child))
        stamp = transform.header.stamp.sec * S + transform.header.stamp.nanosec
        held = self.dynamic.setdefault(child, [])
        if held:
            del held[:bisect.bisect_left(held, held[-1] - self.cache_ns)]  # pruneList
            if stamp < held[-1] - self.cache_ns:
                return  # TF_OLD_DATA: logged, not raised
        bisect.insort(held, stamp)

    def set_transform_static(self, transform, authority) -> None:
        self.names.update((transform.header.frame_id, transform.child_frame_id))
        self.static.add(transform.child_frame_id)

    def clear(self) -> None:
        self.dynamic.clear()

    def held(self) -> int:
        return sum(len(stamps) for stamps in self.dynamic.values())


def _feed(**bounds) -> Tf2Feed:
    cache_ns = int(CACHE_S * S)
    return Tf2Feed(Tf2Store(cache_ns), dict.fromkeys(COUNTS, 0), cache_s=CACHE_S,
                   renew=lambda: Tf2Store(cache_ns), **bounds)


def _send(feed: Tf2Feed, parent, child, stamp_ns, *, static=False, now_ns=None) -> str:
    return feed.take(SimpleNamespace(transforms=[
        transform_stamped(parent, child, stamp_ns=stamp_ns)]), static=static, now_ns=now_ns)


def _feed_bounded(feed: Tf2Feed) -> None:
    store = feed.buffer
    assert store.held() == feed._samples <= feed.max_total_samples
    assert len(store.names) <= feed.max_frames and len(feed.frames) <= feed.max_frames


def test_the_feed_renews_tf2s_buffer_when_its_names_are_spent_and_keeps_the_static_ones():
    feed = _feed(max_frames=10)
    assert _send(feed, 'base_link', 'laser', 0, static=True, now_ns=5 * S) == ''
    said = [_send(feed, 'base_link', f'f{k}', 5 * S, now_ns=5 * S) for k in range(50)]
    assert said[:8] == [''] * 8 and said[8].endswith('holds 10 frames (at most 10)')
    first = feed.buffer
    later = 6 * S + 1  # a cache on: f0 ... f7 expired, but tf2 still holds their names
    assert _send(feed, 'odom', 'base_link', later, now_ns=later) == ''
    assert feed.renewals == 1 and feed.buffer is not first
    assert feed.buffer.names == {'odom', 'base_link', 'laser'}
    assert feed.buffer.static == {'laser'} and feed.buffer.held() == 1
    _feed_bounded(feed)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(entries=st.lists(_ENTRY, max_size=30), clock=st.booleans(),
       good_ns=_TIMES.filter(lambda t: t >= 0))
@example(entries=[(('base_link', f'f{k}'), 0, False, 5 * S, 12) for k in range(6)],
         clock=True, good_ns=30 * S)
def test_after_any_hostile_stream_the_feed_takes_a_good_one_and_tf2_stays_bounded(
        entries, clock, good_ns):
    feed = _feed(max_frames=8, max_samples=30, max_total_samples=60)
    for transform, static, now in _hostile(entries, clock):
        if not 0 <= transform.stamp_ns < 2**31 * S:
            continue  # not a builtin_interfaces/Time
        said = _send(feed, transform.parent, transform.child, transform.stamp_ns,
                     static=static, now_ns=now)
        assert '\n' not in said
        _feed_bounded(feed)
    t = good_ns
    while t <= _recovery_ns(good_ns) + 3 * PERIOD:
        now = t if clock else None
        kept = (_send(feed, 'base_link', 'laser', t, static=True, now_ns=now),
                _send(feed, 'odom', 'base_link', t, now_ns=now))
        _feed_bounded(feed)
        if t > _recovery_ns(good_ns):
            assert kept == ('', ''), (t, kept)
        t += PERIOD

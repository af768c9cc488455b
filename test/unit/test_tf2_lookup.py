"""rcbf_ros.ros.tf2_buffer without ROS: the lookup over a fake of tf2_ros's Buffer (its
``lookup_transform_core``, exceptions and texts as tf2's cache.cpp words them), against our
TransformBuffer; the feed against ObservationSources.read_tf.

The fake answers from a TransformBuffer at tolerance 0 (tf2's rules, checked against tf2_ros
itself in test/ros2/test_ros2_tf_buffer.py) and refuses as tf2 refuses: the first link of the
source's side, then the target's, without data at the time. Held links are then the lookup's
work: with one dynamic link the lookup must answer exactly as our buffer does at any
tolerance.
"""
from __future__ import annotations

from types import SimpleNamespace

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
from tf_messages import T, tf_bytes, transform_stamped, yaw_quaternion

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.messages.tf import StampedTransform
from rcbf_ros.node_logic.sources import ObservationSources
from rcbf_ros.node_logic.tf_buffer import (
    CONNECTIVITY,
    EXTRAPOLATION,
    FRAME,
    IDENTITY,
    NoTransform,
    Rigid,
    TransformBuffer,
)
from rcbf_ros.ros.tf2_buffer import Tf2Feed, Tf2Lookup

S = 1_000_000_000
US = 1_000
T0 = 1_700_000_000 * S


class LookupException(Exception):
    pass


class ConnectivityException(Exception):
    pass


class ExtrapolationException(Exception):
    pass


def _time(ns: int) -> str:
    return f'{ns / S:.6f}'


class FakeTf2:
    """tf2_ros's Buffer as far as the lookup uses it (module docstring)."""

    def __init__(self) -> None:
        self.core = TransformBuffer()
        self.stamps: dict[str, list[int]] = {}
        """Per dynamic child, its samples' stamps (sorted)."""
        self.asked: list[int] = []

    def add(self, parent: str, child: str, stamp_ns: int, translation, rotation,
            static: bool = False) -> None:
        assert self.core.set_transform(StampedTransform(
            parent, child, stamp_ns, tuple(translation), tuple(rotation)), static=static) == ''
        if not static:
            self.stamps[child] = sorted({*self.stamps.get(child, []), stamp_ns})

    def _links(self, frame: str) -> list[str]:
        out = []
        while self.core.parent(frame) is not None:
            out.append(frame)
            frame = self.core.parent(frame)
        return out

    def _chain(self, target: str, source: str) -> list[str]:
        up_source, up_target = self._links(source), self._links(target)
        shared = set(up_source) & set(up_target)
        return ([c for c in up_source if c not in shared]
                + [c for c in up_target if c not in shared])

    def lookup_transform_core(self, target, source, time):
        ns = time.nanoseconds
        self.asked.append(ns)
        found = self.core.lookup_transform(target, source, ns)
        if isinstance(found, NoTransform):
            if found.kind == CONNECTIVITY:
                raise ConnectivityException(found.reason)
            if found.kind != EXTRAPOLATION:
                raise LookupException(found.reason)
            where = f', when looking up transform from frame [{source}] to frame [{target}]'
            for child in self._chain(target, source):
                stamps = self.stamps.get(child)
                if not stamps or stamps[0] <= ns <= stamps[-1]:
                    continue
                if len(stamps) == 1:
                    raise ExtrapolationException(
                        f'Lookup would require extrapolation at time {_time(ns)}, but only '
                        f'time {_time(stamps[0])} is in the buffer{where}')
                if ns > stamps[-1]:
                    raise ExtrapolationException(
                        'Lookup would require extrapolation into the future.  Requested time '
                        f'{_time(ns)} but the latest data is at time {_time(stamps[-1])}{where}')
                raise ExtrapolationException(
                    'Lookup would require extrapolation into the past.  Requested time '
                    f'{_time(ns)} but the earliest data is at time {_time(stamps[0])}{where}')
            raise AssertionError(found)
        if ns == 0:
            newest = [self.stamps[c][-1] for c in self._chain(target, source) if c in self.stamps]
            ns = min(newest) if newest else 0
        sec, nanosec = divmod(ns, S)
        x, y, z = found.translation
        qx, qy, qz, qw = found.rotation
        return SimpleNamespace(
            header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
            transform=SimpleNamespace(translation=SimpleNamespace(x=x, y=y, z=z),
                                      rotation=SimpleNamespace(x=qx, y=qy, z=qz, w=qw)))


def _both(samples, *, mount=True):
    """The fake (behind a Tf2Lookup) and our buffer, given the same transforms."""
    fake, ours = FakeTf2(), TransformBuffer()
    items = [('base_link', 'laser', T0, (0.3, -0.1, 0.2), yaw_quaternion(0.4), True)] * mount
    items += [('odom', 'base_link', stamp, (x, y, 0.0), yaw_quaternion(yaw), False)
              for stamp, (x, y, yaw) in samples]
    for parent, child, stamp, translation, rotation, static in items:
        fake.add(parent, child, stamp, translation, rotation, static)
        assert ours.set_transform(StampedTransform(parent, child, stamp, translation, rotation),
                                  static=static) == ''
    return Tf2Lookup(fake), ours


def _same(a, b) -> None:
    assert isinstance(a, NoTransform) == isinstance(b, NoTransform), (a, b)
    if isinstance(a, NoTransform):
        assert a.kind == b.kind, (a, b)
        return
    np.testing.assert_allclose(a.translation, b.translation, atol=1e-9)
    q, p = np.array(a.rotation), np.array(b.rotation)
    assert min(np.abs(q - p).max(), np.abs(q + p).max()) < 1e-9, (q, p)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(offsets=st.lists(st.integers(0, 2_000_000), min_size=1, max_size=5, unique=True),
       poses=st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-3, 3)),
                      min_size=5, max_size=5),
       asked=st.integers(-1_000_000, 3_000_000), tolerance=st.integers(0, 1_000_000),
       target=st.sampled_from(['odom', 'laser']))
def test_one_dynamic_link_is_held_exactly_as_our_buffer_holds_it(offsets, poses, asked,
                                                                 tolerance, target):
    # whole microseconds, as tf2 prints its times
    samples = [(T0 + offset * US, pose) for offset, pose in zip(offsets, poses)]
    tf2, ours = _both(samples)
    source = 'base_link' if target == 'laser' else 'laser'
    time_ns, tolerance_ns = T0 + asked * US, tolerance * US
    for at in (time_ns, 0):
        _same(tf2.lookup_transform(target, source, at, tolerance_ns=tolerance_ns),
              ours.lookup_transform(target, source, at, tolerance_ns=tolerance_ns))


def test_after_the_newest_within_the_tolerance_the_newest_else_the_fail_safe_naming_both():
    samples = [(T0, (1.0, 2.0, 0.2)), (T0 + S, (3.0, 0.0, 0.6))]
    tf2, ours = _both(samples)
    held = tf2.lookup_transform('odom', 'laser', T0 + S + 90_000_000, tolerance_ns=S // 10)
    _same(held, ours.lookup_transform('odom', 'laser', T0 + S, tolerance_ns=0))
    late = tf2.lookup_transform('odom', 'laser', T0 + S + 110_000_000, tolerance_ns=S // 10)
    assert isinstance(late, NoTransform) and late.kind == EXTRAPOLATION
    assert late.reason.startswith("no transform from 'laser' to 'odom' at "), late.reason
    assert 'too old: the newest is at 1700000001.000 s, 0.110 s before' in late.reason


def test_before_the_oldest_within_the_tolerance_the_oldest_else_the_fail_safe_naming_both():
    samples = [(T0, (1.0, 2.0, 0.2)), (T0 + S, (3.0, 0.0, 0.6))]
    tf2, ours = _both(samples)
    held = tf2.lookup_transform('odom', 'laser', T0 - 50_000_000, tolerance_ns=S // 10)
    _same(held, ours.lookup_transform('odom', 'laser', T0, tolerance_ns=0))
    early = tf2.lookup_transform('odom', 'laser', T0 - 150_000_000, tolerance_ns=S // 10)
    assert isinstance(early, NoTransform) and early.kind == EXTRAPOLATION
    assert early.reason.startswith("no transform from 'laser' to 'odom' at "), early.reason
    assert 'too new: a link starts at 1700000000.000 s, 0.150 s after' in early.reason


def test_a_chain_of_two_dynamic_links_is_held_whole_at_the_held_time():
    """map -> odom from T0 + 0.2 s, odom -> base_link from T0: before T0 + 0.2 s the chain is
    taken at T0 + 0.2 s (both links); after the newest common time, at that time."""
    fake = FakeTf2()
    for k in range(5):
        fake.add('map', 'odom', T0 + 200_000_000 + k * S // 10, (k, 0.0, 0.0), (0, 0, 0, 1))
        fake.add('odom', 'base_link', T0 + k * S // 10, (0.0, k, 0.0), yaw_quaternion(k / 10))
    tf2 = Tf2Lookup(fake)
    early = tf2.lookup_transform('map', 'base_link', T0 + 150_000_000, tolerance_ns=S // 10)
    _same(early, fake.core.lookup_transform('map', 'base_link', T0 + 200_000_000))
    assert fake.asked[-1] == T0 + 200_000_000  # one lookup at the link's oldest time
    late = tf2.lookup_transform('map', 'base_link', T0 + 450_000_000, tolerance_ns=S // 10)
    _same(late, fake.core.lookup_transform('map', 'base_link', T0 + 400_000_000))
    assert isinstance(tf2.lookup_transform('map', 'base_link', T0 + 50_000_000,
                                           tolerance_ns=S // 10), NoTransform)


def test_a_link_of_one_sample_is_held_within_the_tolerance_on_both_sides():
    tf2, ours = _both([(T0, (1.0, 0.0, 0.0))])
    for asked in (T0 - 60_000_000, T0 + 60_000_000, T0 - 200_000_000, T0 + 200_000_000):
        _same(tf2.lookup_transform('odom', 'laser', asked, tolerance_ns=S // 10),
              ours.lookup_transform('odom', 'laser', asked, tolerance_ns=S // 10))


def test_refusals_keep_tf2s_kind_and_name_both_frames():
    tf2, _ = _both([(T0, (1.0, 0.0, 0.0))])
    fake = tf2.buffer
    fake.add('world', 'other', T0, (0, 0, 0), (0, 0, 0, 1), static=True)
    cases = {('odom', 'nowhere'): FRAME, ('odom', 'other'): CONNECTIVITY, ('', 'laser'): FRAME}
    for (target, source), kind in cases.items():
        out = tf2.lookup_transform(target, source, T0)
        assert isinstance(out, NoTransform) and out.kind == kind, out
        assert out.reason.startswith(f'no transform from {source!r} to {target!r}'), out
    assert tf2.lookup_transform('laser', 'laser', 5) is IDENTITY
    assert isinstance(tf2.lookup_transform('odom', 'laser', T0), Rigid)


def test_a_buffer_that_raises_anything_or_answers_nonsense_is_a_refusal_never_a_raise():
    class Broken:
        def __init__(self, answer):
            self.answer = answer

        def lookup_transform_core(self, target, source, time):
            if isinstance(self.answer, Exception):
                raise self.answer
            return self.answer

    zero = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0)),
        transform=SimpleNamespace(translation=SimpleNamespace(x=0.0, y=0.0, z=0.0),
                                  rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=0.0)))
    for answer in (RuntimeError('boom\nline'), TypeError('time'), zero, None,
                   ExtrapolationException('no time in this text')):
        out = Tf2Lookup(Broken(answer)).lookup_transform('odom', 'laser', T0,
                                                         tolerance_ns=S)
        assert isinstance(out, NoTransform) and '\n' not in out.reason, out
        assert "'laser' to 'odom'" in out.reason, out


# the feed ----------------------------------------------------------------------------------
class Recorder:
    def __init__(self):
        self.kept: list[tuple[str, str, bool]] = []

    def set_transform(self, transform, authority):
        self.kept.append((transform.header.frame_id, transform.child_frame_id, False))

    def set_transform_static(self, transform, authority):
        self.kept.append((transform.header.frame_id, transform.child_frame_id, True))

    def clear(self):
        self.kept.append(('', '', False))


def _sources() -> ObservationSources:
    config = filter_config_from_params({
        'system': 'unicycle', 'obstacles.heading_index': 2, 'observation_sources': ['front'],
        'front.type': 'scan', 'front.topic': 'scan', 'footprint.radius': 0.2})
    return ObservationSources(config.sources)


def test_the_feed_refuses_counts_and_says_what_read_tf_says():
    messages = [
        [transform_stamped('odom', 'base_link', rotation=(0, 0, 0, 0)),
         transform_stamped('base_link', 'laser', translation=(float('nan'), 0, 0)),
         transform_stamped('base_link', 'ok')],
        [transform_stamped('/odom', 'base_link', stamp_ns=T0, rotation=yaw_quaternion(0.3))],
        [transform_stamped('a', 'a')],
        [transform_stamped('a', 'b'), transform_stamped('b', 'x' * 1025)],
    ]
    recorder, sources = Recorder(), _sources()
    feed = Tf2Feed(recorder, dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0))
    for k, transforms in enumerate(messages):
        static = k % 2 == 0
        said = feed.take(T['tf2_msgs/msg/TFMessage'](transforms=transforms), static=static)
        assert said == sources.read_tf(tf_bytes(*transforms), static=static), k
    assert feed.counts == sources.tf_counts == {'messages': 4, 'refused': 1,
                                                'transforms_refused': 3}
    assert recorder.kept == [('base_link', 'ok', True), ('/odom', 'base_link', False)]
    assert feed.frames == sources.tf.frames == {'base_link', 'ok', 'odom'}


def test_the_feed_bounds_transforms_per_message_and_frames():
    feed = Tf2Feed(Recorder(), dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0),
                   max_frames=3)
    many = SimpleNamespace(transforms=[transform_stamped('a', 'b')] * 1025)
    assert feed.take(many, static=False).endswith('1025 entries, more than the bound 1024')
    said = feed.take(SimpleNamespace(transforms=[transform_stamped('a', 'b'),
                                                 transform_stamped('b', 'c'),
                                                 transform_stamped('c', 'd')]), static=False)
    assert said == "'c' -> 'd': refused, the buffer holds 3 frames (at most 3)"
    assert feed.take(object(), static=True).startswith('tf2_msgs/msg/TFMessage: ')
    assert feed.counts == {'messages': 3, 'refused': 2, 'transforms_refused': 1}
    assert feed.buffer.kept == [('a', 'b', False), ('b', 'c', False)]


def test_the_feed_refuses_data_older_than_the_cache_in_our_buffers_words():
    recorder, sources = Recorder(), _sources()
    feed = Tf2Feed(recorder, dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0))
    for stamp in (T0 + 20 * S, T0 + 9 * S, T0 + 10 * S):
        transforms = [transform_stamped('odom', 'base_link', stamp_ns=stamp)]
        said = feed.take(T['tf2_msgs/msg/TFMessage'](transforms=transforms), static=False,
                         now_ns=T0 + 19 * S)
        assert said == sources.read_tf(tf_bytes(*transforms), static=False,
                                       now_ns=T0 + 19 * S), stamp
    assert said == ''
    assert feed.counts == sources.tf_counts == {'messages': 3, 'refused': 0,
                                                'transforms_refused': 1}
    assert len(recorder.kept) == 2


def _sender(feed):
    def send(child, stamp, now_ns=None):
        return feed.take(SimpleNamespace(transforms=[
            transform_stamped('odom', child, stamp_ns=stamp)]), static=False,
            now_ns=now_ns or stamp)
    return send


def test_the_feed_bounds_samples_per_link_within_the_cache():
    feed = Tf2Feed(Recorder(), dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0),
                   max_samples=3)
    send = _sender(feed)
    for k in range(3):
        assert send('a', T0 + k * S) == ''
    assert send('a', T0 + 3 * S) == ("'odom' -> 'a': refused, the link holds 3 samples within "
                                     '10.000 s (at most 3)')
    assert send('a', T0 + 2 * S, T0 + 3 * S) != ''  # one stamp again: one more sample for tf2
    assert send('a', T0 + 11 * S) == ''  # the first is older than the cache behind it
    # tf2 drops that first sample only at the link's next one: until then it holds four
    assert feed._samples == 4
    assert send('a', T0 + 12 * S + 1) == '' and feed._samples == 4  # the first left, now
    assert feed.counts['transforms_refused'] == 2


def test_the_feed_bounds_samples_in_all_while_a_flood_lasts_then_clears_what_expired():
    recorder = Recorder()
    feed = Tf2Feed(recorder, dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0),
                   max_total_samples=5)
    send = _sender(feed)
    for k in range(5):
        assert send('a', T0 + k * S) == ''
    assert send('b', T0 + 5 * S) == ("'odom' -> 'b': refused, the buffer holds 5 samples "
                                     '(at most 5)')
    assert send('a', T0 + 5 * S).endswith('refused, the buffer holds 5 samples (at most 5)')
    # 12 s on, two of a's samples lie older than the cache behind the clock: tf2 would keep
    # them (a link drops its old samples only when it takes a new one), so its dynamic data
    # are cleared, and b's sample is taken
    assert send('b', T0 + 12 * S) == ''
    assert recorder.kept[-2:] == [('', '', False), ('odom', 'b', False)]
    assert feed.clears == 1 and feed._samples == 1 and feed.frames == {'odom', 'b'}


def test_without_tf2_ros_start_tf2_says_why_in_one_line(monkeypatch):
    import sys

    from rcbf_ros.ros.tf2_buffer import start_tf2
    monkeypatch.setitem(sys.modules, 'tf2_ros', None)  # import tf2_ros: ImportError
    why = start_tf2(object(), lambda topic, reason: None, qos=None, static_qos=None)
    assert isinstance(why, str) and why.startswith('tf2_ros is not importable ('), why
    assert '\n' not in why

"""TFMessage bytes -> checked transforms (rcbf_ros.messages.tf).

The messages are encoded by rosbags' Jazzy type store, not by the reader under test."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest
from tf_messages import tf_bytes, transform_stamped, yaw_quaternion

from rcbf_ros.messages import sensor, tf


@pytest.mark.parametrize('little_endian', [True, False])
def test_transforms_are_read_with_their_frames_stamps_and_values(little_endian):
    q = yaw_quaternion(0.3)
    data = tf_bytes(
        transform_stamped('odom', 'base_link', stamp_ns=12_000_000_345,
                          translation=(1.0, -2.0, 0.5), rotation=q),
        transform_stamped('/base_link', 'laser', stamp_ns=0, translation=(0.2, 0.0, 0.1)),
        little_endian=little_endian)
    out = tf.tf_transforms(data)
    assert isinstance(out, tf.Transforms) and out.refused == (), out
    first, second = out.transforms
    assert (first.parent, first.child, first.stamp_ns) == ('odom', 'base_link', 12_000_000_345)
    assert first.translation == (1.0, -2.0, 0.5)
    assert first.rotation == pytest.approx(q, abs=1e-15)
    assert (second.parent, second.child) == ('base_link', 'laser')  # tf2 drops the leading /
    assert second.rotation == (0.0, 0.0, 0.0, 1.0)


def test_a_quaternion_near_unit_length_is_normalised():
    out = tf.tf_transforms(tf_bytes(transform_stamped('a', 'b', rotation=(0, 0, 0, 1.004))))
    assert isinstance(out, tf.Transforms) and len(out.transforms) == 1
    assert out.transforms[0].rotation == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(('parent', 'child', 'translation', 'rotation', 'words'), [
    ('odom', 'base_link', (math.nan, 0, 0), (0, 0, 0, 1), 'translation (nan, 0, 0) is not finite'),
    ('odom', 'base_link', (0, math.inf, 0), (0, 0, 0, 1), 'is not finite'),
    ('odom', 'base_link', (0, 0, 0), (0, 0, math.nan, 1), 'rotation (0, 0, nan, 1) is not'),
    ('odom', 'base_link', (0, 0, 0), (0, 0, 0, 0), 'is not a unit quaternion'),
    ('odom', 'base_link', (0, 0, 0), (0, 0, 0, 1.01), 'is not a unit quaternion'),
    ('odom', 'base_link', (0, 0, 0), (0, 1, 0, 1), 'squared length 2'),
    ('odom', 'base_link', (2e6, 0, 0), (0, 0, 0, 1), 'beyond +-1e+06 m'),
    ('odom', 'odom', (0, 0, 0), (0, 0, 0, 1), 'a frame cannot be its own parent'),
    ('/odom', 'odom', (0, 0, 0), (0, 0, 0, 1), 'a frame cannot be its own parent'),
    ('', 'base_link', (0, 0, 0), (0, 0, 0, 1), 'empty frame id'),
    ('odom', '/', (0, 0, 0), (0, 0, 0, 1), 'empty frame id'),
])
def test_a_bad_transform_is_refused_alone_naming_its_frames(parent, child, translation,
                                                            rotation, words):
    data = tf_bytes(transform_stamped('map', 'odom'),
                    transform_stamped(parent, child, translation=translation, rotation=rotation))
    out = tf.tf_transforms(data)
    assert isinstance(out, tf.Transforms), out
    assert [(t.parent, t.child) for t in out.transforms] == [('map', 'odom')]
    (reason,) = out.refused
    assert reason.startswith('transforms[1] ') and words in reason, reason
    assert repr(parent.lstrip('/')) in reason and '\n' not in reason


def test_more_transforms_than_the_bound_refuse_the_message():
    data = tf_bytes(*[transform_stamped('a', f'b{k}') for k in range(5)])
    out = tf.tf_transforms(data, max_transforms=4)
    assert isinstance(out, sensor.Refused) and 'more than the bound 4' in out.reason


def test_a_frame_id_past_the_bound_refuses_the_message():
    data = tf_bytes(transform_stamped('a', 'b' * (tf.MAX_FRAME_ID + 1)))
    out = tf.tf_transforms(data)
    assert isinstance(out, sensor.Refused)
    assert 'transforms[0].child_frame_id' in out.reason and 'bound 1024' in out.reason


def test_a_frame_with_a_newline_is_named_on_one_line():
    out = tf.tf_transforms(tf_bytes(transform_stamped('a\nb', 'c', rotation=(0, 0, 0, 0))))
    assert isinstance(out, tf.Transforms) and "'a\\nb'" in out.refused[0]
    assert '\n' not in out.refused[0]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=7, max_size=7),
       frames=st.lists(st.text(max_size=6), min_size=2, max_size=2),
       stamp=st.integers(-2**31, 2**31 - 1), little=st.booleans(),
       cut=st.integers(0, 40), flips=st.lists(st.tuples(st.integers(0, 400),
                                                        st.integers(0, 255)), max_size=4))
def test_hostile_tf_bytes_never_raise(values, frames, stamp, little, cut, flips):
    data = bytearray(tf_bytes(transform_stamped(frames[0], frames[1], stamp_ns=0,
                                                translation=values[:3], rotation=values[3:]),
                              little_endian=little))
    data[4:8] = stamp.to_bytes(4, 'little' if little else 'big', signed=True)
    for at, byte in flips:
        if at < len(data):
            data[at] = byte
    out = tf.tf_transforms(bytes(data[:len(data) - cut]))
    if isinstance(out, sensor.Refused):
        assert '\n' not in out.reason
        return
    for transform in out.transforms:  # whatever is kept is a usable transform
        assert all(math.isfinite(v) and abs(v) <= tf.MAX_TRANSLATION
                   for v in transform.translation)
        assert math.fsum(v * v for v in transform.rotation) == pytest.approx(1.0, abs=1e-12)
        assert transform.parent and transform.child and transform.parent != transform.child
    assert all('\n' not in reason for reason in out.refused)


@given(data=st.binary(max_size=200))
def test_any_bytes_are_read_or_refused(data):
    out = tf.tf_transforms(b'\x00\x01\x00\x00' + data)
    assert isinstance(out, (tf.Transforms, sensor.Refused))

"""LaserScan and PointCloud2 bytes -> points (rcbf_ros.messages.sensor).

The messages are encoded by rosbags' Jazzy type store, not by the reader under test; the
expected points are closed forms (a scan of known ranges, a cloud built with numpy)."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_messages import cloud_bytes as _cloud_bytes
from sensor_messages import header as _header
from sensor_messages import scan_bytes as _scan_bytes
from sensor_messages import STORE as _STORE
from sensor_messages import T as _T

from rcbf_ros.messages import sensor


@pytest.mark.parametrize('little_endian', [True, False])
def test_scan_of_known_ranges_gives_known_points(little_endian):
    ranges = [1.0, math.nan, 2.0, math.inf, -math.inf, 0.05, 11.0, 10.0, 0.1]
    out = sensor.scan_points(_scan_bytes(ranges, angle_min=-0.4, increment=0.1,
                                         little_endian=little_endian))
    assert isinstance(out, sensor.SensorPoints), out
    kept = [(i, r) for i, r in enumerate(ranges) if i in (0, 2, 7, 8)]
    expected = [(np.float32(r) * math.cos(np.float32(-0.4) + i * np.float32(0.1)),
                 np.float32(r) * math.sin(np.float32(-0.4) + i * np.float32(0.1)))
                for i, r in kept]
    np.testing.assert_allclose(out.points, expected, atol=1e-6)
    assert out.frame_id == 'laser' and out.stamp_ns == 12_000_000_345
    assert out.received == len(ranges) and out.spread == 0.0


def test_empty_scan_gives_no_points():
    out = sensor.scan_points(_scan_bytes([]))
    assert isinstance(out, sensor.SensorPoints) and out.points.shape == (0, 2)


@pytest.mark.parametrize(('field', 'value', 'words'), [
    ('angle_min', math.nan, 'angle_min'), ('increment', math.inf, 'angle_increment'),
    ('range_min', math.nan, 'range_min'), ('range_max', math.nan, 'range_max'),
    ('range_min', 20.0, 'range_min'), ('angle_min', 3e38, 'angle_min'),
    ('increment', 1e37, 'beyond')])
def test_scan_with_bad_geometry_is_refused(field, value, words):
    out = sensor.scan_points(_scan_bytes([1.0, 2.0], **{field: value}))
    assert isinstance(out, sensor.Refused) and words in out.reason and '\n' not in out.reason


def test_scan_past_the_bound_is_refused_in_one_line():
    out = sensor.scan_points(_scan_bytes(np.ones(50)), max_points=49)
    assert isinstance(out, sensor.Refused) and 'bound 49' in out.reason


def test_a_point_far_from_the_frame_origin_is_kept_and_one_past_any_state_refuses():
    # the distance that counts is the robot's (sources.MAX_RANGE), not the frame origin's
    out = sensor.scan_points(_scan_bytes([1.0, 2e4, 3.0], range_max=1e30))
    assert isinstance(out, sensor.SensorPoints) and len(out.points) == 3
    out = sensor.cloud_points(_cloud_bytes(np.array([[2e4, -3e7, 0.2], [1.0, 1.0, 0.2]])))
    assert isinstance(out, sensor.SensorPoints) and len(out.points) == 2
    out = sensor.scan_points(_scan_bytes([1.0, 2e15, 3.0], range_max=math.inf))
    assert isinstance(out, sensor.Refused) and 'ranges[1]' in out.reason
    out = sensor.cloud_points(_cloud_bytes(np.array([[1.0, 2e15, 0.2]]), dtype='<f8'))
    assert isinstance(out, sensor.Refused) and out.reason.startswith(
        f'{sensor.POINT_CLOUD2}: data: point (1, 2e+15) lies beyond')


@pytest.mark.parametrize('height, width', [(0, 3), (3, 0), (0, 0)])
def test_a_cloud_of_no_points_whose_data_holds_bytes_is_refused(height, width):
    data = bytearray(_cloud_bytes(np.ones((1, 3))))
    # height and width follow the header: encapsulation 4, stamp 8, frame_id 4 + 10 (aligned)
    at = 4 + 8 + 4 + len(b'base_link') + 1
    at += (-(at - 4)) % 4
    assert int.from_bytes(data[at:at + 8], 'little') == 1 | (1 << 32)
    data[at:at + 8] = height.to_bytes(4, 'little') + width.to_bytes(4, 'little')
    out = sensor.cloud_points(bytes(data))
    assert isinstance(out, sensor.Refused)
    assert (f'height {height} x width {width} declares no point, but data has 12 bytes'
            in out.reason)


def test_a_cloud_whose_data_runs_past_its_rows_is_refused():
    field = _T['sensor_msgs/msg/PointField']
    fields = [field(name=a, offset=4 * k, datatype=sensor.FLOAT32, count=1)
              for k, a in enumerate('xyz')]

    def cloud(n_bytes):
        msg = _T[sensor.POINT_CLOUD2](
            header=_header(), height=1, width=1, fields=fields, is_bigendian=False,
            point_step=12, row_step=12, data=np.ones(n_bytes, np.uint8), is_dense=False)
        return bytes(_STORE.serialize_cdr(msg, sensor.POINT_CLOUD2))
    assert isinstance(sensor.cloud_points(cloud(12)), sensor.SensorPoints)
    out = sensor.cloud_points(cloud(24))
    assert isinstance(out, sensor.Refused) and 'data has 24 bytes, more than the height 1 x ' \
        'row_step 12' in out.reason


@pytest.mark.filterwarnings('error::RuntimeWarning')  # no numpy warning on the node's log
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ranges=st.lists(st.floats(width=32), max_size=40),
       angle_min=st.floats(width=32), increment=st.floats(width=32),
       cut=st.integers(0, 400), flips=st.lists(st.tuples(st.integers(0, 400),
                                                          st.integers(0, 255)), max_size=4))
def test_hostile_scan_bytes_never_raise(ranges, angle_min, increment, cut, flips):
    data = bytearray(_scan_bytes(ranges, angle_min=angle_min, increment=increment,
                                 range_max=math.inf))
    for where, value in flips:
        if where < len(data):
            data[where] = value
    data = bytes(data[:max(len(data) - cut, 0)])
    out = sensor.scan_points(data)
    if isinstance(out, sensor.Refused):
        assert out.reason and '\n' not in out.reason and len(out.reason) <= 300
    else:
        assert out.points.ndim == 2 and out.points.shape[1] == 2
        assert np.all(np.isfinite(out.points))
        assert np.all(np.abs(out.points) <= sensor.MAX_COORDINATE)
        assert len(out.points) <= out.received <= sensor.MAX_POINTS


@pytest.mark.parametrize(('dtype', 'layout', 'pad', 'height', 'row_pad', 'little_endian'), [
    ('<f4', ('x', 'y', 'z'), 0, 1, 0, True),
    ('>f4', ('z', 'x', 'y'), 3, 2, 5, True),
    ('<f8', ('y', 'z', 'x'), 1, 4, 0, False),
    ('>f8', ('x', 'y', 'z'), 8, 3, 9, False)])
def test_cloud_built_with_numpy_gives_its_points(dtype, layout, pad, height, row_pad,
                                                 little_endian):
    rng = np.random.default_rng(3)
    points = rng.uniform(-5.0, 5.0, (120, 3))
    points[::7, 0] = np.nan
    data = _cloud_bytes(points, dtype=dtype, layout=layout, pad=pad, height=height,
                        row_pad=row_pad, little_endian=little_endian)
    out = sensor.cloud_points(data, min_height=-1.0, max_height=2.0)
    assert isinstance(out, sensor.SensorPoints), out
    stored = points.astype(dtype).astype(np.float64)
    keep = (stored[:, 2] >= -1.0) & (stored[:, 2] <= 2.0) & np.isfinite(stored[:, 0])
    np.testing.assert_array_equal(out.points, stored[keep, :2])
    assert out.frame_id == 'base_link' and out.received == 120


def test_cloud_thinning_keeps_every_point_within_spread_of_a_centre():
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.uniform(-3.0, 3.0, (500, 2)), np.zeros((500, 1))], axis=1)
    out = sensor.cloud_points(_cloud_bytes(points), voxel_size=0.5)
    assert isinstance(out, sensor.SensorPoints)
    assert len(out.points) < 500 and out.spread == pytest.approx(0.5 * math.sqrt(0.5))
    stored = points[:, :2].astype(np.float32).astype(np.float64)
    distance = np.linalg.norm(stored[:, None, :] - out.points[None, :, :], axis=2).min(axis=1)
    assert np.all(distance <= out.spread + 1e-9)
    assert len(np.unique(out.points, axis=0)) == len(out.points)


def _fields(**changes):
    field = _T['sensor_msgs/msg/PointField']
    spec = {'x': (0, sensor.FLOAT32), 'y': (4, sensor.FLOAT32), 'z': (8, sensor.FLOAT32)}
    spec.update(changes)
    return [field(name=name, offset=offset, datatype=datatype, count=1)
            for name, (offset, datatype) in spec.items() if offset is not None]


@pytest.mark.parametrize(('kwargs', 'words'), [
    ({'fields': _fields(x=(None, None))}, "no field 'x'"),
    ({'fields': _fields(z=(10, sensor.FLOAT32))}, 'past point_step'),
    ({'fields': _fields(y=(4, 5))}, 'datatype 5'),
    ({'fields': _fields(y=(0, sensor.FLOAT32))}, "fields 'x' and 'y' overlap"),
    ({'fields': _fields(z=(2, sensor.FLOAT32))}, "fields 'x' and 'z' overlap"),
    ({'fields': _fields(x=(0, sensor.FLOAT64), y=(8, sensor.FLOAT32),
                        z=(4, sensor.FLOAT32))}, "fields 'x' and 'z' overlap"),
    ({'data_cut': 1}, 'fewer than'),
    ({'height': 2, 'data_cut': 13}, 'fewer than')])
def test_cloud_with_wrong_layout_is_refused(kwargs, words):
    points = np.ones((10, 3))
    out = sensor.cloud_points(_cloud_bytes(points, **kwargs))
    assert isinstance(out, sensor.Refused), out
    assert words in out.reason and '\n' not in out.reason


def test_cloud_past_the_bound_is_refused():
    out = sensor.cloud_points(_cloud_bytes(np.ones((30, 3))), max_points=29)
    assert isinstance(out, sensor.Refused) and 'bound 29' in out.reason


def test_cloud_declaring_absurd_sizes_is_refused_without_allocating():
    msg = _T[sensor.POINT_CLOUD2](
        header=_header(), height=2**31, width=2**31, fields=_fields(), is_bigendian=False,
        point_step=12, row_step=12, data=np.zeros(12, np.uint8), is_dense=True)
    data = bytes(_STORE.serialize_cdr(msg, sensor.POINT_CLOUD2))
    out = sensor.cloud_points(data)
    assert isinstance(out, sensor.Refused) and 'height x width' in out.reason


@pytest.mark.filterwarnings('error::RuntimeWarning')
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(0, 30), height=st.sampled_from([1, 2, 3]),
       cut=st.integers(0, 300), voxel=st.sampled_from([0.0, 0.25]),
       flips=st.lists(st.tuples(st.integers(0, 600), st.integers(0, 255)), max_size=4),
       seed=st.integers(0, 2**16))
def test_hostile_cloud_bytes_never_raise(n, height, cut, voxel, flips, seed):
    points = np.random.default_rng(seed).normal(0.0, 1e3, (n * height, 3))
    data = bytearray(_cloud_bytes(points, height=height))
    for where, value in flips:
        if where < len(data):
            data[where] = value
    data = bytes(data[:max(len(data) - cut, 0)])
    out = sensor.cloud_points(data, min_height=-1e9, max_height=1e9, voxel_size=voxel)
    if isinstance(out, sensor.Refused):
        assert out.reason and '\n' not in out.reason and len(out.reason) <= 300
    else:
        assert out.points.ndim == 2 and out.points.shape[1] == 2
        assert np.all(np.isfinite(out.points))
        assert np.all(np.abs(out.points) <= sensor.MAX_COORDINATE + max(voxel, out.spread))


def test_bad_voxel_size_is_refused():
    out = sensor.cloud_points(_cloud_bytes(np.ones((3, 3))), voxel_size=1e-9)
    assert isinstance(out, sensor.Refused) and 'voxel_size' in out.reason


def _floats_of_bits(bits) -> np.ndarray:
    """float32 values of raw bit patterns (signalling NaNs kept as they are)."""
    return np.frombuffer(np.asarray(bits, dtype='<u4').tobytes(), dtype='<f4')


_SIGNALLING_NAN = 0x7F800001
"""A float32 signalling NaN: its cast to float64 raises numpy's 'invalid value' flag."""


def _finite_or_beyond(out) -> None:
    """Finite points, or the refusal of a value past any state (sensor.MAX_COORDINATE)."""
    if isinstance(out, sensor.Refused):
        assert 'lies beyond' in out.reason and '\n' not in out.reason, out.reason
    else:
        assert np.all(np.isfinite(out.points))
        assert np.all(np.abs(out.points) <= sensor.MAX_COORDINATE + max(1.0, out.spread))


@pytest.mark.filterwarnings('error::RuntimeWarning')  # no numpy warning on the node's log
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bits=st.lists(st.one_of(st.just(_SIGNALLING_NAN), st.integers(0, 2**32 - 1)),
                     min_size=1, max_size=30))
def test_scan_of_any_bit_pattern_warns_nothing(bits):
    out = sensor.scan_points(_scan_bytes(_floats_of_bits(bits), range_max=math.inf))
    _finite_or_beyond(out)


@pytest.mark.filterwarnings('error::RuntimeWarning')
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bits=st.lists(st.one_of(st.just(_SIGNALLING_NAN), st.integers(0, 2**32 - 1)),
                     min_size=3, max_size=60).map(lambda b: b[:len(b) - len(b) % 3]),
       voxel=st.sampled_from([0.0, 0.25]))
def test_cloud_of_any_bit_pattern_warns_nothing(bits, voxel):
    points = _floats_of_bits(bits).reshape(-1, 3)
    out = sensor.cloud_points(_cloud_bytes(points), min_height=-math.inf,
                              max_height=math.inf, voxel_size=voxel)
    _finite_or_beyond(out)


@pytest.mark.parametrize('frame_id', ['f' * sensor.MAX_FRAME_ID, 'é' * sensor.MAX_FRAME_ID,
                                      '\U0001F600' * sensor.MAX_FRAME_ID])
def test_frame_id_of_the_bound_in_characters_is_kept(frame_id):
    out = sensor.scan_points(_scan_bytes([1.0], frame_id=frame_id))
    assert isinstance(out, sensor.SensorPoints) and out.frame_id == frame_id


@pytest.mark.parametrize('frame_id', ['f' * (sensor.MAX_FRAME_ID + 1),
                                      'é' * (sensor.MAX_FRAME_ID + 1),
                                      '\U0001F600' * (sensor.MAX_FRAME_ID + 1)])
def test_frame_id_past_the_bound_is_refused_in_characters(frame_id):
    out = sensor.scan_points(_scan_bytes([1.0], frame_id=frame_id))
    assert isinstance(out, sensor.Refused) and 'header.frame_id' in out.reason
    assert '\n' not in out.reason


@settings(max_examples=60, deadline=None)
@given(centre=st.sampled_from([0.0, 1e4, -3e7, 1e12, -1e15 + 10.0]),
       voxel=st.sampled_from([sensor.MIN_VOXEL_SIZE, 0.05, 1.0]),
       seed=st.integers(0, 2**16))
def test_thinning_covers_every_point_however_far_from_the_frame_origin(centre, voxel, seed):
    rng = np.random.default_rng(seed)
    points = np.column_stack([centre + rng.uniform(-3.0, 3.0, 200),
                              -centre + rng.uniform(-3.0, 3.0, 200), np.full(200, 0.2)])
    out = sensor.cloud_points(_cloud_bytes(points, dtype='<f8'), voxel_size=voxel)
    assert isinstance(out, sensor.SensorPoints) and 0 < len(out.points) <= 200
    gaps = np.hypot(*(points[:, None, :2] - out.points[None]).transpose(2, 0, 1))
    assert np.all(gaps.min(axis=1) <= out.spread * (1 + 1e-12))


def _beam_points(ranges, angle_min, increment, range_min, range_max):
    """A scan's points in float64 from its float32 fields, every beam's angle computed anew:
    the reader's beam directions are kept per geometry, this oracle keeps nothing."""
    r = np.asarray(ranges, dtype=np.float32).astype(np.float64)
    angles = (float(np.float32(angle_min))
              + np.arange(len(r)) * float(np.float32(increment)))
    valid = (r >= float(np.float32(range_min))) & (r <= float(np.float32(range_max)))
    return np.column_stack([r[valid] * np.cos(angles[valid]), r[valid] * np.sin(angles[valid])])


_GEOMETRIES = st.tuples(st.sampled_from([0.0, -0.0, -3.0, 0.5, -math.pi, 1e-30]),
                        st.sampled_from([0.0, -0.0, 0.1, -0.1, 2 * math.pi / 360, 0.2]),
                        st.integers(0, 40))


@settings(max_examples=80, deadline=None)
@given(geometries=st.lists(_GEOMETRIES, min_size=2, max_size=12))
def test_scans_of_changing_geometry_give_the_points_of_their_own_beams(geometries):
    # one sensor after another (or one whose angle_min, angle_increment or beam count changes):
    # each scan's points are those of its own beams, bit for bit (the sign of a zero too),
    # whatever scans came before
    for angle_min, increment, count in geometries:
        ranges = 0.5 + 0.25 * np.arange(count)
        out = sensor.scan_points(_scan_bytes(ranges, angle_min=angle_min, increment=increment))
        assert isinstance(out, sensor.SensorPoints), out
        expected = _beam_points(ranges, angle_min, increment, 0.1, 10.0)
        assert out.points.shape == expected.shape
        assert out.points.tobytes() == np.ascontiguousarray(expected).tobytes(), (
            angle_min, increment, count)


def test_a_scan_whose_angle_min_is_minus_zero_is_not_read_with_plus_zeros_beams():
    # 0.0 and -0.0 are equal numbers, but the first beam's sine, and so its y, differs in sign
    ranges = [1.0, 2.0]
    for angle_min in (0.0, -0.0, 0.0):
        out = sensor.scan_points(_scan_bytes(ranges, angle_min=angle_min, increment=-0.1))
        assert isinstance(out, sensor.SensorPoints), out
        assert math.copysign(1.0, out.points[0, 1]) == math.copysign(1.0, angle_min)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ranges=st.lists(st.floats(-1e6, 1e6, width=32) | st.sampled_from([math.inf, math.nan]),
                       min_size=0, max_size=40),
       range_min=st.sampled_from([0.0, 0.1, -1e6]),
       angle_min=st.floats(-4.0, 4.0), increment=st.floats(-0.5, 0.5))
def test_a_scan_bounds_its_points_distance_from_the_frame_origin(ranges, range_min, angle_min,
                                                                 increment):
    out = sensor.scan_points(_scan_bytes(ranges, angle_min=angle_min, increment=increment,
                                         range_min=range_min, range_max=1e6))
    assert isinstance(out, sensor.SensorPoints), out
    if range_min < 0.0:  # a negative range: a point behind the beam, no bound given
        assert out.reach == math.inf
        return
    assert out.reach < math.inf
    distance = np.hypot(*out.points.T)
    assert (distance <= out.reach * (1 + 1e-12)).all()
    if len(distance):
        assert out.reach <= distance.max() * (1 + 1e-12)  # the largest range: no wider

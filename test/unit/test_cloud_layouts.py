"""PointCloud2 field layouts: a cloud is read only where its x, y and z are unambiguous.

Each of x, y, z declared once, its bytes (count x the datatype's size) within point_step and
apart from the other two; any other layout is refused in one line naming the field. The
messages are encoded by rosbags' Jazzy type store, not by the reader under test.
"""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from sensor_messages import header, STORE, T

from rcbf_ros.messages import sensor

SIZES = {sensor.FLOAT32: 4, sensor.FLOAT64: 8}
COORDINATES = ('x', 'y', 'z')


def _cloud(fields: list[tuple[str, int, int, int]], point_step: int,
           values: dict[str, float]) -> bytes:
    """A cloud of two points on ``fields`` ((name, offset, datatype, count) each); the bytes
    of a point random but for the first element of each once-declared x, y, z field, which
    holds ``values``."""
    rng = np.random.default_rng(point_step)
    point = bytearray(rng.integers(0, 256, point_step, dtype=np.uint8).tobytes())
    names = [name for name, *_ in fields]
    for name, offset, datatype, _ in fields:
        size = SIZES.get(datatype)
        if name in values and names.count(name) == 1 and size and offset + size <= point_step:
            point[offset:offset + size] = np.array(
                [values[name]], '<f4' if size == 4 else '<f8').tobytes()
    field = T['sensor_msgs/msg/PointField']
    msg = T[sensor.POINT_CLOUD2](
        header=header('base_link'), height=1, width=2,
        fields=[field(name=name, offset=offset, datatype=datatype, count=count)
                for name, offset, datatype, count in fields],
        is_bigendian=False, point_step=point_step, row_step=2 * point_step,
        data=np.frombuffer(bytes(point) * 2, np.uint8), is_dense=True)
    return bytes(STORE.serialize_cdr(msg, sensor.POINT_CLOUD2))


any_field = st.tuples(st.sampled_from(['x', 'y', 'z', 'intensity', 'rgb']), st.integers(0, 40),
                      st.sampled_from([sensor.FLOAT32, sensor.FLOAT64, 2]), st.integers(0, 4))
any_layout = st.tuples(st.lists(any_field, max_size=7), st.integers(0, 48))


@st.composite
def near_layout(draw: st.DrawFn) -> tuple[list[tuple[str, int, int, int]], int]:
    """x, y, z once each, packed in a random order with gaps that may be negative (an
    overlap) and a point_step that may cut the last one short; a few other fields (maybe a
    coordinate again) on top."""
    fields, end = [], 0
    for name in draw(st.permutations(COORDINATES)):
        datatype = draw(st.sampled_from(list(SIZES)))
        count = draw(st.sampled_from([1, 1, 1, 2, 3, 0]))
        offset = max(0, end + draw(st.integers(-6, 4)))
        fields.append((name, offset, datatype, count))
        end = max(end, offset + count * SIZES[datatype])
    extra = draw(st.lists(any_field, max_size=2))
    fields = draw(st.permutations(fields + extra))
    return fields, max(0, end + draw(st.integers(-4, 8)))


@settings(max_examples=400, deadline=None)
@given(layout=st.one_of(any_layout, near_layout()))
def test_an_accepted_layout_is_unambiguous_and_a_refused_one_names_the_field(layout):
    fields, point_step = layout
    values = {'x': 1.5, 'y': -2.25, 'z': 0.125}
    out = sensor.cloud_points(_cloud(fields, point_step, values))
    declared = {axis: [f for f in fields if f[0] == axis] for axis in COORDINATES}
    if isinstance(out, sensor.Refused):
        assert '\n' not in out.reason
        assert any(f"'{axis}'" in out.reason for axis in COORDINATES), out.reason
        return
    spans = []
    for axis in COORDINATES:
        assert len(declared[axis]) == 1, (axis, fields)  # declared once
        _, offset, datatype, count = declared[axis][0]
        assert datatype in SIZES and count >= 1
        spans.append((offset, offset + count * SIZES[datatype]))
    assert all(end <= point_step for _, end in spans)  # within point_step
    for a in range(3):  # apart
        for b in range(a + 1, 3):
            assert spans[a][1] <= spans[b][0] or spans[b][1] <= spans[a][0], spans
    np.testing.assert_array_equal(out.points, [[1.5, -2.25], [1.5, -2.25]])


def test_a_coordinate_declared_twice_is_refused_whichever_comes_first():
    # the first x on padding bytes would put every point at x = 0
    for first, second in ((12, 0), (0, 12)):
        fields = [('x', first, sensor.FLOAT32, 1), ('x', second, sensor.FLOAT32, 1),
                  ('y', 4, sensor.FLOAT32, 1), ('z', 8, sensor.FLOAT32, 1)]
        out = sensor.cloud_points(_cloud(fields, 16, {}))
        assert out == sensor.Refused(f"{sensor.POINT_CLOUD2}: field 'x' is declared twice "
                                     '(fields[0] and fields[1])')


def test_a_field_whose_count_reaches_into_another_is_refused():
    fields = [('x', 0, sensor.FLOAT32, 3), ('y', 4, sensor.FLOAT32, 1),
              ('z', 8, sensor.FLOAT32, 1)]
    out = sensor.cloud_points(_cloud(fields, 12, {}))
    assert isinstance(out, sensor.Refused) and "fields 'x' and 'y' overlap" in out.reason
    fields = [('x', 0, sensor.FLOAT32, 1), ('y', 4, sensor.FLOAT32, 1),
              ('z', 8, sensor.FLOAT32, 2)]
    out = sensor.cloud_points(_cloud(fields, 12, {}))
    assert isinstance(out, sensor.Refused) and "field 'z' at offset 8 (2 x 4 bytes) ends past " \
        'point_step 12' in out.reason


def test_a_repeated_field_that_is_not_a_coordinate_is_no_matter():
    fields = [('x', 0, sensor.FLOAT32, 1), ('y', 4, sensor.FLOAT32, 1),
              ('z', 8, sensor.FLOAT32, 1), ('intensity', 12, sensor.FLOAT32, 1),
              ('intensity', 12, sensor.FLOAT32, 1)]
    out = sensor.cloud_points(_cloud(fields, 16, {'x': 3.0, 'y': 4.0, 'z': 0.0}))
    assert isinstance(out, sensor.SensorPoints)
    np.testing.assert_array_equal(out.points, [[3.0, 4.0], [3.0, 4.0]])

"""Points from a sensor: sensor_msgs/LaserScan, PointCloud2 and Range CDR bytes -> (N, 2).

The filter keeps the robot off every valid point of a scan or cloud; this module reads those
points straight from the CDR bytes a subscription receives (with its 4-byte encapsulation
header, either byte order), vectorised, without building a message: a scan of 2,000 beams or a
cloud of 24k points is read in tens of microseconds. The layout is the Jazzy definitions of
:func:`rcbf_ros.messages.typestore.jazzy_typestore` (the tests encode with rosbags).

Every size is bounded before it is used (:data:`MAX_POINTS` points per message,
:data:`MAX_FIELDS` fields, :data:`MAX_FRAME_ID` bytes of frame id, :data:`MAX_POINT_STEP`
bytes per point), and bytes that do not fit the declared layout are refused: the readers
return :class:`Refused` with one line naming the field, and never raise. Which points count
(REP 117 for scans): NaN, +-inf and ranges outside [range_min, range_max] are skipped; a
Range's reading is an arc of points (:func:`range_points`). A point
is never skipped for its distance from the frame's origin (a cloud in ``odom`` lies wherever
the robot is): one beyond :data:`MAX_COORDINATE`, where no state may lie, refuses the message;
the distance that counts is the robot's, once the points are placed
(:data:`rcbf_ros.node_logic.sources.MAX_RANGE`). Pure library: numpy only.
"""
from __future__ import annotations

import functools
import math
import struct
from typing import Any, Callable, NamedTuple

import numpy as np

LASER_SCAN = 'sensor_msgs/msg/LaserScan'
POINT_CLOUD2 = 'sensor_msgs/msg/PointCloud2'
RANGE = 'sensor_msgs/msg/Range'

MAX_POINTS = 200_000
"""The most beams of a scan or points (height x width) of a cloud read from one message; a
larger one is refused (a 3-D lidar's full cloud is ~100k points)."""
MAX_FIELDS = 64
"""The most PointField entries of a cloud."""
MAX_FRAME_ID = 1024
"""The most characters of a header's frame_id (and of a PointField name): the CDR length,
which counts the terminating NUL and UTF-8 bytes, may be up to 4 x this + 1."""
MAX_POINT_STEP = 65_536
"""The most bytes per point of a cloud."""
MAX_COORDINATE = 1.0e15
"""The largest |x| or |y| (m) of a point; a message with a point beyond is refused. No state
lies beyond (``input_bounds.state`` is at most the QP's data limit, 1e15), and the squares of
the barrier stay finite."""
MAX_ANGLE = 1.0e3
"""The largest |angle| (rad) of a scan's beam; a scan whose beams lie beyond is refused."""
MIN_VOXEL_SIZE = 1.0e-3
"""The smallest grid cell (m) of a cloud's thinning (0 turns thinning off)."""
_FULL_TURN = float(np.float32(2.0 * math.pi))
"""2 pi as a float32 field holds it (rounded up): a full turn's field of view."""
MIN_OBSTACLES_ANGLE = 1.0e-3
"""The smallest angle (rad) between the points of a Range's arc: at most 2 pi / this + 1
points, 6,285."""

FLOAT32, FLOAT64 = 7, 8
"""sensor_msgs/PointField datatypes of the coordinates read here."""
_FIELD_SIZE = {FLOAT32: 4, FLOAT64: 8}
_COORDINATES = ('x', 'y', 'z')
"""The fields read from a cloud: each declared once, their bytes disjoint within a point."""


class SensorPoints(NamedTuple):
    """The valid points of one message, in the message's frame."""

    points: np.ndarray
    """(N, 2) float64 x, y of each valid point (a cloud: after the z band and thinning)."""
    frame_id: str
    """header.frame_id."""
    stamp_ns: int
    """header.stamp in nanoseconds."""
    received: int
    """The beams or points the message carried (valid or not)."""
    spread: float = 0.0
    """How far (m) a point read from the message may lie from the point that stands for it
    here: half a thinning cell's diagonal, else 0. A source widens its obstacles by it."""
    reach: float = math.inf
    """A bound (m) on every point's distance from the frame's origin, where the read gives
    one for free (a scan's largest valid range, range_min >= 0), else inf."""


class Refused(NamedTuple):
    """A message that cannot be read: one line naming the field."""

    reason: str


class _Bad(ValueError):
    """A layout error inside a reader (becomes :class:`Refused`)."""


_WORDS = {order: (struct.Struct(order + 'I').unpack_from, struct.Struct(order + 'i').unpack_from)
          for order in '<>'}
"""Per byte order, the unpacking of a CDR uint32 and int32."""


class _Cursor:
    """Reads CDR primitives with CDR alignment (relative to the body, after the header)."""

    def __init__(self, data: bytes | memoryview) -> None:
        view = memoryview(data).cast('B')
        if len(view) < 4 or view[0] != 0 or view[1] not in (0, 1):
            raise _Bad('not a plain CDR sample (encapsulation header '
                       f'{bytes(view[:4]).hex() or "missing"})')
        self.little = view[1] == 1
        self.order = '<' if self.little else '>'
        self._uint32, self._int32 = _WORDS[self.order]
        self.view = view
        self.body = 4
        self.pos = 4

    def _take(self, size: int, align: int, what: str) -> int:
        self.pos += (-(self.pos - self.body)) % align
        start = self.pos
        if start + size > len(self.view):
            raise _Bad(f'{what}: the message ends at byte {len(self.view)}, before its '
                       f'{size} bytes at {start}')
        self.pos = start + size
        return start

    def uint32(self, what: str) -> int:
        start = self._take(4, 4, what)
        return self._uint32(self.view, start)[0]

    def int32(self, what: str) -> int:
        start = self._take(4, 4, what)
        return self._int32(self.view, start)[0]

    def uint8(self, what: str) -> int:
        return self.view[self._take(1, 1, what)]

    def float32s(self, count: int, what: str) -> tuple[float, ...]:
        start = self._take(4 * count, 4, what)
        return struct.unpack_from(f'{self.order}{count}f', self.view, start)

    def float64s(self, count: int, what: str) -> tuple[float, ...]:
        start = self._take(8 * count, 8, what)
        return struct.unpack_from(f'{self.order}{count}d', self.view, start)

    def string(self, what: str, bound: int) -> str:
        """A CDR string of at most ``bound`` characters (its length counts the terminating
        NUL and each UTF-8 byte: the bytes are bounded first, then the characters)."""
        size = self.uint32(what)
        if size > 4 * bound + 1:
            raise _Bad(f'{what}: {size} bytes, more than {bound} characters can take')
        start = self._take(size, 1, what)
        raw = bytes(self.view[start:start + size])
        if raw.endswith(b'\x00'):
            raw = raw[:-1]
        try:
            text = raw.decode('utf-8')
        except UnicodeDecodeError:
            raise _Bad(f'{what}: not UTF-8') from None
        if len(text) > bound:
            raise _Bad(f'{what}: {len(text)} characters, more than the bound {bound}')
        return text

    def header(self) -> tuple[str, int]:
        sec = self.int32('header.stamp.sec')
        nanosec = self.uint32('header.stamp.nanosec')
        frame_id = self.string('header.frame_id', MAX_FRAME_ID)
        return frame_id, sec * 1_000_000_000 + nanosec


def _check_bounds(low: tuple[str, float], high: tuple[str, float]) -> None:
    """Refuse range bounds (name, value) that are NaN or crossed."""
    for name, value in (low, high):
        if value != value:
            raise _Bad(f'{name} is nan')
    if low[1] > high[1]:
        raise _Bad(f'{low[0]} {low[1]} > {high[0]} {high[1]}')


def _beyond(what: str, x: np.ndarray, y: np.ndarray) -> None:
    """Refuse points beyond :data:`MAX_COORDINATE` (x, y finite)."""
    far = np.flatnonzero((np.abs(x) > MAX_COORDINATE) | (np.abs(y) > MAX_COORDINATE))
    if far.size:
        raise _Bad(f'{what}: point ({x[far[0]]:.6g}, {y[far[0]]:.6g}) lies beyond '
                   f'{MAX_COORDINATE:g} m of the frame (and {far.size - 1} more)')


def _beam_directions(angle_min: float, increment: float, count: int) -> np.ndarray:
    """(2, count) read-only: the cos, then the sin, of beam i's angle angle_min + i increment. A
    sensor repeats its geometry in every message, so they are computed once per geometry
    (:func:`_directions`): keyed on the values exactly, the sign of a zero included (0.0 and
    -0.0 are equal keys, but their beams' sines differ in sign)."""
    return _directions(angle_min, increment, count, math.copysign(1.0, angle_min),
                       math.copysign(1.0, increment))


@functools.lru_cache(maxsize=8)
def _directions(angle_min: float, increment: float, count: int, _sign_min: float,
                _sign_increment: float) -> np.ndarray:
    """:func:`_beam_directions`, computed (the signs only key the cache)."""
    angles = angle_min + np.arange(count) * increment
    directions = np.empty((2, count))
    np.cos(angles, out=directions[0])
    np.sin(angles, out=directions[1])
    directions.setflags(write=False)
    return directions


def _quiet(parse: Callable[..., SensorPoints | Refused]) -> Callable[..., SensorPoints | Refused]:
    """``parse`` with numpy's floating-point warnings off: the bytes are untrusted, and a
    signalling NaN or an overflow in a cast or product is a value the parse drops (NaN fails
    every comparison), not a warning on the node's log."""
    if _GET_ERROR_OBJECT is not None:
        # numpy 1.x: the thread's error object set directly, its mask 0 (every error ignored),
        # as np.errstate(all='ignore') sets it through two dictionaries each way
        @functools.wraps(parse)
        def quiet(*args: Any, **kwargs: Any) -> SensorPoints | Refused:
            previous = _GET_ERROR_OBJECT()
            _SET_ERROR_OBJECT([previous[0], 0, previous[2]])
            try:
                return parse(*args, **kwargs)
            finally:
                _SET_ERROR_OBJECT(previous)
        return quiet

    @functools.wraps(parse)
    def quiet_state(*args: Any, **kwargs: Any) -> SensorPoints | Refused:
        with np.errstate(all='ignore'):
            return parse(*args, **kwargs)
    return quiet_state


def _reader(kind: str) -> Callable[[Callable[..., SensorPoints | Refused]],
                                   Callable[..., SensorPoints | Refused]]:
    """A reader of ``kind`` messages that never raises: :func:`_quiet`, and any failure inside
    (a layout error, :class:`_Bad`, or any other: the bytes are untrusted) a
    :class:`Refused` of one line naming ``kind``."""
    def wrap(parse: Callable[..., SensorPoints | Refused]
             ) -> Callable[..., SensorPoints | Refused]:
        @functools.wraps(parse)
        def read(*args: Any, **kwargs: Any) -> SensorPoints | Refused:
            try:
                return parse(*args, **kwargs)
            except _Bad as exc:
                return Refused(f'{kind}: {exc}')
            except Exception as exc:
                return Refused(f'{kind}: {type(exc).__name__}: '
                               f'{" ".join(str(exc).split())}'[:200])
        return _quiet(read)
    return wrap


_GET_ERROR_OBJECT = getattr(np, 'geterrobj', None)
_SET_ERROR_OBJECT = getattr(np, 'seterrobj', None)
"""numpy 1.x's per-thread floating-point error object (numpy 2 has none: its errstate is a
context variable, cheap to set)."""


def _thinned(x: np.ndarray, y: np.ndarray, voxel_size: float
             ) -> tuple[np.ndarray, np.ndarray, float]:
    """The centres of the grid cells (side ``voxel_size``) that hold the points, and how far
    a point lies from its cell's centre at most: half the diagonal, or the rounding of a cell
    index far from the origin, measured (|x|, |y| <= :data:`MAX_COORDINATE` and voxel_size
    >= :data:`MIN_VOXEL_SIZE` keep each index within int64)."""
    column = np.floor(x / voxel_size).astype(np.int64)
    row = np.floor(y / voxel_size).astype(np.int64)
    centre_x, centre_y = (column + 0.5) * voxel_size, (row + 0.5) * voxel_size
    spread = max(voxel_size * math.sqrt(0.5),
                 float(np.hypot(x - centre_x, y - centre_y).max()))
    column_0, row_0 = int(column.min()), int(row.min())
    column, row = column - column_0, row - row_0
    span = int(row.max()) + 1
    if (int(column.max()) + 1) * span < 2 ** 63:  # one int64 key per cell
        keys = np.unique(column * span + row)
        column, row = np.divmod(keys, span)
    else:
        order = np.lexsort((row, column))
        column, row = column[order], row[order]
        first = np.concatenate(([True], (column[1:] != column[:-1]) | (row[1:] != row[:-1])))
        column, row = column[first], row[first]
    return ((column + column_0 + 0.5) * voxel_size, (row + row_0 + 0.5) * voxel_size, spread)


@_reader(LASER_SCAN)
def scan_points(data: bytes | memoryview, *, max_points: int = MAX_POINTS
                ) -> SensorPoints | Refused:
    """The valid points of a LaserScan sample, in its frame.

    Beam i lies at angle_min + i angle_increment; it counts where its range r is finite and
    range_min <= r <= range_max (REP 117, as collision_monitor reads it), and is the point
    (r cos a, r sin a); a range beyond :data:`MAX_COORDINATE` refuses the scan. Intensities
    are not read.
    """
    cursor = _Cursor(data)
    frame_id, stamp = cursor.header()
    (angle_min, _angle_max, increment, _time_increment, _scan_time, range_min,
     range_max) = cursor.float32s(7, 'angle_min..range_max')
    if not (math.isfinite(angle_min) and math.isfinite(increment)):
        name, value = (('angle_min', angle_min) if not math.isfinite(angle_min)
                       else ('angle_increment', increment))
        return Refused(f'{LASER_SCAN}: {name} is {value}')
    _check_bounds(('range_min', range_min), ('range_max', range_max))
    count = cursor.uint32('ranges')
    if count > max_points:
        return Refused(f'{LASER_SCAN}: ranges has {count} beams, more than the bound '
                       f'{max_points}')
    if not abs(angle_min) + count * abs(increment) <= MAX_ANGLE:
        return Refused(f'{LASER_SCAN}: angle_min {angle_min:g} and angle_increment '
                       f'{increment:g} put beams beyond +-{MAX_ANGLE:g} rad')
    start = cursor._take(4 * count, 4, 'ranges')
    ranges = np.frombuffer(cursor.view, dtype=cursor.order + 'f4', count=count,
                           offset=start).astype(np.float64)
    # NaN fails both comparisons; so do +-inf where both bounds are finite
    valid = (ranges >= max(range_min, 0.0)) & (ranges <= range_max)  # REP 117: r >= 0
    if not (math.isfinite(range_min) and math.isfinite(range_max)):
        valid &= np.isfinite(ranges)
    index = valid.nonzero()[0]  # flatnonzero's, without its ravel
    if index.size == count:  # every beam valid
        index = None
    r = ranges if index is None else ranges.take(index)
    largest = float(np.maximum.reduce(r)) if r.size else 0.0
    if not largest <= MAX_COORDINATE:
        beam = int(np.argmax(r)) if index is None else int(index[np.argmax(r)])
        return Refused(f'{LASER_SCAN}: ranges[{beam}] {ranges[beam]:.6g} lies beyond '
                       f'{MAX_COORDINATE:g} m (within range_max {range_max:g})')
    directions = _beam_directions(angle_min, increment, count)
    if index is not None:
        directions = directions.take(index, axis=1)
    # (N, 2), its columns contiguous: r cos a, r sin a
    points = np.multiply(directions, r, out=None if index is None else directions).T
    # |(r cos a, r sin a)| = r where every r >= 0 (a negative range_min: no bound)
    return SensorPoints(points, frame_id, stamp, count,
                        reach=largest if range_min >= 0.0 else math.inf)


@_reader(POINT_CLOUD2)
def cloud_points(data: bytes | memoryview, *, min_height: float = -math.inf,
                 max_height: float = math.inf, voxel_size: float = 0.0,
                 max_points: int = MAX_POINTS) -> SensorPoints | Refused:
    """The valid points of a PointCloud2 sample, in its frame.

    x, y and z are found by name in ``fields`` (FLOAT32 or FLOAT64, any offset within
    point_step, either byte order, any height); each must be declared once, and their bytes
    (count x the datatype's size each; the first element is read) lie within point_step and
    apart, else the cloud is refused naming the field. Point (row r, column c) starts at byte
    r row_step + c point_step of ``data``. A point counts where x, y and z are finite and
    min_height <= z <= max_height. With ``voxel_size`` > 0, the points are thinned on a grid of
    that cell size in x, y: each occupied cell gives its centre, and ``spread`` is half the
    cell's diagonal (every point of the cell lies within it of the centre).
    """
    if voxel_size != 0.0 and not voxel_size >= MIN_VOXEL_SIZE:
        return Refused(f'{POINT_CLOUD2}: voxel_size {voxel_size} is neither 0 nor >= '
                       f'{MIN_VOXEL_SIZE}')
    cursor = _Cursor(data)
    frame_id, stamp = cursor.header()
    height, width = cursor.uint32('height'), cursor.uint32('width')
    count = height * width
    if count > max_points:
        return Refused(f'{POINT_CLOUD2}: height x width is {count} points, more than the '
                       f'bound {max_points}')
    n_fields = cursor.uint32('fields')
    if n_fields > MAX_FIELDS:
        return Refused(f'{POINT_CLOUD2}: fields has {n_fields} entries, more than the bound '
                       f'{MAX_FIELDS}')
    fields: dict[str, tuple[int, int, int, int]] = {}  # offset, datatype, count, index
    for k in range(n_fields):
        name = cursor.string(f'fields[{k}].name', MAX_FRAME_ID)
        offset = cursor.uint32(f'fields[{k}].offset')
        datatype = cursor.uint8(f'fields[{k}].datatype')
        field_count = cursor.uint32(f'fields[{k}].count')
        if name in _COORDINATES and name in fields:  # which one is meant cannot be told
            return Refused(f'{POINT_CLOUD2}: field {name!r} is declared twice '
                           f'(fields[{fields[name][3]}] and fields[{k}])')
        fields.setdefault(name, (offset, datatype, field_count, k))
    big = bool(cursor.uint8('is_bigendian'))
    point_step = cursor.uint32('point_step')
    row_step = cursor.uint32('row_step')
    size = cursor.uint32('data')
    start = cursor._take(size, 1, 'data')
    if point_step > MAX_POINT_STEP:
        return Refused(f'{POINT_CLOUD2}: point_step {point_step} is more than the bound '
                       f'{MAX_POINT_STEP}')
    columns = []
    spans: list[tuple[int, int]] = []  # the bytes of x, y, z in a point: [begin, end)
    for axis in _COORDINATES:
        if axis not in fields:
            return Refused(f'{POINT_CLOUD2}: no field {axis!r} (fields: '
                           f'{", ".join(sorted(fields))[:100] or "none"})')
        offset, datatype, field_count, _ = fields[axis]
        if datatype not in _FIELD_SIZE:
            return Refused(f'{POINT_CLOUD2}: field {axis!r} has datatype {datatype}, not '
                           f'FLOAT32 ({FLOAT32}) or FLOAT64 ({FLOAT64})')
        if field_count < 1:
            return Refused(f'{POINT_CLOUD2}: field {axis!r} has count 0')
        end = offset + field_count * _FIELD_SIZE[datatype]  # every element of the field
        if end > point_step:
            return Refused(f'{POINT_CLOUD2}: field {axis!r} at offset {offset} ({field_count} '
                           f'x {_FIELD_SIZE[datatype]} bytes) ends past point_step '
                           f'{point_step}')
        for other, (begins, ends) in zip(_COORDINATES, spans):  # disjoint bytes of a point
            if offset < ends and begins < end:
                return Refused(f'{POINT_CLOUD2}: fields {other!r} and {axis!r} overlap '
                               f'(bytes {begins}..{ends - 1} and {offset}..{end - 1})')
        columns.append((offset, datatype))
        spans.append((offset, end))
    if count == 0:
        if size:
            return Refused(f'{POINT_CLOUD2}: height {height} x width {width} declares no '
                           f'point, but data has {size} bytes')
        return SensorPoints(np.zeros((0, 2)), frame_id, stamp, 0)
    if row_step < width * point_step:
        return Refused(f'{POINT_CLOUD2}: row_step {row_step} < width {width} x point_step '
                       f'{point_step}')
    needed = (height - 1) * row_step + width * point_step
    if size < needed:
        return Refused(f'{POINT_CLOUD2}: data has {size} bytes, fewer than the '
                       f'{needed} its height, width, row_step and point_step declare')
    if size > height * row_step:
        return Refused(f'{POINT_CLOUD2}: data has {size} bytes, more than the height '
                       f'{height} x row_step {row_step} its layout declares')
    order = '>' if big else '<'
    values = []
    for offset, datatype in columns:
        column = np.ndarray(shape=(height, width), dtype=order + ('f4' if datatype == FLOAT32
                                                                  else 'f8'),
                            buffer=cursor.view, offset=start + offset,
                            strides=(row_step, point_step))
        values.append(column.astype(np.float64).ravel())
    x, y, z = values
    keep = ((z >= min_height) & (z <= max_height) & np.isfinite(x)
            & np.isfinite(y))  # NaN fails each
    x, y = x[keep], y[keep]
    _beyond('data', x, y)
    spread = 0.0
    if voxel_size and x.size:
        x, y, spread = _thinned(x, y, voxel_size)
    return SensorPoints(np.stack((x, y), axis=1), frame_id, stamp, count, spread)


@_reader(RANGE)
def range_points(data: bytes | memoryview, *, obstacles_angle: float = math.pi / 180
                 ) -> SensorPoints | Refused:
    """The points of a Range sample (sonar, infrared ranger), in its frame.

    The object that gave the reading r may lie anywhere at distance r within the field of
    view (Range.msg draws an arc; a sonar's is a cone of half-angle a = field_of_view / 2), so
    in the plane it lies at an azimuth within +-a and at a distance between r cos a and r (a
    point of the cone off the sensor's plane projects nearer; a cone wider than a half-space,
    a > pi / 2, anywhere within r). The reading is points on the middle arc of that band,
    from -a to +a, ``obstacles_angle`` apart, the last at +a, as collision_monitor draws its
    arc; ``spread`` widens each so that their circles cover the whole band: half its width
    plus the middle radius times half the largest angle between two points (any point of
    the band lies within that of a drawn one), which collision_monitor's points do not.
    Which readings count (REP 117, Range.msg): a finite r within [min_range, max_range] is
    the band at r; -inf, an object too close to measure, is the whole sector within
    min_range; +inf (nothing within range), NaN and a finite r outside [min_range, max_range]
    give no point. A field of view that is not within [0, 2 pi], or range bounds that are NaN
    or crossed, refuse the message.
    """
    if not MIN_OBSTACLES_ANGLE <= obstacles_angle <= math.pi:
        return Refused(f'{RANGE}: obstacles_angle {obstacles_angle} is not within '
                       f'[{MIN_OBSTACLES_ANGLE}, pi]')
    cursor = _Cursor(data)
    frame_id, stamp = cursor.header()
    cursor.uint8('radiation_type')
    field_of_view, min_range, max_range, reading = cursor.float32s(
        4, 'field_of_view..range')
    if not 0.0 <= field_of_view <= _FULL_TURN:
        return Refused(f'{RANGE}: field_of_view {field_of_view} is not within [0, 2 pi]')
    _check_bounds(('min_range', min_range), ('max_range', max_range))
    half = 0.5 * field_of_view
    nearest = math.cos(half)  # of the distance r, the nearest a point of the cone projects to
    if half > 0.5 * math.pi:  # wider than a half-space: anywhere within r, at any azimuth
        half, nearest = math.pi, 0.0
    if reading == -math.inf:  # REP 117: detected, nearer than min_range
        if not min_range < math.inf:
            return Refused(f'{RANGE}: range is -inf with min_range inf')
        inner, outer = 0.0, max(min_range, 0.0)
    elif max(min_range, 0.0) <= reading <= max_range and reading < math.inf:
        inner, outer = reading * nearest, reading
    else:  # +inf: nothing within range; NaN or outside the bounds: no reading
        return SensorPoints(np.zeros((0, 2)), frame_id, stamp, 1, reach=0.0)
    if not outer <= MAX_COORDINATE:
        return Refused(f'{RANGE}: range {outer:.6g} lies beyond {MAX_COORDINATE:g} m')
    steps = math.ceil(2.0 * half / obstacles_angle)
    angles = np.append(-half + obstacles_angle * np.arange(steps), half)
    radius = 0.5 * (inner + outer)
    points = np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)
    gap = min(obstacles_angle, 2.0 * half)  # the largest angle between two drawn points
    return SensorPoints(points, frame_id, stamp, 1,
                        spread=radius * gap / 2.0 + 0.5 * (outer - inner), reach=outer)

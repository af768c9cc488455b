"""The scene markers as plain data: state + filter geometry + barrier values -> marker dicts.

What the ``scene_markers`` node publishes (:mod:`rcbf_ros.ros.scene_node`), decided here without
messages so that it is tested without DDS. Each marker is a dict with the fields of a
visualization_msgs/Marker that the node sets: ``frame_id``, ``ns``, ``id``, ``type`` (the
Marker constants below), ``position`` (x, y, z), ``orientation`` (quaternion x, y, z, w),
``scale`` (x, y, z), ``color`` (r, g, b, a) and, where used, ``points`` and ``text``.

The scene, in metres and radians (REP 103: x forward, y left, z up):

- every obstacle, up to ``max_obstacles`` of them (the nearest to the robot; a label, ns
  ``omitted``, says how many are left out): a grey cylinder at its true radius (ns
  ``obstacles``) and a ring at radius + margin (ns ``margins``) coloured by its barrier's
  value;
- every barrier's value as text (ns ``barriers``): at its obstacle, between the cars of its gap,
  or in a list beside the robot; coloured green for h >= ``caution``, amber for
  0 <= h < ``caution``, red for h < 0 and grey while unknown;
- the robot (ns ``robot``): Unicycle, an arrow at (x, y) along theta (a sphere without a
  heading index), and the look-ahead point the obstacle barriers, or the sensor points' rows,
  guard when driving forwards (ns ``lookahead``); PVTOL, in the x-z plane
  (x1 along x, x2 up along z), its body tilted by theta with the thrust arrow, and the safety
  operator's band (ns ``bands``); Car following, the five cars on the x axis (car 4, the one
  the filter drives, in blue) and a line per gap (ns ``gaps``); other systems, a sphere at the
  obstacles' (or the sensor points') position coordinates;
- the filter's last diagnostic message above the robot (ns ``status``);
- with ``footprint.radius`` > 0, the robot's footprint: a ring of that radius around its
  position (ns ``footprint``);
- with sensor points, the filter's ``binding_points`` (its ``filter_info`` section, read by
  :func:`info_binding_points`): one sphere per point coloured by its row value as barrier
  values are (ns ``binding_points``, one SPHERE_LIST), and a line from the guarded point to
  each point whose row binds, value <= :data:`ACTIVE_ROW_VALUE` (ns ``active_rows``, one
  LINE_LIST). The two lists are there, empty, when the latest answer names no point, so each
  array replaces the last one's points.

A filter with observation sources keeps its state and its sensor points in ``odom_frame_id``,
so the scene is drawn there (:func:`marker_frame`); one with only sources has no obstacle and
no barrier text, the robot, its footprint and the points only.

Ids are stable for a given configuration (one per marker and namespace), so each array
replaces the previous one's markers.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.filter_info import BINDING_POINTS
from rcbf_ros.core.scene import SceneGeometry
from rcbf_ros.messages.tf import frame_name_refusal
from rcbf_ros.node_logic.filter_edge import float64_sections, one_line
from rcbf_ros.parameters.reader import defaults_of, RATE_LIMITS_HZ, read_parameters, setting

ARROW, CUBE, SPHERE, CYLINDER, LINE_STRIP, LINE_LIST, SPHERE_LIST, TEXT_VIEW_FACING = (
    0, 1, 2, 3, 4, 5, 7, 9)
"""visualization_msgs/Marker type constants used here."""
OK, WARN, ERROR = 0, 1, 2
"""diagnostic_msgs/DiagnosticStatus levels."""

GREEN = (0.18, 0.70, 0.30, 1.0)
AMBER = (1.00, 0.62, 0.00, 1.0)
RED = (0.88, 0.10, 0.10, 1.0)
GREY = (0.55, 0.55, 0.55, 1.0)
OBSTACLE = (0.35, 0.35, 0.40, 0.9)
ROBOT = (0.12, 0.40, 0.85, 1.0)
OTHER_CAR = (0.60, 0.60, 0.62, 1.0)
FOOTPRINT = (0.12, 0.40, 0.85, 0.8)

DEFAULT_FRAME = 'map'
"""The markers' frame without observation sources (:func:`marker_frame`): the obstacles'."""
DEFAULT_CAUTION = 0.1
"""Barrier values below this (and >= 0) are amber."""
RING_SEGMENTS = 48
"""Line segments of a margin ring."""
IDENTITY = (0.0, 0.0, 0.0, 1.0)
ACTIVE_ROW_VALUE = 1e-6
"""A sensor point's row whose value at the command is at most this binds (or needs slack):
it is an active row of the QP, drawn with a line from the guarded point."""
MAX_INFO_BYTES = 1 << 20
"""Largest ``filter_info`` sample read (bytes): the filter's own, with 20,000 barriers, is a
third of this; a longer one is refused before it is decoded."""
POINT_SIZE = 0.06
"""Diameter of a binding point's sphere (m)."""

MAX_RATE_HZ = 100.0
"""The most MarkerArrays a second ``rate_hz`` may ask for: more than a viewer draws."""
MAX_DRAWN_OBSTACLES = 2000
"""The most obstacles ``max_obstacles`` may ask to draw: each is a cylinder, a ring of
:data:`RING_SEGMENTS` segments and a label, some 3 kB of a MarkerArray."""

Marker = dict[str, Any]
Color = tuple[float, float, float, float]

@dataclass(frozen=True)
class SceneSettings:
    """Settings of the scene_markers node besides the filter geometry."""

    frame_id: str = setting('', description="frame of every marker; '': the filter's state "
                                            'frame (odom_frame_id with observation_sources, '
                                            'else map)')
    """Frame of every marker; '' (the default): :func:`marker_frame` picks the filter's."""
    rate_hz: float = setting(10.0, minimum=RATE_LIMITS_HZ[0], maximum=MAX_RATE_HZ,
                             description='most MarkerArrays a second (one after each new state '
                                         'or diagnostics)')
    """Most MarkerArrays a second (one after each new state or diagnostics, no faster)."""
    caution_h: float = setting(DEFAULT_CAUTION, minimum=0,
                               description='barrier values in [0, caution_h) are drawn amber, '
                                           'below 0 red')
    """Barrier values in [0, caution_h) are amber, above green."""
    max_obstacles: int = setting(200, minimum=0, maximum=MAX_DRAWN_OBSTACLES,
                                 description='most obstacles drawn: those nearest the robot '
                                             '(the first ones before a state); a label says '
                                             'how many are left out')
    """Most obstacles drawn, so that an array's size and build time stay bounded whatever the
    ``obstacles`` topic holds: the nearest to the robot (surface distance), the first ones
    while no state is known; a label (ns ``omitted``) says how many are left out."""


SCENE_PARAMETER_DEFAULTS: dict[str, Any] = defaults_of(SceneSettings)
"""The scene_markers node's own parameters and their defaults (:class:`SceneSettings`)."""


def scene_settings(params: Mapping[str, Any]) -> SceneSettings:
    """The node's settings from its flat parameters (defaults: :class:`SceneSettings`'s).

    Raises:
        ValueError: naming the key: a non-string ``frame_id`` or one tf refuses
            (:func:`~rcbf_ros.messages.tf.frame_name_refusal`), ``rate_hz`` outside
            [RATE_LIMITS_HZ[0], MAX_RATE_HZ], ``max_obstacles`` outside
            [0, MAX_DRAWN_OBSTACLES],
            ``caution_h`` < 0.
    """
    frame_id = params.get('frame_id', SceneSettings.frame_id)
    if not isinstance(frame_id, str):
        raise ValueError(f'frame_id: expected a frame name, got {frame_id!r}')
    why = frame_name_refusal(frame_id.strip()) if frame_id.strip() else ''
    if why:
        raise ValueError(f'frame_id: {why}')
    return read_parameters(SceneSettings, {**params, 'frame_id': frame_id.strip()})


def marker_frame(frame_id: str, geometry: SceneGeometry) -> str:
    """The frame every marker is drawn in: ``frame_id``, or for '' the filter's state frame:
    with observation sources its ``odom_frame_id``, where its state and its sensor points are
    (REP 105), else :data:`DEFAULT_FRAME`.

    Raises:
        ValueError: naming ``frame_id`` and ``odom_frame_id``: with observation sources, any
            other frame (the state and the binding points would be drawn where they are not).
    """
    odom = geometry.odom_frame_id
    if not frame_id:
        return odom if odom is not None else DEFAULT_FRAME
    if odom is not None and frame_id != odom:
        raise ValueError(f'frame_id: {frame_id!r} is not odom_frame_id {odom!r}: the state and '
                         "the sensor points are in odom_frame_id ('' takes it)")
    return frame_id


def h_colour(h: float, *, caution: float = DEFAULT_CAUTION) -> Color:
    """Green for h >= caution, amber for 0 <= h < caution, red for h < 0, grey for NaN."""
    if h is None or not math.isfinite(h):
        return GREY
    if h < 0.0:
        return RED
    return AMBER if h < caution else GREEN


def h_text(name: str, h: float) -> str:
    """``<name>  h = +0.123`` (``h = ?`` while the value is unknown)."""
    value = f'{h:+.3f}' if h is not None and math.isfinite(h) else '?'
    return f'{name}  h = {value}'


def barrier_values(values: Mapping[str, str]) -> dict[str, float]:
    """{barrier: h} from a filter diagnostic's key/values (``h.<barrier>``; unreadable: NaN)."""
    out = {}
    for key, text in values.items():
        if key.startswith('h.') and len(key) > 2:
            try:
                out[key[2:]] = float(text)
            except (TypeError, ValueError):
                out[key[2:]] = math.nan
    return out


def info_binding_points(data: Any) -> np.ndarray:
    """The ``binding_points`` rows [x, y, row value, h] of a ``filter_info`` sample (CDR
    bytes), read as the filter node's edge reads a Float64MultiArray: (m, 4), m <=
    :data:`rcbf_ros.core.filter_info.BINDING_POINTS`; (0, 4) when the sample has no such
    section (an answer without sensor points, or before their rows were evaluated).

    Raises:
        ValueError: one line, naming ``filter_info``: not bytes, longer than
            :data:`MAX_INFO_BYTES`, not a Float64MultiArray, a layout that does not fit, or a
            ``binding_points`` section that is not whole rows of 4, has more than
            ``BINDING_POINTS`` rows or a NaN or inf.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f'filter_info: expected CDR bytes, got {type(data).__name__}')
    if len(data) > MAX_INFO_BYTES:
        raise ValueError(f'filter_info: sample of {len(data)} bytes, more than '
                         f'{MAX_INFO_BYTES}')
    try:
        sections = float64_sections(bytes(data), default_label='u')
    except ValueError as exc:
        raise ValueError(f'filter_info: {one_line(exc)}') from None
    values = sections.get('binding_points')
    if values is None:
        return np.empty((0, 4))
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size % 4 or array.size > 4 * BINDING_POINTS:
        raise ValueError(f'filter_info: binding_points: expected rows of 4, at most '
                         f'{BINDING_POINTS}, got {array.size} values')
    if not np.isfinite(array).all():
        raise ValueError('filter_info: binding_points: contains NaN or inf')
    return array.reshape(-1, 4)


def _marker(*, frame_id: str, ns: str, id: int, type: int,
            position: Sequence[float] = (0.0, 0.0, 0.0),
            orientation: Sequence[float] = IDENTITY, scale: Sequence[float] = (1.0, 1.0, 1.0),
            color: Sequence[float] = GREY, points: Sequence[Sequence[float]] | None = None,
            text: str = '', colors: Sequence[Sequence[float]] | None = None) -> Marker:
    marker: Marker = {
        'frame_id': frame_id, 'ns': ns, 'id': int(id), 'type': int(type),
        'position': tuple(float(v) for v in position),
        'orientation': tuple(float(v) for v in orientation),
        'scale': tuple(float(v) for v in scale), 'color': tuple(float(v) for v in color),
    }
    if points is not None:
        marker['points'] = [tuple(float(v) for v in p) for p in points]
    if colors is not None:
        marker['colors'] = [tuple(float(v) for v in c) for c in colors]
    if text:
        marker['text'] = text
    return marker


def _yaw(theta: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation by theta about z."""
    return 0.0, 0.0, math.sin(theta / 2.0), math.cos(theta / 2.0)


def _pitch(angle: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation by angle about y."""
    return 0.0, math.sin(angle / 2.0), 0.0, math.cos(angle / 2.0)


_CYLINDER_ALONG_Y = (math.sin(math.pi / 4.0), 0.0, 0.0, math.cos(math.pi / 4.0))
"""A cylinder's axis (its z) turned onto y: discs drawn in the x-z plane."""


class _Frame:
    """Where the system's plane lies in the scene: x-y, or x-z for the PVTOL (z up)."""

    def __init__(self, geometry: SceneGeometry) -> None:
        self.vertical = geometry.system == 'pvtol'
        self.unit = 4.0 if geometry.system == 'car_following' else 1.0
        """Size of labels and robot parts relative to the Unicycle's arena."""

    def point(self, a: float, b: float, up: float = 0.0) -> tuple[float, float, float]:
        """The scene point of plane coordinates (a, b), ``up`` out of the plane (toward the
        viewer: +z for the x-y plane, -y for the x-z plane)."""
        return (a, -up, b) if self.vertical else (a, b, up)


def _h(h: Mapping[str, float], name: str) -> float:
    value = h.get(name, math.nan)
    return float(value) if value is not None else math.nan


def _worst(values: Sequence[float]) -> float:
    """The smallest known value (NaN when none is known)."""
    known = [v for v in values if math.isfinite(v)]
    return min(known) if known else math.nan


def drawn_obstacles(geometry: SceneGeometry, state: np.ndarray | None, limit: int
                    ) -> np.ndarray:
    """Indices (ascending) of the at most ``limit`` obstacles drawn: all when there are no
    more; else the ``limit`` nearest the robot's position (distance to the disc's edge), or
    the first ``limit`` while ``state`` is None. O(n) in the obstacles."""
    count = len(geometry.obstacles)
    if count <= limit:
        return np.arange(count)
    if limit <= 0:
        return np.arange(0)
    if state is None:
        return np.arange(limit)
    x, y = geometry.position(state)
    discs = np.array([(d.x, d.y, d.radius) for d in geometry.obstacles], dtype=np.float64)
    gap = np.hypot(discs[:, 0] - x, discs[:, 1] - y) - discs[:, 2]
    return np.sort(np.argpartition(gap, limit - 1)[:limit])


def _obstacle_markers(geometry: SceneGeometry, h: Mapping[str, float], frame: _Frame, *,
                      frame_id: str, caution: float, drawn: np.ndarray) -> list[Marker]:
    out = []
    height = 0.3
    orientation = _CYLINDER_ALONG_Y if frame.vertical else IDENTITY
    angles = np.linspace(0.0, 2.0 * math.pi, RING_SEGMENTS + 1)
    for i in drawn.tolist():
        disc = geometry.obstacles[i]
        out.append(_marker(frame_id=frame_id, ns='obstacles', id=i, type=CYLINDER,
                           position=frame.point(disc.x, disc.y, height / 2.0),
                           orientation=orientation,
                           scale=(2.0 * disc.radius, 2.0 * disc.radius, height), color=OBSTACLE))
        value = _h(h, disc.name)
        ring = disc.radius + disc.margin
        colour = h_colour(value, caution=caution)
        out.append(_marker(
            frame_id=frame_id, ns='margins', id=i, type=LINE_STRIP, scale=(0.02, 0.0, 0.0),
            color=(*colour[:3], 0.6),
            points=[frame.point(disc.x + ring * math.cos(a), disc.y + ring * math.sin(a), 0.01)
                    for a in angles]))
    return out


def _unicycle_markers(geometry: SceneGeometry, state: np.ndarray, h: Mapping[str, float],
                      frame: _Frame, *, frame_id: str, caution: float) -> list[Marker]:
    x, y = geometry.position(state)
    if geometry.heading_index is None:  # no heading to point the arrow along
        out = [_marker(frame_id=frame_id, ns='robot', id=0, type=SPHERE,
                       position=frame.point(x, y, 0.05), scale=(0.15, 0.15, 0.15), color=ROBOT)]
    else:
        out = [_marker(frame_id=frame_id, ns='robot', id=0, type=ARROW,
                       position=frame.point(x, y, 0.05),
                       orientation=_yaw(float(state[geometry.heading_index])),
                       scale=(0.35, 0.08, 0.08), color=ROBOT)]
    point = geometry.guarded_point(state)
    if point is not None:
        worst = _worst([_h(h, d.name) for d in geometry.obstacles])
        out.append(_marker(frame_id=frame_id, ns='lookahead', id=0, type=SPHERE,
                           position=frame.point(point[0], point[1], 0.05),
                           scale=(0.06, 0.06, 0.06), color=h_colour(worst, caution=caution)))
    return out


def _pvtol_markers(geometry: SceneGeometry, state: np.ndarray, h: Mapping[str, float],
                   frame: _Frame, *, frame_id: str, caution: float) -> list[Marker]:
    x1, x2 = geometry.position(state)
    theta, thrust = float(state[4]), float(state[5])
    body = frame.point(x1, x2)
    up = (-math.sin(theta), 0.0, math.cos(theta))  # the thrust direction (x1_ddot ~ -sin)
    length = 0.3 * thrust
    out = [
        _marker(frame_id=frame_id, ns='robot', id=0, type=CUBE, position=body,
                orientation=_pitch(-theta), scale=(0.5, 0.1, 0.06), color=ROBOT),
        _marker(frame_id=frame_id, ns='robot', id=1, type=ARROW, scale=(0.03, 0.07, 0.07),
                color=ROBOT, points=[body, tuple(b + length * u for b, u in zip(body, up))]),
    ]
    operator = next((b for b in geometry.bands if b.center_index is not None), None)
    if operator is not None and operator.center_index < state.size:
        worst = _worst([_h(h, name) for name in operator.names])
        vertical = geometry.band('arena_y')
        low, high = ((vertical.center - vertical.half_width, vertical.center + vertical.half_width)
                     if vertical is not None else (-3.0, 3.0))
        x_h = float(state[operator.center_index])
        out.append(_marker(frame_id=frame_id, ns='bands', id=0, type=CUBE,
                           position=frame.point(x_h, (low + high) / 2.0, -0.05),
                           scale=(2.0 * operator.half_width, 0.02, high - low),
                           color=(*h_colour(worst, caution=caution)[:3], 0.2)))
    return out


def _car_markers(geometry: SceneGeometry, state: np.ndarray, h: Mapping[str, float],
                 frame: _Frame, *, frame_id: str, caution: float) -> list[Marker]:
    positions = state[0::2]
    # the car in every gap is the one the filter drives
    driven = set.intersection(*({gap.a, gap.b} for gap in geometry.gaps)) \
        if geometry.gaps else set()
    out = []
    for i, p in enumerate(positions):
        colour = ROBOT if 2 * i in driven else OTHER_CAR
        out.append(_marker(frame_id=frame_id, ns='robot', id=i, type=CUBE,
                           position=(float(p), 0.0, 0.5), scale=(1.5, 1.0, 1.0), color=colour))
    for i, gap in enumerate(geometry.gaps):
        pa, pb = float(state[gap.a]), float(state[gap.b])
        colour = h_colour(_h(h, gap.name), caution=caution)
        out.append(_marker(frame_id=frame_id, ns='gaps', id=i, type=LINE_STRIP,
                           scale=(0.15, 0.0, 0.0), color=colour,
                           points=[(pa, 0.0, 1.3), (pb, 0.0, 1.3)]))
    return out


def _robot_markers(geometry: SceneGeometry, state: np.ndarray, h: Mapping[str, float],
                   frame: _Frame, *, frame_id: str, caution: float) -> list[Marker]:
    draw = {'unicycle': _unicycle_markers, 'pvtol': _pvtol_markers,
            'car_following': _car_markers}.get(geometry.system)
    if draw is not None:
        return draw(geometry, state, h, frame, frame_id=frame_id, caution=caution)
    if not (geometry.obstacles or geometry.sensor_points):
        return []
    x, y = geometry.position(state)
    return [_marker(frame_id=frame_id, ns='robot', id=0, type=SPHERE,
                    position=frame.point(x, y, 0.05), scale=(0.15, 0.15, 0.15), color=ROBOT)]


def _footprint_marker(geometry: SceneGeometry, state: np.ndarray, frame: _Frame, *,
                      frame_id: str) -> list[Marker]:
    """The footprint ring around the robot's position (none without a footprint radius)."""
    radius = geometry.footprint_radius
    if not radius > 0.0:
        return []
    x, y = geometry.position(state)
    angles = np.linspace(0.0, 2.0 * math.pi, RING_SEGMENTS + 1)
    return [_marker(frame_id=frame_id, ns='footprint', id=0, type=LINE_STRIP,
                    scale=(0.02, 0.0, 0.0), color=FOOTPRINT,
                    points=[frame.point(x + radius * math.cos(a), y + radius * math.sin(a),
                                        0.02) for a in angles])]


def _point_markers(geometry: SceneGeometry, state: np.ndarray | None, points: np.ndarray,
                   frame: _Frame, *, frame_id: str, caution: float) -> list[Marker]:
    """The binding points' spheres and the active rows' lines (both lists, maybe empty)."""
    colours = [h_colour(float(value), caution=caution) for value in points[:, 2]]
    out = [_marker(frame_id=frame_id, ns='binding_points', id=0, type=SPHERE_LIST,
                   scale=(POINT_SIZE, POINT_SIZE, POINT_SIZE), color=GREY,
                   points=[frame.point(x, y, 0.05) for x, y in points[:, :2].tolist()],
                   colors=colours)]
    lines: list[tuple[float, float, float]] = []
    line_colours: list[Color] = []
    if state is not None:
        guarded = geometry.guarded_point(state) or geometry.position(state)
        start = frame.point(guarded[0], guarded[1], 0.05)
        for (x, y, value, _), colour in zip(points.tolist(), colours):
            if value <= ACTIVE_ROW_VALUE:
                lines += [start, frame.point(x, y, 0.05)]
                line_colours += [colour, colour]
    out.append(_marker(frame_id=frame_id, ns='active_rows', id=0, type=LINE_LIST,
                       scale=(0.015, 0.0, 0.0), color=RED, points=lines, colors=line_colours))
    return out


def _anchor(geometry: SceneGeometry, state: np.ndarray | None) -> tuple[float, float]:
    """Plane coordinates the list of barrier values and the status hang from."""
    if state is None:
        return 0.0, 0.0
    if geometry.system == 'car_following':
        return float(state[6]) if state.size > 6 else 0.0, 0.0
    return geometry.position(state)


def _text_markers(geometry: SceneGeometry, state: np.ndarray | None, h: Mapping[str, float],
                  frame: _Frame, *, frame_id: str, caution: float,
                  status: tuple[int, str] | None, drawn: np.ndarray) -> list[Marker]:
    size = 0.12 * frame.unit
    placed: dict[str, tuple[float, float, float]] = {}
    for k in drawn.tolist():
        disc = geometry.obstacles[k]
        placed[disc.name] = frame.point(disc.x, disc.y, 0.45)
    left_out = len(geometry.obstacles) - len(drawn)
    hidden = ({disc.name for disc in geometry.obstacles} - set(placed)) if left_out else set()
    if state is not None:
        for gap in geometry.gaps:
            placed[gap.name] = ((float(state[gap.a]) + float(state[gap.b])) / 2.0, 0.0, 2.0)
    a, b = _anchor(geometry, state)
    row = {name: k for k, name in enumerate(
        name for name in geometry.barrier_names if name not in placed and name not in hidden)}
    out = []
    for i, name in enumerate(geometry.barrier_names):
        if name in hidden:
            continue
        value = _h(h, name)
        if name in placed:
            position = placed[name]
        elif frame.vertical:  # beside the drone, one line per barrier going down
            position = frame.point(a + 0.9, b + 0.5 - 1.4 * size * row[name], 0.1)
        else:
            position = frame.point(a + 0.9 * frame.unit,
                                   b + 0.5 * frame.unit - 1.4 * size * row[name], 0.4)
        out.append(_marker(frame_id=frame_id, ns='barriers', id=i, type=TEXT_VIEW_FACING,
                           position=position, scale=(0.0, 0.0, size),
                           color=h_colour(value, caution=caution), text=h_text(name, value)))
    if status is not None:
        level, message = status
        colour = RED if level >= ERROR else AMBER if level == WARN else GREY
        position = (frame.point(a, b + 0.45, 0.1) if frame.vertical
                    else frame.point(a, b, 0.6 * frame.unit + 2.0 * size))
        out.append(_marker(frame_id=frame_id, ns='status', id=0, type=TEXT_VIEW_FACING,
                           position=position, scale=(0.0, 0.0, size), color=colour,
                           text=message[:120]))
    if left_out:
        position = (frame.point(a, b + 0.45 + 1.4 * size, 0.1) if frame.vertical
                    else frame.point(a, b, 0.6 * frame.unit + 3.4 * size))
        out.append(_marker(frame_id=frame_id, ns='omitted', id=0, type=TEXT_VIEW_FACING,
                           position=position, scale=(0.0, 0.0, size), color=GREY,
                           text=omitted_text(len(drawn), len(geometry.obstacles))))
    return out


def omitted_text(drawn: int, count: int) -> str:
    """What the ``omitted`` label says when ``drawn`` of ``count`` obstacles are drawn."""
    return (f'{count - drawn} of {count} obstacles not drawn (the {drawn} nearest are; '
            'max_obstacles)')


def scene_markers(*, geometry: SceneGeometry, state: Sequence[float] | np.ndarray | None,
                  h: Mapping[str, float], frame_id: str = 'map',
                  caution: float = DEFAULT_CAUTION,
                  status: tuple[int, str] | None = None,
                  points: Sequence[Sequence[float]] | np.ndarray | None = None,
                  max_obstacles: int = SceneSettings.max_obstacles) -> list[Marker]:
    """Every marker of the scene (see the module docstring).

    Args:
        geometry: the filter's geometry (:func:`rcbf_ros.core.scene.scene_geometry`).
        state: (n_x,) the latest state, or None (obstacles and barrier values only).
        h: barrier name -> latest value from the filter's diagnostics (absent: unknown).
        frame_id: the frame every marker is given in.
        caution: barrier values in [0, caution) are amber.
        status: (level, message) of the filter's last diagnostic, or None.
        points: (m, 4) rows [x, y, row value, h] of the filter's latest ``binding_points``
            (:func:`info_binding_points`; (0, 4): none named), or None: no ``filter_info``
            read, nothing drawn for them.
        max_obstacles: the most obstacles drawn (:func:`drawn_obstacles`), with their
            rings and labels; a label (ns ``omitted``) says how many more there are.

    Raises:
        ValueError: ``state`` has the wrong length or a NaN/inf entry, ``points`` is not
            (m, 4) finite, or ``frame_id`` is empty.
    """
    if not frame_id:
        raise ValueError('frame_id: must not be empty')
    array = None
    if state is not None:
        array = np.asarray(state, dtype=np.float64).reshape(-1)
        if array.size != geometry.n_x:
            raise ValueError(f'state: expected {geometry.n_x} values, got {array.size}')
        if not np.all(np.isfinite(array)):
            raise ValueError('state: contains NaN or inf')
    rows = None
    if points is not None:
        rows = np.asarray(points, dtype=np.float64)
        if rows.size == 0:
            rows = rows.reshape(0, 4)
        if rows.ndim != 2 or rows.shape[1] != 4 or not np.isfinite(rows).all():
            raise ValueError(f'points: expected finite (m, 4) rows, got shape {rows.shape}')
    frame = _Frame(geometry)
    drawn = drawn_obstacles(geometry, array, max_obstacles)
    out = _obstacle_markers(geometry, h, frame, frame_id=frame_id, caution=caution,
                            drawn=drawn)
    if array is not None:
        out += _robot_markers(geometry, array, h, frame, frame_id=frame_id, caution=caution)
        out += _footprint_marker(geometry, array, frame, frame_id=frame_id)
    if rows is not None:
        out += _point_markers(geometry, array, rows, frame, frame_id=frame_id, caution=caution)
    out += _text_markers(geometry, array, h, frame, frame_id=frame_id, caution=caution,
                         status=status, drawn=drawn)
    return out

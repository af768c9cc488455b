"""Safety-filter configuration: ROS parameters (flat, dotted) -> frozen dataclass -> RCBFProblem.

ROS 2 parameters are scalars or flat homogeneous arrays, so the layout is flat too; a YAML file
may nest mappings (``obstacles: {x: [...]}``), which ROS (and :func:`flatten`) turn into dotted
names (``obstacles.x``). The same keys feed the safety_filter node, the learner and offline
scripts (one source of truth: ``config/<system>.yaml``). Every error names the bad key.

Keys (all optional except ``system``)::

    system: unicycle | car_following | pvtol | package.module.ClassName
    system_params.<name>: constructor argument of the system (e.g. with_operator)
    input_limits.min / input_limits.max: [m floats] (override the system's; [] = unbounded)
    alpha, k_c, slack_weight
    input_weight: [m floats > 0] weights of u_S in the QP cost (default all 1)
    obstacles.x / .y / .radius: [k floats];  obstacles.margin, obstacles.lookahead,
        obstacles.heading_index (-1: none), obstacles.position_indices: [2 ints],
        obstacles.gammas: [r - 1 cascade gains], obstacles.speed_input (-1: none; the input
        whose negative proposals move the look-ahead point behind the robot, see
        rcbf_ros.core.rcbf.barrier_terms)
    bands.<name>.index, .half_width, .center, .center_index (-1: constant centre), .gammas,
        .form (quadratic: one barrier, the paper's; sides: two linear ones, see BandBarrier):
        one band per <name> (e.g. bands.operator.*, bands.tilt.*)
    gaps.a / gaps.b: [ints], gaps.delta, gaps.gammas
    walls.nx / walls.ny / walls.offset: [floats], walls.gammas  (h = nx x + ny y - offset)
    disturbance.mean / disturbance.std: [n_x floats]: a static box (empty: zero / learned)
    fail_safe_action: [m floats]
    control_period_s, latency_s: how long the plant holds a command and how old its state is
        when it acts (s, 0 to 1; 0: the continuous-time rows; see rcbf_ros.core.sampled_data)
    compile_assembly: bool (compile the per-step autograd assembly of a system or barrier
        without a closed form; see core/filter.py)
    observation_sources: [names]; <name>.type (scan | pointcloud), <name>.topic,
        <name>.timeout_s, <name>.min_height / .max_height / .voxel_size (pointcloud),
        <name>.best_effort; footprint.radius; odom_frame_id, base_frame_id,
        transform_tolerance (the sensor points' frames and tf, docs/SAFETY_FILTER.md
        "Perception sources")
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
import re
from typing import Any, Mapping

from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    cascade,
    CircleObstacles,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.dynamics import ControlAffineSystem, heading_indices, load_system
from rcbf_ros.core.mappings import flatten
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import sampled_data_margin, TIMING_LIMIT_S
from rcbf_ros.messages import systems
from rcbf_ros.parameters.reader import (
    parameter_keys,
    ParameterError,
    read_bool,
    read_float,
    read_floats,
    read_int,
    read_parameters,
    setting,
)


def float_list(params: Mapping[str, Any], key: str, length: int | None = None, *,
               default: Any = ()) -> tuple[float, ...]:
    """params[key] as floats (a scalar counts as one); errors name ``key``. An empty list is
    accepted whatever ``length`` (meaning: not set)."""
    return _sized(key, read_floats(key, params.get(key, default)), length)


def _sized(key: str, values: tuple[Any, ...], length: int | None) -> tuple[Any, ...]:
    """``values``, refused naming ``key`` when not empty and not ``length`` long."""
    if length is not None and values and len(values) != length:
        raise ParameterError(f'{key}: expected {length} values, got {len(values)}')
    return values


def number(params: Mapping[str, Any], key: str, default: float, *,
           positive: bool = False) -> float:
    """params[key] (or ``default``) as a finite float, > 0 if ``positive``; errors name ``key``.

    A numeric string is taken (YAML 1.1 reads ``1.0e6`` as a string); a bool is not a number.
    """
    return read_float(key, params.get(key, default), positive=positive)


def flag(params: Mapping[str, Any], key: str, default: bool = False) -> bool:
    """params[key] (or ``default``) as a bool; anything else (1, 'true') is refused naming
    ``key``, as rcl types a YAML bool and nothing else as a bool parameter."""
    return read_bool(key, params.get(key, default))


OBSTACLE_LIMIT = 20_000
"""The most circular obstacles one filter takes (``obstacles.x``; the ``obstacles`` topic too).

A large set is evaluated over arrays (:mod:`rcbf_ros.core.lie_closed_form_rows`), its memory
linear in the rows (about 0.7 kB a row with its parameters: 14 MB at 20,000, built in about
0.1 s), and its QP carries only the rows that can bind; a decision still checks
every row, in time linear in the rows (about 0.25 ms at 10,000 and 1.9 ms at 100,000 on the
Unicycle, benchmarks/bench_obstacle_scale.py), and every answer (``filter_info``) carries h
and the row value of every row, 16 bytes a row. The bound keeps both small beside a control
period; a larger set is refused at the edge, naming the key, before anything is built."""
COST_WEIGHT_LIMIT = 1.0e12
"""The largest weight of the QP cost (``slack_weight``, ``input_weight``): the solver squares
and inverts the cost's diagonal, and 2 x 1e308 overflows."""
COST_WEIGHT_FLOOR = 1.0e-12
"""The least weight of the QP cost: the inverse of 5e-324 overflows."""
CASCADE_LIMIT = 8
"""The most cascade gains a barrier family takes (relative degree up to 9)."""


def _index(key: str, value: Any, size: int, *, allow_none: bool = False,
           kind: str = 'state') -> int | None:
    """An index into the state (``kind`` 'state', size n_x) or the input ('input', n_u);
    with ``allow_none`` a negative one is None."""
    out = read_int(key, value)  # True or 1.5: a typo must not pick another index
    if allow_none and out < 0:
        return None
    if not 0 <= out < size:
        name = 'n_x' if kind == 'state' else 'n_u'
        raise ParameterError(f'{key}: {kind} index {out} out of range for {name} = {size}')
    return out


@dataclass(frozen=True)
class InputLimitParameters:
    """``input_limits.*``: the system's actuator limits, overridden."""

    lower: tuple[float, ...] | None = setting(
        None, key='min', description="lower input limits, n_u values ([]: none; not set: the "
                                     "system's)")
    """Lower limits (None: the system's; empty: none)."""
    upper: tuple[float, ...] | None = setting(
        None, key='max', description="upper input limits, n_u values ([]: none; not set: the "
                                     "system's)")
    """Upper limits (None: the system's; empty: none)."""


@dataclass(frozen=True)
class ObstacleParameters:
    """``obstacles.*``: circular obstacles (read when ``obstacles.x`` lists one)."""

    x: tuple[float, ...] = setting(
        (), max_length=OBSTACLE_LIMIT, description='obstacle centres, x (m), one per obstacle')
    """Centres, x (m)."""
    y: tuple[float, ...] = setting(
        (), max_length=OBSTACLE_LIMIT, description='obstacle centres, y (m), one per obstacle')
    """Centres, y (m)."""
    radius: tuple[float, ...] = setting(
        (), max_length=OBSTACLE_LIMIT, description='obstacle radii (m), one per obstacle')
    """Radii (m), >= 0."""
    margin: float = setting(0.0, minimum=0, description='added to every radius (m, >= 0)')
    """Added to every radius (m)."""
    lookahead: float = setting(
        0.0, minimum=0, description='distance (m) of the guarded point ahead of the position')
    """Distance of the guarded point ahead of the position (m)."""
    heading_index: int = setting(
        -1, description='state index of the heading the look-ahead follows (-1: none)')
    """State index of the heading (-1: none)."""
    position_indices: tuple[int, ...] = setting(
        (0, 1), length=2, description='state indices of the position')
    """State indices of the position."""
    gammas: tuple[float, ...] = setting(
        (), max_length=CASCADE_LIMIT,
        description='cascade gains for relative degree r > 1, r - 1 values > 0')
    """Cascade gains (relative degree r > 1: r - 1 of them)."""
    speed_input: int = setting(
        -1, description='input whose negative proposals move the look-ahead point behind '
                        '(-1: none)')
    """Input whose negative proposals move the look-ahead point behind (-1: none); see
    rcbf_ros.core.rcbf.barrier_terms."""


@dataclass(frozen=True)
class GapParameters:
    """``gaps.*``: least distances between pairs of state entries (read when ``gaps.a`` is
    set)."""

    a: tuple[int, ...] = setting((), description='state index of the first position of each gap')
    """State index of each gap's first position."""
    b: tuple[int, ...] = setting((), description='state index of the second position of each '
                                                 'gap')
    """State index of each gap's second position."""
    delta: float = setting(0.0, minimum=0, description='least distance |x_a - x_b| to keep (m)')
    """Least distance to keep (m)."""
    gammas: tuple[float, ...] = setting((), max_length=CASCADE_LIMIT,
                                        description='cascade gains of the gap barriers')
    """Cascade gains."""


@dataclass(frozen=True)
class WallParameters:
    """``walls.*``: half-planes h = nx x + ny y - offset (read when ``walls.nx`` is set)."""

    nx: tuple[float, ...] = setting((), description='wall normals, x: h = nx x + ny y - offset')
    """Normals, x."""
    ny: tuple[float, ...] = setting((), description='wall normals, y, one per wall')
    """Normals, y."""
    offset: tuple[float, ...] = setting((), description='wall offsets (m), one per wall')
    """Offsets (m)."""
    gammas: tuple[float, ...] = setting((), max_length=CASCADE_LIMIT,
                                        description='cascade gains of the wall barriers')
    """Cascade gains."""


@dataclass(frozen=True)
class DisturbanceParameters:
    """``disturbance.*``: a static disturbance box."""

    mean: tuple[float, ...] = setting(
        (), description='static disturbance box centre, n_x values in state-derivative units '
                        "(a proposal's disturbance_mean wins)")
    """Box centre (n_x values; empty: zero / learned)."""
    std: tuple[float, ...] = setting(
        (), minimum=0, description='static disturbance box std, n_x values >= 0 (box: mean +/- '
                                   "k_c std; a proposal's disturbance_std wins)")
    """Box std (n_x values >= 0; empty: zero / learned)."""


@dataclass(frozen=True)
class BandParameters:
    """``bands.<name>.*``: one band barrier per name."""

    index: int = setting(0, description='band barrier <name>: state index it bounds')
    """State index it bounds."""
    center: float = setting(0.0, description='band <name>: constant centre')
    """Constant centre."""
    center_index: int = setting(
        -1, description='band <name>: state index of a moving centre (-1: the constant centre)')
    """State index of a moving centre (-1: the constant centre)."""
    half_width: float = setting(0.0, description='band <name>: half width')
    """Half width (> 0)."""
    form: str = setting('quadratic', description='band <name>: quadratic (one barrier) or sides '
                                                 '(two linear ones)')
    """quadratic: one barrier (the paper's); sides: two linear ones (see BandBarrier)."""
    gammas: tuple[float, ...] = setting((), max_length=CASCADE_LIMIT,
                                        description='band <name>: cascade gains')
    """Cascade gains."""
    layout: bool = setting(False, description='band <name> belongs to the layout (left out of '
                                              'the envelope)')
    """Part of the layout, not of the envelope (see :func:`envelope_params`)."""


SOURCE_TYPES = ('scan', 'pointcloud', 'range')
"""The kinds of observation source: sensor_msgs/LaserScan, PointCloud2, Range."""
SOURCE_LIMIT = 16
"""The most observation sources of one filter."""
MIN_VOXEL_SIZE = 1.0e-3
"""The smallest ``<name>.voxel_size`` but 0 (:data:`rcbf_ros.messages.sensor.MIN_VOXEL_SIZE`)."""
MIN_OBSTACLES_ANGLE = 1.0e-3
"""The smallest ``<name>.obstacles_angle``
(:data:`rcbf_ros.messages.sensor.MIN_OBSTACLES_ANGLE`)."""
SOURCE_TIMEOUT_S = 0.5
"""Default of ``<name>.timeout_s``."""
TRANSFORM_TOLERANCE_LIMIT_S = 10.0
"""The largest ``transform_tolerance``: tf's cache holds 10 s behind a link's newest sample."""
_SOURCE_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*')


@dataclass(frozen=True)
class SourceParameters:
    """``<name>.*``: one observation source (a name listed in ``observation_sources``). Every
    key is fixed at start: the node subscribes once, and keeps each source's settings."""

    type: str = setting('', choices=SOURCE_TYPES,
                        description='scan (sensor_msgs/LaserScan), pointcloud '
                                    '(sensor_msgs/PointCloud2) or range (sensor_msgs/Range)',
                        read_only=True)
    """scan, pointcloud or range."""
    topic: str = setting('', description='the topic the source subscribes to', read_only=True)
    """The topic (required)."""
    timeout_s: float = setting(
        SOURCE_TIMEOUT_S, positive=True, maximum=3600.0, read_only=True,
        description='the fail-safe when the latest message is older than this (s)')
    """The fail-safe once the latest message is older than this (s); none yet too."""
    min_height: float = setting(0.05, description='pointcloud: the lowest z (m) of a point '
                                                  'that counts, in the message frame',
                                read_only=True)
    """pointcloud: lowest z of a point that counts (m)."""
    max_height: float = setting(0.5, description='pointcloud: the highest z (m) of a point '
                                                 'that counts, in the message frame',
                                read_only=True)
    """pointcloud: highest z of a point that counts (m)."""
    voxel_size: float = setting(0.0, minimum=0, maximum=100.0, read_only=True,
                                description='pointcloud: thinning grid cell (m; 0: off)')
    """pointcloud: thinning grid cell (m); 0 turns thinning off."""
    obstacles_angle: float = setting(
        math.pi / 180, minimum=MIN_OBSTACLES_ANGLE, maximum=math.pi, read_only=True,
        description="range: the angle (rad) between the points of a reading's arc "
                    "(collision_monitor's obstacles_angle)")
    """range: the angle between the points of a reading's arc (rad)."""
    best_effort: bool = setting(True, description='subscribe best effort (sensor data QoS); '
                                                  'false: reliable', read_only=True)
    """Sensor-data QoS (best effort, keep last 5) by default; false: reliable."""


@dataclass(frozen=True)
class FootprintParameters:
    """``footprint.*``: the robot's body as sensor points see it."""

    radius: float = setting(
        0.0, minimum=0, maximum=1.0e3,
        description="the robot's radius (m): every sensor point keeps the guarded point "
                    'radius + obstacles.margin away')
    """The robot's radius (m); a point keeps the guarded point radius + margin away."""


@dataclass(frozen=True)
class SourceConfig:
    """The observation sources of a filter, validated."""

    sources: tuple[tuple[str, SourceParameters], ...]
    """(name, parameters) per source, in ``observation_sources`` order."""
    odom_frame_id: str
    """The state's frame: points in it are taken as they are."""
    base_frame_id: str
    """The robot's frame: points in it (or tf-joined to it but not to ``odom_frame_id``) go to
    the state's frame through the robot's pose at their stamp, from the states."""
    position_indices: tuple[int, int]
    """State indices of the robot's position (``obstacles.position_indices``)."""
    heading_index: int | None
    """State index of its heading (``obstacles.heading_index``; None: no base frame)."""
    transform_tolerance: float = 0.1
    """How far (s) a tf link may be held past its first or last sample, for a message's
    stamp (``transform_tolerance``)."""


@dataclass(frozen=True)
class FilterParameters:
    """Every fixed key of ``config/<system>.yaml`` the filter reads (``system_params.<name>``
    and ``bands.<name>.*`` (:class:`BandParameters`) come on top, one per name)."""

    system: str = setting('', description='unicycle, car_following, pvtol or '
                                          'package.module.Class (required)', read_only=True)
    """The system: a packaged name or a dotted path (required: :func:`build_system` says so)."""
    input_limits: InputLimitParameters = field(default_factory=InputLimitParameters)
    """The actuator limits, when they override the system's."""
    alpha: float = setting(1.0, positive=True, description='class-K gain of every RCBF row, > 0')
    """Class-K gain of every RCBF row."""
    k_c: float = setting(2.0, minimum=0,
                         description='the disturbance box is mean +/- k_c std, >= 0')
    """The disturbance box is mean +/- k_c std."""
    slack_weight: float = setting(
        1.0e6, minimum=COST_WEIGHT_FLOOR, maximum=COST_WEIGHT_LIMIT,
        description='weight l of the slack in the QP cost, > 0')
    """Weight of the slack in the QP cost."""
    input_weight: tuple[float, ...] = setting(
        (), minimum=COST_WEIGHT_FLOOR, maximum=COST_WEIGHT_LIMIT,
        description='weights of u_S in the QP cost, n_u values > 0 ([]: all 1)')
    """Weights of u_S in the QP cost (empty: all 1)."""
    obstacles: ObstacleParameters | None = setting(None, when='x')
    """Circular obstacles (None: none)."""
    gaps: GapParameters | None = setting(None, when='a')
    """Pair gaps (None: none)."""
    walls: WallParameters | None = setting(None, when='nx')
    """Walls (None: none)."""
    disturbance: DisturbanceParameters = field(default_factory=DisturbanceParameters)
    """The static disturbance box."""
    fail_safe_action: tuple[float, ...] = setting(
        (), description='what is published when the filter cannot filter, n_u values within the '
                        'limits ([]: zeros clipped to the limits)')
    """Action when filtering is impossible (empty: zeros clipped to the limits)."""
    control_period_s: float = setting(
        0.0, minimum=0, maximum=TIMING_LIMIT_S,
        description='T: how long the plant holds each command (s); > 0 tightens every RCBF '
                    'row to hold between samples (0: continuous-time rows)')
    """T: how long the plant holds each command (s); 0: the continuous-time rows."""
    latency_s: float = setting(
        0.0, minimum=0, maximum=TIMING_LIMIT_S,
        description='L: the age of the state when its command starts to act (s); > 0 tightens '
                    'every RCBF row for it')
    """L: the age of the state when its command starts to act (s)."""
    compile_assembly: bool = setting(
        False, description='compile the per-step constraint assembly (faster calls, slower '
                           'start)')
    """Compile the per-step autograd assembly (see :class:`FilterConfig`)."""
    observation_sources: tuple[str, ...] = setting(
        (), max_length=SOURCE_LIMIT, distinct=True, read_only=True,
        description='names of the sensor sources (each configured by <name>.*)')
    """Sensor sources, each configured by ``<name>.*`` (:class:`SourceParameters`)."""
    footprint: FootprintParameters = field(default_factory=FootprintParameters)
    """The robot's body as sensor points see it."""
    odom_frame_id: str = setting('odom', description="the state's frame (sensor points in it "
                                                     'are taken as they are)', read_only=True)
    """The state's frame."""
    base_frame_id: str = setting('base_link', description="the robot's frame (sensor points "
                                                          'that tf does not place in '
                                                          "odom_frame_id go through it and the "
                                                          "states' pose at their stamp); an "
                                                          "Odometry state's child_frame_id",
                                 read_only=True)
    """The robot's frame."""
    transform_tolerance: float = setting(
        0.1, minimum=0, maximum=TRANSFORM_TOLERANCE_LIMIT_S, read_only=True,
        description="how far (s) a tf link may be held past its first or last sample to place "
                    "a source's message at its stamp; beyond: fail-safe")
    """How far (s) a tf link may be held past its samples for a source's stamp."""


FILTER_OPEN_PREFIXES: tuple[str, ...] = ('system_params.', 'bands.')
"""Families of keys whose middle part the user names (``bands.operator.index``)."""


@dataclass(frozen=True)
class FilterConfig:
    """Everything the safety filter is configured with, validated."""

    problem: RCBFProblem
    """System, barriers and gains."""
    static_mean: tuple[float, ...]
    """Static disturbance mean (n_x values, or empty: zero / learned on a topic)."""
    static_std: tuple[float, ...]
    """Static disturbance std (n_x values, or empty)."""
    fail_safe_action: tuple[float, ...] | None
    """Action applied when filtering is impossible (None: zeros clipped to the limits)."""
    compile_assembly: bool = False
    """Trace and compile the per-step autograd constraint assembly (faster calls, slower start);
    no effect for the built-in systems and barriers, assembled in closed form."""
    footprint: BarrierFamily | None = None
    """With observation sources: the one-obstacle circle family whose centre each sensor
    point takes (:class:`rcbf_ros.core.filter.SafetyFilter`'s ``footprint``), else None."""
    sources: SourceConfig | None = None
    """The observation sources (None: none)."""
    control_period_s: float = 0.0
    """T: how long the plant holds each command (s; 0: the continuous-time rows)."""
    latency_s: float = 0.0
    """L: the age of the state when its command starts to act (s)."""


def build_system(params: Mapping[str, Any]) -> ControlAffineSystem:
    """The system named by ``system`` with ``system_params.*`` and ``input_limits.*``."""
    name = params.get('system')
    if not isinstance(name, str) or not name:
        raise ValueError('system: required (unicycle, car_following, pvtol or a dotted path)')
    sys_params = {k[len('system_params.'):]: v for k, v in params.items()
                  if k.startswith('system_params.')}
    limits = read_parameters(InputLimitParameters, params, prefix='input_limits.')
    if limits.lower is not None or limits.upper is not None:
        lo, hi = limits.lower or (), limits.upper or ()
        if len(lo) != len(hi):
            raise ValueError('input_limits.min/max: lengths differ')
        if any(a > b for a, b in zip(lo, hi)):
            raise ValueError('input_limits.min: must not exceed input_limits.max')
        sys_params['u_min'] = lo or None
        sys_params['u_max'] = hi or None
    system = load_system(name, sys_params)
    if system.u_min is not None and len(system.u_min) != system.n_u:
        raise ValueError(f'input_limits.min: expected {system.n_u} values')
    return system


def _cascade(base: BarrierFamily, system: ControlAffineSystem, gammas: tuple[float, ...],
             key: str) -> BarrierFamily:
    """:func:`cascade`, its errors naming ``key``."""
    if any(g <= 0 for g in gammas):
        raise ValueError(f'{key}: every cascade gain must be > 0, got {list(gammas)}')
    return cascade(base, system, gammas)


def _obstacles(p: ObstacleParameters, system: ControlAffineSystem) -> BarrierFamily:
    n = len(p.x)
    _sized('obstacles.y', p.y, n)
    _sized('obstacles.radius', p.radius, n)
    if len(p.y) != n or len(p.radius) != n:
        raise ValueError('obstacles.y/obstacles.radius: need one value per obstacles.x')
    if any(r < 0 for r in p.radius):
        raise ValueError(f'obstacles.radius: every radius must be >= 0, got {list(p.radius)}')
    if min(p.radius) + p.margin <= 0:
        raise ValueError('obstacles.radius: radius + obstacles.margin must be > 0 for every '
                         'obstacle')
    key = 'obstacles.position_indices'
    positions = tuple(_index(key, i, system.n_x) for i in p.position_indices)
    heading = _index('obstacles.heading_index', p.heading_index, system.n_x, allow_none=True)
    _check_layout(system, positions=positions, heading=heading)
    base = CircleObstacles(
        centers=tuple(zip(p.x, p.y)), radii=p.radius, margin=p.margin,
        position_indices=positions,  # type: ignore[arg-type]
        heading_index=heading,
        lookahead=p.lookahead,
        speed_input=_index('obstacles.speed_input', p.speed_input, system.n_u,
                           allow_none=True, kind='input'))  # type: ignore[arg-type]
    if base.speed_input is not None and p.gammas:
        raise ValueError('obstacles.speed_input: the look-ahead point follows the direction '
                         'of travel only at relative degree 1 (no obstacles.gammas)')
    if p.lookahead > p.margin:
        raise ParameterError(
            f'obstacles.lookahead: {p.lookahead:g} exceeds obstacles.margin {p.margin:g}: the '
            'barriers guard a point that far ahead of the position, so the robot itself could '
            'enter an obstacle by lookahead - margin (keep margin >= lookahead)')
    if base.speed_input is not None and 3.0 * abs(p.lookahead) > p.margin:
        raise ParameterError(
            f'obstacles.margin: {p.margin:g} is less than 3 x obstacles.lookahead '
            f'({3.0 * abs(p.lookahead):g}) with obstacles.speed_input set: the guarded point '
            'may switch to the one behind the robot, which brings the robot up to '
            '3 lookahead - margin into an obstacle (keep margin >= 3 lookahead, or leave '
            'speed_input out)')
    return _cascade(base, system, p.gammas, 'obstacles.gammas')


def _check_layout(system: ControlAffineSystem, *, positions: tuple[int | None, ...],
                  heading: int | None) -> None:
    """The obstacles' indices against the system's state layout, where it declares its
    headings (:func:`rcbf_ros.core.dynamics.heading_indices`): the heading index must name a
    heading, and a position index must not.

    Raises:
        ParameterError: naming ``obstacles.heading_index`` or ``obstacles.position_indices``.
    """
    headings = heading_indices(system)
    if headings is None:
        return
    name = type(system).__name__
    if heading is not None and heading not in headings:
        where = (f'its heading is state {list(headings)[0]}' if len(headings) == 1
                 else f'its headings are states {list(headings)}' if headings
                 else 'it has no heading (-1: none)')
        raise ParameterError(f'obstacles.heading_index: state {heading} of {name} is not a '
                             f'heading; {where}')
    angles = [i for i in positions if i in headings]
    if angles:
        raise ParameterError(f'obstacles.position_indices: state {angles[0]} of {name} is a '
                             'heading, not a position')


def band_names(params: Mapping[str, Any]) -> list[str]:
    """The ``<name>`` of every ``bands.<name>.<key>`` parameter, sorted.

    Raises:
        ParameterError: naming a ``bands.`` key that is not ``bands.<name>.<key>`` (a name
            with a dot, or no key), which would otherwise be left out in silence.
    """
    odd = sorted(k for k in params if k.startswith('bands.') and k.count('.') != 2)
    if odd:
        raise ParameterError(f'{odd[0]}: expected bands.<name>.<key> (a band name holds no '
                             "'.')")
    return sorted({k.split('.')[1] for k in params if k.startswith('bands.')})


def _band(name: str, params: Mapping[str, Any], system: ControlAffineSystem) -> BarrierFamily:
    prefix = f'bands.{name}.'
    p = read_parameters(BandParameters, params, prefix=prefix)
    if p.center_index == p.index:
        raise ParameterError(f"{prefix}center_index: state {p.index} is the band's own "
                             f'{prefix}index: the band x - x would be 0, never active')
    try:
        base = BandBarrier(
            index=_index(f'{prefix}index', p.index, system.n_x),  # type: ignore[arg-type]
            half_width=p.half_width, center=p.center,
            center_index=_index(f'{prefix}center_index', p.center_index, system.n_x,
                                allow_none=True),
            name=name, form=p.form)
        return cascade(base, system, p.gammas)
    except ParameterError:
        raise
    except ValueError as exc:  # the barrier's own checks name the key below the prefix
        raise ValueError(f'{prefix}{exc}') from exc


def _gaps(p: GapParameters, system: ControlAffineSystem) -> BarrierFamily:
    if len(p.b) != len(p.a):
        raise ValueError('gaps.b: need one index per gaps.a')
    pairs = tuple((_index('gaps.a', a, system.n_x), _index('gaps.b', b, system.n_x))
                  for a, b in zip(p.a, p.b))
    same = [a for a, b in pairs if a == b]
    if same:
        raise ParameterError(f'gaps.b: state {same[0]} is also its gaps.a: a gap between an '
                             'entry and itself is 0, never above gaps.delta')
    base = PairGap(pairs=pairs, delta=p.delta)  # type: ignore
    return _cascade(base, system, p.gammas, 'gaps.gammas')


def _walls(p: WallParameters, system: ControlAffineSystem) -> BarrierFamily:
    nys = _sized('walls.ny', p.ny, len(p.nx))
    offsets = _sized('walls.offset', p.offset, len(p.nx))
    if any(a == 0.0 and b == 0.0 for a, b in zip(p.nx, nys)):
        raise ValueError('walls.nx/walls.ny: every wall needs a non-zero normal')
    base = HalfPlane(normals=tuple(zip(p.nx, nys)), offsets=offsets)
    return _cascade(base, system, p.gammas, 'walls.gammas')


def build_families(params: Mapping[str, Any],
                   system: ControlAffineSystem) -> tuple[BarrierFamily, ...]:
    """Barrier families (cascaded as configured) from the flat parameters."""
    return _families(read_parameters(FilterParameters, params), params, system)


def _check_planar(params: Mapping[str, Any], key: str) -> None:
    """Refuse ``key`` (obstacles or sources: points in a plane) on a system of the table whose
    entry declares no planar position (:attr:`rcbf_ros.messages.systems.System.
    planar_position`), and ``obstacles.position_indices`` other than the declared one: they
    would name other quantities (the cars' [p1, v1] is a position and a speed, PVTOL's [2, 3]
    its velocities). A system named by dotted path is not checked.

    Raises:
        ParameterError: naming ``key`` or ``obstacles.position_indices``, and the system.
    """
    name = params.get('system')
    if not (isinstance(name, str) and name in systems.system_names()):
        return
    entry = systems.lookup(name)
    names = [item for item, _ in entry.state]
    if entry.planar_position is None:
        raise ParameterError(f'{key}: system {name} declares no planar position (its state '
                             f'[{", ".join(names)}] holds none to place obstacles or points '
                             'in)')
    indices = read_parameters(ObstacleParameters, params, prefix='obstacles.').position_indices
    if tuple(indices) != entry.planar_position:
        shown = ', '.join(names[i] for i in entry.planar_position)
        raise ParameterError(f'obstacles.position_indices: {list(indices)} is not the planar '
                             f'position of {name}, {list(entry.planar_position)} ({shown})')


def _families(p: FilterParameters, params: Mapping[str, Any],
              system: ControlAffineSystem) -> tuple[BarrierFamily, ...]:
    """The static barrier families; none only with ``observation_sources`` (the sensor points
    are then the filter's only obstacles)."""
    families: list[BarrierFamily] = []
    if p.obstacles is not None:
        obstacles = _obstacles(p.obstacles, system)  # its own index checks first
        _check_planar(params, 'obstacles.x')
        families.append(obstacles)
    families += [_band(name, params, system) for name in band_names(params)]
    if p.gaps is not None:
        families.append(_gaps(p.gaps, system))
    if p.walls is not None:
        families.append(_walls(p.walls, system))
    if not families and not p.observation_sources:
        raise ValueError('barriers: configure at least one of obstacles.*, bands.*, gaps.*, '
                         'walls.*, observation_sources')
    return tuple(families)


def configures_barriers(params: Mapping[str, Any]) -> bool:
    """Whether flat parameters configure at least one barrier family: the conditions
    :func:`build_families` builds a family on (a layout emptied of obstacles may leave none)."""
    params = flatten(params)
    return bool(params.get('obstacles.x') or params.get('gaps.a') or params.get('walls.nx')
                or any(k.startswith('bands.') and k.count('.') == 2 for k in params))


def envelope_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """The parameters of the system's envelope: the bands that are the same in every layout.

    Obstacles, gaps, walls and every band marked ``bands.<name>.layout: true`` (e.g. PVTOL's
    safety operator, present in some layouts only) are dropped; the rest is kept as is.
    Modular SAC-RCBF keeps the envelope's correction in its losses (see
    :mod:`rcbf_ros.learning.sac`).

    Raises:
        ValueError: naming ``bands.<name>.layout`` when it is not true or false.
    """
    params = flatten(params)
    flags = {k: v for k, v in params.items()
             if k.startswith('bands.') and k.count('.') == 2 and k.endswith('.layout')}
    for key, value in flags.items():
        if not isinstance(value, bool):
            raise ValueError(f'{key}: expected true or false, got {value!r}')
    layout = {k.split('.')[1] for k, v in flags.items() if v}
    return {k: v for k, v in params.items()
            if not k.startswith(('obstacles.', 'gaps.', 'walls.'))
            and not (k.startswith('bands.') and k.split('.')[1] in layout)}


def envelope_problem(params: Mapping[str, Any]) -> RCBFProblem | None:
    """The RCBF problem of :func:`envelope_params` (None when the envelope has no barrier)."""
    envelope = envelope_params(params)
    return filter_config_from_params(envelope).problem if configures_barriers(envelope) else None


def filter_config_from_params(params: Mapping[str, Any]) -> FilterConfig:
    """Validate flat (or nested) parameters into a :class:`FilterConfig`.

    Raises:
        ValueError: one line naming the bad key.
    """
    params = flatten(params)
    system = build_system(params)
    p = read_parameters(FilterParameters, params)
    problem = RCBFProblem(
        system=system, families=_families(p, params, system), alpha=p.alpha, k_c=p.k_c,
        slack_weight=p.slack_weight,
        input_weight=_sized('input_weight', p.input_weight, system.n_u) or None)
    mean = _sized('disturbance.mean', p.disturbance.mean, system.n_x)
    std = _sized('disturbance.std', p.disturbance.std, system.n_x)
    fail_safe = _sized('fail_safe_action', p.fail_safe_action, system.n_u) or None
    if fail_safe is not None and system.u_min is not None and any(
            not lo <= a <= hi for a, lo, hi in zip(fail_safe, system.u_min, system.u_max)):
        raise ValueError(f'fail_safe_action: {list(fail_safe)} lies outside the input limits '
                         f'[{list(system.u_min)}, {list(system.u_max)}]')
    sources = _sources(p, params, system)
    footprint = None if sources is None else _footprint(p, params, system)
    # refused here, naming the key, where no margin is derived (the filter builds the same)
    sampled_data_margin(problem, control_period_s=p.control_period_s, latency_s=p.latency_s,
                        footprint=footprint)
    return FilterConfig(problem=problem, static_mean=mean, static_std=std,
                        fail_safe_action=fail_safe, compile_assembly=p.compile_assembly,
                        footprint=footprint, sources=sources,
                        control_period_s=p.control_period_s, latency_s=p.latency_s)


def _sources(p: FilterParameters, params: Mapping[str, Any],
             system: ControlAffineSystem) -> SourceConfig | None:
    """The observation sources (None without ``observation_sources``)."""
    if not p.observation_sources:
        return None
    _check_planar(params, 'observation_sources')
    taken = {key.split('.')[0] for key in parameter_keys(FilterParameters) if '.' in key}
    taken |= {'system_params', 'bands', 'obstacles', 'gaps', 'walls', 'footprint', 'tf'}
    sources = []
    for name in p.observation_sources:
        if not _SOURCE_NAME.fullmatch(name) or name in taken:
            raise ParameterError(f'observation_sources: {name!r} is not a source name (a '
                                 'letter, then letters, digits or _; not a key group of the '
                                 'filter)')
        source = read_parameters(SourceParameters, params, prefix=f'{name}.')
        if not source.type:
            raise ParameterError(f'{name}.type: required (scan, pointcloud or range)')
        if not source.topic:
            raise ParameterError(f'{name}.topic: required')
        if source.voxel_size and source.voxel_size < MIN_VOXEL_SIZE:
            raise ParameterError(f'{name}.voxel_size: {source.voxel_size:g} is neither 0 nor '
                                 f'>= {MIN_VOXEL_SIZE:g}')
        if source.min_height > source.max_height:
            raise ParameterError(f'{name}.min_height: {source.min_height:g} > '
                                 f'{name}.max_height {source.max_height:g}')
        sources.append((name, source))
    topics = [source.topic for _, source in sources]
    twice = sorted({t for t in topics if topics.count(t) > 1})
    if twice:
        raise ParameterError(f'observation_sources: topic {twice[0]!r} is taken by two sources')
    geometry = read_parameters(ObstacleParameters, params, prefix='obstacles.')
    positions = _index('obstacles.position_indices', geometry.position_indices[0],
                       system.n_x), _index('obstacles.position_indices',
                                           geometry.position_indices[1], system.n_x)
    heading = _index('obstacles.heading_index', geometry.heading_index, system.n_x,
                     allow_none=True)
    for key, frame in (('odom_frame_id', p.odom_frame_id), ('base_frame_id', p.base_frame_id)):
        if not frame:
            raise ParameterError(f'{key}: required with observation_sources')
    if p.odom_frame_id == p.base_frame_id:
        raise ParameterError(f'base_frame_id: {p.base_frame_id!r} is odom_frame_id too')
    return SourceConfig(sources=tuple(sources), odom_frame_id=p.odom_frame_id,
                        base_frame_id=p.base_frame_id,
                        position_indices=positions,  # type: ignore[arg-type]
                        heading_index=heading, transform_tolerance=p.transform_tolerance)


def _footprint(p: FilterParameters, params: Mapping[str, Any],
               system: ControlAffineSystem) -> BarrierFamily:
    """The one-obstacle family every sensor point takes: radius ``footprint.radius``, the
    margin, look-ahead, indices and cascade gains of ``obstacles.*``."""
    geometry = read_parameters(ObstacleParameters, params, prefix='obstacles.')
    if p.footprint.radius + geometry.margin <= 0.0:
        raise ParameterError('footprint.radius: footprint.radius + obstacles.margin must be > 0 '
                             'with observation_sources')
    template = replace(geometry, x=(0.0,), y=(0.0,), radius=(p.footprint.radius,))
    return _obstacles(template, system)

"""Decision logic of the safety_filter node, in plain functions (no messages, no middleware).

The node (:mod:`rcbf_ros.ros.safety_filter_node`) keeps subscriptions, parameters and timing;
the message edge (:mod:`rcbf_ros.node_logic.filter_edge`) turns bytes into checked samples and
a :class:`Decision` back into bytes (its names are importable from here too). Here, unit-tested
without launching anything (ros2cli's api/verb split):

- which parameters the node declares, and their validation into :class:`NodeSettings`;
- pairing a proposal with a state (its own ``state`` section, else the latest state message if
  it is fresh enough), choosing the disturbance box, and the fail-safe on any problem
  (:func:`decide`);
- answering a new state with the proposal in force, fail-safe once it is too old
  (:func:`decide_held`), and when a new state is answered at all (:func:`refilter_due`);
- with a sampled-data margin, a state older than ``latency_s`` is the fail-safe
  (:func:`state_age_limit_s`), and an answer goes out within ``control_period_s`` of the
  latest one (:func:`hold_due`, :func:`decide_hold`);
- throttling of repeated log lines (:class:`LogThrottle`);
- what a change of parameters at runtime builds (:func:`build_active_filter` from the merged
  parameters, :func:`merged_parameters`) and which parameters are fixed at start
  (:func:`is_read_only`).

Invariant: the published command is either within the actuator limits and meets every RCBF row
with a slack of at most ``slack_tolerance`` (checked by the filter from the rows themselves at the
published command, and again here), or the fail-safe action with an ERROR saying why. Every path
that cannot filter a proposal (bad, stale or out-of-bound input, no state yet, a failed,
unverified or infeasible solve) yields the fail-safe.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core.config import (
    BandParameters,
    filter_config_from_params,
    FILTER_OPEN_PREFIXES,
    FilterConfig,
    FilterParameters,
    OBSTACLE_LIMIT,
    SourceParameters,
)
from rcbf_ros.core.filter import (
    InputBounds,
    OSQP_EPS,
    OSQP_INT_MAX,
    OSQP_MAX_ITER,
    SafetyFilter,
)
from rcbf_ros.node_logic.edges import (  # noqa: F401 - the node's edge types, re-exported
    COMMAND_TYPES,
    MessageSettings,
    STATE_TYPES,
    TWIST_FIELDS,
)
from rcbf_ros.node_logic.filter_edge import (  # noqa: F401 - samples, answers: re-exported
    checked_vector,
    Decision,
    diagnostic_values,
    diagnostics_due,
    ERROR,
    full_info_layout,
    full_info_values,
    info_sections,
    OBSTACLE_COLUMNS,
    obstacle_parameters,
    OK,
    Proposal,
    proposal_from_sections,
    PROPOSAL_SECTIONS,
    ProposalSample,
    reason_key,
    state_from_sections,
    StateSample,
    status_code,
    status_name,
    WARN,
)
from rcbf_ros.node_logic.interface import (
    declarations,
    parameter_specs,
    ParameterSpec,
    READ_ONLY_SUFFIX,
)
from rcbf_ros.parameters.reader import (
    defaults_of,
    parameter_keys,
    ParameterError,
    parameters_of,
    read_float,
    read_floats,
    read_parameters,
    setting,
)

DURATION_LIMIT_S = 1.0e9
"""The longest duration (s) a parameter may name: the node's clock counts int64 nanoseconds
(292 years); 1e9 s leaves room for the sums it makes of them."""
SLACK_TOLERANCE_LIMIT = 0.01
"""The most slack a published command may need: a row may then go unmet by that much, which
lets a barrier fall to -0.01 / alpha (a few mm inside the margin of an obstacle); more would
publish commands that drive into obstacles as OK answers."""
DDS_INT_MAX = 2 ** 31 - 1
"""The largest history depth a DDS QoS takes (a 32-bit integer)."""




@dataclass(frozen=True)
class NodeSettings(MessageSettings):
    """Settings of the safety_filter node besides the filter itself."""

    state_frame_id: str = setting(
        '', description="with state_type odometry: the frame an Odometry's header.frame_id must "
                        "name (the obstacles' frame); '' accepts any (with "
                        'observation_sources: odom_frame_id, the only frame allowed)')
    """For 'odometry': the frame a state's header.frame_id must name ('' accepts any; with
    observation sources '' means ``odom_frame_id``, and no other frame is accepted:
    :func:`state_frame_settings`)."""
    max_state_age_s: float = setting(
        0.5, positive=True, maximum=DURATION_LIMIT_S,
        description='a `state` older than this (s, since its arrival) is stale: fail-safe')
    """A state message older than this (since its arrival) is stale: fail-safe."""
    refilter_on_state: bool = setting(
        False, description='filter the proposal in force again on every new state and source '
                           'message (at most every refilter_min_period_s); false: one answer '
                           'per proposal (lock-step)')
    """Answer each new ``state`` (and observation source) message too, by filtering the
    latest proposal again against the newest state (:func:`decide_held`).

    Off by default: a lock-step simulator steps on every answer that names its pending state,
    so an answer per state besides the answer per proposal would step it on the previous
    proposal's command. The drop-in launch turns it on: a robot's base holds the last
    command, which must stay safe while the robot moves and the controller is quiet."""
    refilter_min_period_s: float = setting(
        0.01, minimum=0, maximum=DURATION_LIMIT_S,
        description='least time (s) from any answer to a re-filter (0: one per state or '
                    'source message)')
    """The least time from the latest answer (a proposal's or a re-filter's) to a re-filter:
    a state that comes sooner is not answered (the next one is), which bounds the re-filters
    to 1 / refilter_min_period_s a second (100 by default) whatever the state rate, and skips
    the state right after a proposal's answer. 0.01 s leaves a 50 Hz odometry's jitter room:
    each of its messages is answered."""
    max_proposal_age_s: float = setting(
        0.5, positive=True, maximum=DURATION_LIMIT_S,
        description='a re-filtered proposal older than this (s, since its arrival) is stale: '
                    'fail-safe until a new one arrives')
    """A re-filtered proposal older than this (since its arrival) gives the fail-safe, as a
    base's command timeout would; a proposal's own answer is made when it arrives (age 0)."""
    stop_pub_timeout: float = setting(
        2.0, minimum=0, maximum=DURATION_LIMIT_S,
        description="how long (s) a quiet controller's fail-safe goes on being published "
                    "before the node goes quiet too, until a new proposal (collision_monitor's "
                    'name and default)')
    """After a proposal is ``max_proposal_age_s`` old, its fail-safe goes out for this long
    (at states and timer calls), then nothing until a new proposal arrives: the base holds the
    fail-safe it got last, and another publisher of its command (teleoperation through a
    multiplexer) is not drowned in it. Nav2 collision_monitor's ``stop_pub_timeout``."""
    slack_tolerance: float = setting(
        1.0e-4, minimum=0, maximum=SLACK_TOLERANCE_LIMIT,
        description='most slack the published command may need in any RCBF row; more: fail-safe')
    """The most slack the published command may need in any RCBF row; more (the rows are
    infeasible within the input limits) publishes the fail-safe.

    An active but feasible row still carries eps ~ |u_S| / (l |L_g h|) > 0 (the soft penalty
    l eps^2 of the paper's QP), about 1e-6 with l = 1e6, hence the default 1e-4."""
    input_bounds: InputBounds = field(default_factory=InputBounds)
    """Magnitude bounds of state, proposal and disturbance box; beyond them: fail-safe."""
    log_throttle_s: float = setting(
        1.0, minimum=0, maximum=DURATION_LIMIT_S,
        description='least time (s) between two log lines with the same reason')
    """Minimum period of repeated log lines with the same reason."""
    qos_reliable: bool = setting(
        True, key='qos.reliable', read_only=True,
        description='reliable (true) or best-effort (false) QoS on every topic')
    """Reliable (True) or best-effort QoS on every topic."""
    qos_depth: int = setting(10, key='qos.depth', strict=True, minimum=1, maximum=DDS_INT_MAX,
                             read_only=True,
                             description='keep-last history depth on every topic')
    """Keep-last history depth on every topic."""
    osqp_eps_abs: float = setting(OSQP_EPS, key='osqp.eps_abs', positive=True,
                                  description='OSQP absolute tolerance')
    """OSQP absolute tolerance."""
    osqp_eps_rel: float = setting(OSQP_EPS, key='osqp.eps_rel', positive=True,
                                  description='OSQP relative tolerance')
    """OSQP relative tolerance."""
    osqp_max_iter: int = setting(
        OSQP_MAX_ITER, key='osqp.max_iter', strict=True, minimum=1, maximum=OSQP_INT_MAX,
        description='OSQP iteration cap (then the interior-point fallback, else fail-safe)')
    """OSQP iteration cap (a starved solve yields the fail-safe)."""
    diagnostics_min_period_s: float = setting(
        0.1, key='diagnostics.min_period_s', minimum=0, maximum=DURATION_LIMIT_S,
        description='least time (s) between two OK diagnostics (0: one per proposal); WARN and '
                    'ERROR always go out; filter_info carries every answer')
    """Minimum period of OK diagnostics (0: one per proposal); WARN / ERROR always go out.

    ``/diagnostics`` is for people and monitors (diagnostic_updater publishes at about 1 Hz);
    ``filter_info`` is the record of every answer. By default OK statuses go out at most at
    10 Hz, so that a DiagnosticArray per command does not bound the rate the node keeps up
    with."""
    diagnostics_name: str = setting('safety_filter', key='diagnostics.name',
                                    description='DiagnosticStatus.name')
    """DiagnosticStatus.name."""
    diagnostics_hardware_id: str = setting('', key='diagnostics.hardware_id',
                                           description='DiagnosticStatus.hardware_id')
    """DiagnosticStatus.hardware_id."""


NODE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(NodeSettings)
"""Parameters of the node itself (not of the filter), in declaration order."""

NODE_PARAMETER_DEFAULTS: dict[str, Any] = defaults_of(NodeSettings)
"""Name -> default of :data:`NODE_PARAMETERS`."""

_OPEN_FAMILIES: tuple[ParameterSpec, ...] = (
    ParameterSpec('system_params.<name>', None, 'any',
                  'constructor argument <name> of the system (e.g. with_operator)'
                  + READ_ONLY_SUFFIX),
    *parameter_specs(BandParameters, prefix='bands.<name>.', declared_defaults=False,
                     say_default=True),
)

SOURCE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(
    SourceParameters, prefix='<name>.', declared_defaults=False, say_default=True)
"""``<name>.*`` of each observation source (a name of ``observation_sources``): declared when
given, fixed at start."""

FILTER_DESCRIPTIONS: dict[str, str] = {
    spec.name: spec.description
    for spec in parameter_specs(FilterParameters) + _OPEN_FAMILIES[:1]
    + parameter_specs(BandParameters, prefix='bands.<name>.')}
"""Key -> one line, without the filter's default (for nodes that declare the keys with values
of their own)."""

FILTER_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(
    FilterParameters, declared_defaults=False, say_default=True) + _OPEN_FAMILIES \
    + SOURCE_PARAMETERS
"""Keys of :func:`rcbf_ros.core.config.filter_config_from_params` (``config/<system>.yaml``),
from :class:`rcbf_ros.core.config.FilterParameters`. Not set (``None``) by default: the
config's own default applies. ``<name>`` families are declared when the parameter overrides
(YAML, ``-p``) name them."""

PARAMETERS: tuple[ParameterSpec, ...] = NODE_PARAMETERS + FILTER_PARAMETERS
"""Every parameter the safety_filter node declares (one spec per declaration)."""

FILTER_PARAMETER_KEYS: tuple[str, ...] = parameter_keys(FilterParameters)
"""The fixed keys of the filter's configuration (the fields of FilterParameters)."""
OPEN_PARAMETER_PREFIXES: tuple[str, ...] = FILTER_OPEN_PREFIXES
"""Families of keys whose names are chosen by the user (``bands.operator.index``, ...)."""
_KNOWN_NAMES = frozenset(spec.name for spec in PARAMETERS if not spec.pattern)
_KEY_GROUPS = frozenset(spec.name.split('.', 1)[0] for spec in PARAMETERS if '.' in spec.name
                        and not spec.name.startswith('<'))


READ_ONLY_PARAMETERS: tuple[str, ...] = tuple(
    p.key for cls in (NodeSettings, FilterParameters) for p in parameters_of(cls)
    if p.rule.read_only)
"""Parameters fixed at start: they choose the state and input sizes, the message types and the
endpoints' QoS. Declared read-only; a set is refused (``ros2 param describe`` says so)."""
READ_ONLY_PREFIXES: tuple[str, ...] = ('system_params.',)
"""Families fixed at start (a system's constructor arguments may change n_x or n_u)."""
READ_ONLY_DESCRIPTION = 'read-only: fixed at start (restart the node to change it)'
"""The description of a read-only parameter's descriptor."""


def is_source_key(name: str) -> bool:
    """Whether ``name`` is a key of an observation source (``<name>.timeout_s``, ...:
    :data:`SOURCE_PARAMETERS`), its source name not a group of the filter's own keys."""
    group = name.split('.', 1)[0]
    return group not in _KEY_GROUPS and any(spec.matches(name) for spec in SOURCE_PARAMETERS)


def is_read_only(name: str) -> bool:
    """Whether the parameter ``name`` is fixed at start (:data:`READ_ONLY_PARAMETERS`, the
    open families of :data:`READ_ONLY_PREFIXES`, every source key)."""
    return (name in READ_ONLY_PARAMETERS or name.startswith(READ_ONLY_PREFIXES)
            or is_source_key(name))


def feeds_the_filter(name: str) -> bool:
    """Whether the parameter ``name`` is read by :func:`build_active_filter` (a node or filter
    key of :data:`PARAMETERS`, or one of the open families); other parameters (``use_sim_time``,
    a shared params file's keys for other nodes) change nothing here."""
    return (name in _KNOWN_NAMES or name.startswith(OPEN_PARAMETER_PREFIXES)
            or is_source_key(name))


def parameter_declarations(override_names: Sequence[str] = ()) -> list[tuple[str, Any]]:
    """Every (name, default) the node declares, from :data:`PARAMETERS`.

    The fixed filter keys default to ``None`` (not set); keys under the open prefixes
    (``system_params.*``, ``bands.<name>.*``) are declared when the parameter overrides (YAML,
    ``-p``) name them, so that a ``bands.operator.*`` block is read without listing it anywhere.

    Args:
        override_names: names of the parameter overrides the node was started with.
    """
    declared: dict[str, Any] = dict(declarations(PARAMETERS))
    for name in sorted(override_names):
        if (name.startswith(OPEN_PARAMETER_PREFIXES) or is_source_key(name)) \
                and name not in declared:
            declared[name] = None
    return list(declared.items())


def collect_parameters(values: Mapping[str, Any]) -> dict[str, Any]:
    """Declared parameter values -> the flat dict the config functions take (unset dropped).

    Tuples and numpy arrays (as some middlewares return arrays) become lists.
    """
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if value is None:
            continue
        if isinstance(value, (tuple, np.ndarray)) or type(value).__name__ == 'array':
            value = list(value)
        flat[key] = value
    return flat


def node_settings_from_params(params: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (missing ones take their defaults).

    Raises:
        ValueError: naming the bad key.
    """
    return read_parameters(NodeSettings, params)


def build_safety_filter(*, config: FilterConfig, settings: NodeSettings) -> SafetyFilter:
    """The node's filter: the configured problem with the node's solver settings, slack
    tolerance and input bounds (the one construction shared by the node and refilter).

    Raises:
        ValueError: naming the bad key.
    """
    return SafetyFilter(
        config.problem, fail_safe_action=config.fail_safe_action,
        eps_abs=settings.osqp_eps_abs, eps_rel=settings.osqp_eps_rel,
        max_iter=settings.osqp_max_iter, compile_assembly=config.compile_assembly,
        slack_tolerance=settings.slack_tolerance, input_bounds=settings.input_bounds,
        footprint=config.footprint, control_period_s=config.control_period_s,
        latency_s=config.latency_s)


@dataclass(frozen=True)
class ActiveFilter:
    """Everything the node filters with, built from one set of parameters; the node swaps the
    whole of it at once when the parameters change (a callback reads one of these, never half
    of an old one and half of a new one)."""

    params: Mapping[str, Any]
    """The flat parameters it was built from (:func:`collect_parameters`)."""
    settings: NodeSettings
    """The node's own settings."""
    config: FilterConfig
    """The filter's configuration (problem, static disturbance box, fail-safe action)."""
    safety_filter: SafetyFilter
    """The filter itself."""
    static_mean: np.ndarray = field(init=False, repr=False, compare=False)
    """``config.static_mean`` as a read-only float64 array (empty: none), made once for every
    :func:`decide` that uses it."""
    static_std: np.ndarray = field(init=False, repr=False, compare=False)
    """``config.static_std`` likewise."""

    def __post_init__(self) -> None:
        for name in ('static_mean', 'static_std'):
            array = np.array(getattr(self.config, name), dtype=np.float64).reshape(-1)
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def robot_frame_id(self) -> str:
        """The child frame an Odometry state must name: ``base_frame_id`` with observation
        sources, whose points are placed in the robot's frame by its pose ('' without: any)."""
        return self.config.sources.base_frame_id if self.config.sources is not None else ''


def build_active_filter(*, params: Mapping[str, Any],
                        probe_states: Sequence[Sequence[float]] = (),
                        changed: Sequence[str] = ()) -> ActiveFilter:
    """Validate every parameter and build the filter: the one construction of the node's
    start and of every change at runtime (the same checks, the same messages).

    Beyond each key's own checks, a filter is accepted only if it can filter: every length
    of its geometry lies within ``input_bounds.state`` (:func:`check_geometry`), and its rows
    can be evaluated in float64 within the QP's data limit at the origin and at every one of
    ``probe_states`` (e.g. the robot's latest state), with its static disturbance box
    (:meth:`rcbf_ros.core.filter.SafetyFilter.evaluation_refusal`). Parameters that fail
    there would make every answer the fail-safe: filtering switched off by a value.

    Args:
        changed: the keys a change at runtime sets: the probe's refusal names one of them
            (the one without which the filter passes, else all); at start (none), the first
            key of ``params`` without which it passes.

    Raises:
        ValueError: one line naming the bad key (:class:`ProbeError` for the evaluation
            check: the key without which the filter would pass it, and the state).
    """
    active = _built(params)
    reason = _probe_refusal(active, probe_states)
    if reason is not None:
        blamed = _blame(active.params, probe_states, changed or tuple(active.params))
        raise ProbeError(f'{blamed or ", ".join(changed) or "parameters"}: with this value the '
                         f'filter could never filter (every answer the fail-safe) {reason}')
    return active


def _built(params: Mapping[str, Any]) -> ActiveFilter:
    """The filter of ``params`` after every check but the probe."""
    params = collect_parameters(params)
    settings = node_settings_from_params(params)
    config = filter_config_from_params(params)
    settings = state_frame_settings(settings, config)
    check_geometry(params, bounds=settings.input_bounds)
    system = config.problem.system
    for key, limits in (('input_limits.min', system.u_min), ('input_limits.max', system.u_max)):
        # a proposal within the limits must never be refused as out of bounds
        _within(key, limits or (), settings.input_bounds.command, 'input_bounds.command')
    safety_filter = build_safety_filter(config=config, settings=settings)
    settings.check_inputs(n_u=safety_filter.n_u, system=str(params.get('system')))
    return ActiveFilter(params=params, settings=settings, config=config,
                        safety_filter=safety_filter)


def state_frame_settings(settings: NodeSettings, config: FilterConfig) -> NodeSettings:
    """``settings`` with the frame a state must be in: with observation sources, whose points
    are placed in ``odom_frame_id``, a state in any other frame would be filtered against
    points in the wrong place, so ``state_frame_id`` '' becomes ``odom_frame_id`` and any
    other value is refused.

    Raises:
        ParameterError: naming ``state_frame_id`` and ``odom_frame_id``.
    """
    if config.sources is None:
        return settings
    odom = config.sources.odom_frame_id
    if settings.state_frame_id not in ('', odom):
        raise ParameterError(
            f'state_frame_id: {settings.state_frame_id!r} is not odom_frame_id {odom!r}: the '
            "observation sources' points are placed in odom_frame_id, so the state must be "
            "in it too ('' takes odom_frame_id)")
    return replace(settings, state_frame_id=odom)


def _probe_refusal(active: ActiveFilter, probe_states: Sequence[Sequence[float]]) -> str | None:
    """Why ``active`` cannot evaluate its rows at the origin or a probe state, or None."""
    safety_filter = active.safety_filter
    mean = active.static_mean if active.static_mean.size else None
    std = active.static_std if active.static_std.size else None
    for state in ([0.0] * safety_filter.n_x, *probe_states):
        reason = safety_filter.evaluation_refusal(state, mean, std)
        if reason is not None:
            shown = ', '.join(f'{v:.6g}' for v in state)
            return f'at the state [{shown}]: {reason}'
    return None


def _blame(params: Mapping[str, Any], probe_states: Sequence[Sequence[float]],
           suspects: Sequence[str]) -> str:
    """The first of ``suspects`` without which the filter passes the probe (its default taken
    instead), or '' when no single one is to blame. Each try builds a filter: at runtime only
    the keys of the change are tried, so that a refusal costs a few builds."""
    for key in suspects:
        if key not in params or key == 'system' or is_read_only(key):
            continue
        try:
            trial = _built({k: v for k, v in params.items() if k != key})
        except Exception:  # the others do not make a filter without it: not this one alone
            continue
        if _probe_refusal(trial, probe_states) is None:
            return key
    return ''


class ProbeError(ValueError):
    """Parameters each valid on its own whose filter cannot evaluate its rows at a probe
    state (:func:`build_active_filter`)."""


GEOMETRY_KEYS = ('obstacles.x', 'obstacles.y', 'obstacles.radius', 'obstacles.margin',
                 'obstacles.lookahead', 'walls.offset', 'gaps.delta')
"""Lengths (m) of the barrier geometry, besides the bands' ``center`` and ``half_width``."""


def check_geometry(params: Mapping[str, Any], *, bounds: InputBounds) -> None:
    """Every length of the barrier geometry (:data:`GEOMETRY_KEYS`, ``bands.<name>.center``
    and ``.half_width``), every obstacle's radius plus margin and every wall's distance from
    the origin lie within ``input_bounds.state``.

    A state beyond its bound is refused anyway; geometry beyond it is nowhere a state may
    be, and its squares overflow float64 long before 1e308 (an obstacle at x = 1e200, a
    radius of 1e154, a wall whose normal of 1e-300 puts it 1e300 m away): every answer would
    be the fail-safe.

    Raises:
        ParameterError: naming the key, the value and the bound.
    """
    bound = bounds.state
    keys = [*GEOMETRY_KEYS, *(k for k in params if k.startswith('bands.')
                              and k.endswith(('.center', '.half_width')))]
    for key in keys:
        _within(key, read_floats(key, params.get(key), max_length=OBSTACLE_LIMIT), bound,
                'input_bounds.state')
    radii = read_floats('obstacles.radius', params.get('obstacles.radius'),
                        max_length=OBSTACLE_LIMIT)
    margin = read_float('obstacles.margin', params.get('obstacles.margin', 0.0))
    if radii and not max(radii) + margin <= bound:
        raise ParameterError(f'obstacles.radius: {max(radii):.6g} plus obstacles.margin '
                             f'{margin:.6g} lies beyond input_bounds.state = {bound:.6g}')
    normals = zip(read_floats('walls.nx', params.get('walls.nx')),
                  read_floats('walls.ny', params.get('walls.ny')),
                  read_floats('walls.offset', params.get('walls.offset')))
    _within('walls.offset', [abs(c) / math.hypot(a, b) for a, b, c in normals if a or b],
            bound, 'input_bounds.state', what='a wall at distance')


def _within(key: str, values: Sequence[float], bound: float, name: str, *,
            what: str = '') -> None:
    """Refuse, naming ``key``, the first of ``values`` whose magnitude is beyond ``bound``."""
    far = [v for v in values if not abs(v) <= bound]
    if far:
        lead = f'{what} ' if what else ''
        raise ParameterError(f'{key}: {lead}{far[0]:.6g} lies beyond {name} = {bound:.6g} '
                             '(no input the filter takes is there)')


def merged_parameters(*, current: Mapping[str, Any],
                      changes: Mapping[str, Any]) -> dict[str, Any]:
    """``current`` with ``changes`` applied (a value of None unsets the key), as the flat dict
    :func:`build_active_filter` takes."""
    merged = dict(current)
    merged.update(changes)
    return collect_parameters(merged)


def same_parameters(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two flat parameter dicts hold the same keys with the same values of the same
    types (``True`` is not ``1.0``, which ``==`` takes it for: a change from one to the other
    is built, and refused when the key takes no bool)."""
    return a.keys() == b.keys() and all(
        type(a[key]) is type(b[key]) and repr(a[key]) == repr(b[key]) for key in a)


_NOT_SET = object()


def describe_changes(*, old: Mapping[str, Any], new: Mapping[str, Any],
                     width: int = 160) -> str:
    """``key: old -> new`` for every key whose value differs, ``; `` between them (each value
    cut to ``width`` characters); '' when nothing differs."""
    def shown(key: str, params: Mapping[str, Any]) -> str:
        value = params.get(key, _NOT_SET)
        if isinstance(value, list) and len(value) > width:  # its text begins the same
            value = value[:width]
        text = 'not set' if value is _NOT_SET else repr(value)
        return text if len(text) <= width else text[:width - 3] + '...'
    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    return '; '.join(f'{key}: {shown(key, old)} -> {shown(key, new)}' for key in keys)


def state_age_s(*, sample: StateSample, now_ns: int) -> float:
    """Seconds since the sample arrived."""
    return (now_ns - sample.received_ns) * 1e-9


def state_age_limit_s(*, control_period_s: float, latency_s: float) -> float | None:
    """The most a state may be aged at a decision: ``latency_s`` when a sampled-data margin is
    in force (``control_period_s`` or ``latency_s`` > 0: the margin covers a state at most
    ``latency_s`` old when its command starts to act, docs/SAFETY_FILTER.md), else None (no
    bound beyond ``max_state_age_s``)."""
    return latency_s if control_period_s > 0 or latency_s > 0 else None


def decision_age_s(*, received_ns: int, now_ns: int, stamp_ns: int | None = None,
                   stamp_now_ns: int | None = None) -> float:
    """Seconds a state is old at a decision at ``now_ns``: since its arrival (monotonic), and
    for a stamped one (an Odometry) since its header stamp on the node's clock
    (``stamp_now_ns``: ROS time, simulation time under ``use_sim_time``), the larger of the
    two, as an observation source's age is counted: a stamp in the future does not make a
    state younger than its arrival, a stamp far in the past (or none, 0) makes it old."""
    newest = now_ns - received_ns
    if stamp_ns is not None and stamp_now_ns is not None:
        newest = max(newest, stamp_now_ns - stamp_ns)
    return newest / 1e9  # correctly rounded: 20 ms is 0.02, not above latency_s = 0.02


def late_state_reason(*, age_s: float, latency_s: float) -> str:
    """The fail-safe's reason for a state older than ``latency_s`` (status 19, late state)."""
    return f'late state: {age_s:.6f} s old > latency_s = {latency_s:g}'


def fail_safe_decision(*, safety_filter: SafetyFilter, reason: str,
                       u_rl: np.ndarray | None = None, state: np.ndarray | None = None,
                       state_source: str = '') -> Decision:
    """The fail-safe command with an ERROR and its reason."""
    proposal = None if u_rl is None else np.asarray(u_rl, dtype=np.float64)
    return Decision(u_safe=safety_filter.fail_safe_action.copy(), u_rl=proposal, level=ERROR,
                    reason=reason, fail_safe=True, state=state, state_source=state_source)


def _disturbance(learned: np.ndarray | None, static: Sequence[float]) -> np.ndarray | None:
    if learned is not None:
        return learned
    return np.asarray(static, dtype=np.float64) if len(static) else None


def decide(*, safety_filter: SafetyFilter, proposal: Proposal | None, proposal_error: str = '',
           latest_state: StateSample | None, now_ns: int, max_state_age_s: float,
           static_mean: Sequence[float] = (), static_std: Sequence[float] = (),
           slack_tolerance: float = 1e-4,
           sense: Callable[[np.ndarray], str] | None = None,
           latency_s: float | None = None, stamp_now_ns: int | None = None,
           proposal_received_ns: int | None = None) -> Decision:
    """Filter one proposal, or decide the fail-safe.

    State: the proposal's own ``state`` section when it has one (the proposer's state: no
    staleness check), else ``latest_state`` from the state topic, which must exist, be valid
    and be at most ``max_state_age_s`` old (measured from its arrival).
    Disturbance box: the proposal's learned mean / std when present, else the static ones from
    the parameters (each independently; empty: none).
    With a sampled-data margin (``latency_s`` not None: :func:`state_age_limit_s`) the state
    chosen must also be at most ``latency_s`` old (:func:`decision_age_s`; the proposal's own
    state counts from the proposal's arrival), else the fail-safe, status 19 (late state).

    Args:
        proposal: the validated proposal, or None when it was rejected.
        proposal_error: why the proposal was rejected (used when ``proposal`` is None).
        latest_state: the latest state message, or None when none arrived yet.
        now_ns: monotonic time of the proposal's arrival in nanoseconds.
        sense: called with the state chosen, before the filter: sets the filter's sensor
            points for it (:mod:`rcbf_ros.node_logic.sources`); a reason ('' for none) makes
            the answer the fail-safe.
        latency_s: the most the state may be aged at the decision (None: no such bound).
        stamp_now_ns: the node's clock (ROS time) at the decision, for an Odometry's stamp.
        proposal_received_ns: the proposal's arrival (monotonic ns; None: ``now_ns``), from
            which its own state's age counts.

    Returns:
        ERROR + fail-safe on bad input, no / bad / stale state, a refused input, a failed or
        unverified solve, or rows that need more slack than ``slack_tolerance`` (checked here
        too, whatever tolerance the filter was built with); OK otherwise.
    """
    if proposal is None:
        return fail_safe_decision(safety_filter=safety_filter,
                                  reason=f'bad proposal: {proposal_error or "unusable"}')
    if proposal.state is not None:
        state, source = proposal.state, 'proposal'
        if latency_s is not None:
            age = decision_age_s(received_ns=now_ns if proposal_received_ns is None
                                 else proposal_received_ns, now_ns=now_ns)
            if not age <= latency_s:
                return fail_safe_decision(
                    safety_filter=safety_filter, u_rl=proposal.u, state=state,
                    state_source=source, reason=late_state_reason(age_s=age, latency_s=latency_s))
    elif latest_state is None:
        return fail_safe_decision(safety_filter=safety_filter, u_rl=proposal.u,
                                  reason='no state received yet')
    elif latest_state.state is None:
        return fail_safe_decision(safety_filter=safety_filter, u_rl=proposal.u,
                                  reason=f'bad state: {latest_state.error}')
    else:
        age = state_age_s(sample=latest_state, now_ns=now_ns)
        if age > max_state_age_s:
            return fail_safe_decision(
                safety_filter=safety_filter, u_rl=proposal.u,
                reason=f'stale state: {age:.3f} s old > max_state_age_s = {max_state_age_s}')
        state, source = latest_state.state, 'topic'
        if latency_s is not None:
            age = decision_age_s(received_ns=latest_state.received_ns, now_ns=now_ns,
                                 stamp_ns=latest_state.stamp_ns, stamp_now_ns=stamp_now_ns)
            if not age <= latency_s:
                return fail_safe_decision(
                    safety_filter=safety_filter, u_rl=proposal.u, state=state,
                    state_source=source, reason=late_state_reason(age_s=age, latency_s=latency_s))
    if sense is not None:
        reason = sense(state)
        if reason:
            return fail_safe_decision(safety_filter=safety_filter, u_rl=proposal.u,
                                      reason=reason, state=state, state_source=source)
    mean = _disturbance(proposal.disturbance_mean, static_mean)
    std = _disturbance(proposal.disturbance_std, static_std)
    try:
        result = safety_filter.filter(state, proposal.u, mean, std)
    except ValueError as exc:  # validated above; kept so that no path skips the fail-safe
        return fail_safe_decision(safety_filter=safety_filter, u_rl=proposal.u,
                                  reason=f'bad input: {exc}', state=state, state_source=source)
    if result.fail_safe:
        return Decision(u_safe=result.u_safe, u_rl=proposal.u, level=ERROR,
                        reason=f'{result.status}: {result.reason}', fail_safe=True,
                        result=result, state_source=source, state=state)
    if not result.needed_slack <= slack_tolerance:  # NaN too
        return Decision(u_safe=safety_filter.fail_safe_action.copy(), u_rl=proposal.u,
                        level=ERROR, fail_safe=True, result=result, state_source=source,
                        state=state,
                        reason=f'slack_exceeded: barrier rows need slack '
                               f'{result.needed_slack:.3g} > slack_tolerance '
                               f'{slack_tolerance:.3g}')
    return Decision(u_safe=result.u_safe, u_rl=proposal.u, level=OK, reason='',
                    fail_safe=False, result=result, state_source=source, state=state)


class HeldProposal(NamedTuple):
    """The proposal in force: the latest ``cmd_proposed`` sample as read (a bad one too: it is
    what the controller last asked for), and when it arrived (a tuple, as
    :class:`ProposalSample`: one per proposal)."""

    sample: ProposalSample
    """The sample as read (:meth:`rcbf_ros.node_logic.filter_edge.FilterEdge.read_proposal`)."""
    received_ns: int
    """Monotonic arrival time in nanoseconds (its age counts from here)."""


def proposal_age_s(*, held: HeldProposal, now_ns: int) -> float:
    """Seconds since the held proposal arrived."""
    return (now_ns - held.received_ns) / 1e9  # correctly rounded: 9 ms is 0.009


def refilter_due(*, enabled: bool, held: HeldProposal | None, last_answer_ns: int | None,
                 now_ns: int, min_period_s: float) -> bool:
    """Whether a new state (or source) message arriving at ``now_ns`` is answered by filtering
    the held proposal again: re-filtering is on, a proposal is held, and the latest answer (a
    proposal's or a re-filter's, at ``last_answer_ns``; None: none yet) is at least
    ``min_period_s`` old.

    Each message asks once, so there is at most one re-filter per message; ``min_period_s``
    bounds them to 1 / min_period_s a second whatever the message rate, and skips the message
    right after a proposal's answer (that answer is the check of the command in force)."""
    if not enabled or held is None:
        return False
    return last_answer_ns is None or (now_ns - last_answer_ns) / 1e9 >= min_period_s


def decide_held(*, held: HeldProposal, again: bool, safety_filter: SafetyFilter,
                latest_state: StateSample | None, now_ns: int, max_state_age_s: float,
                max_proposal_age_s: float, static_mean: Sequence[float] = (),
                static_std: Sequence[float] = (), slack_tolerance: float = 1e-4,
                sense: Callable[[np.ndarray], str] | None = None,
                latency_s: float | None = None, stamp_now_ns: int | None = None) -> Decision:
    """The answer to a held proposal: at its arrival (``again`` False), or again at a new
    state or source message or at the hold timer (``again`` True).

    Filtered again, a proposal more than ``max_proposal_age_s`` old (since its arrival) gives
    the fail-safe, as a base's command timeout would: a controller that went quiet no longer
    drives the robot. Otherwise it is filtered against the newest state: the latest state
    message when it arrived after the proposal, else the proposal's own ``state`` section if
    it has one (:func:`decide`, whose checks apply as they are). At its arrival a proposal's
    age is 0: the age check is for re-filtering alone.

    Args:
        now_ns: monotonic time of the message answered (the proposal's arrival, or the new
            state's, or the timer's call); the other arguments: as :func:`decide`'s (the
            proposal's own state aged from the proposal's arrival).
    """
    sample = held.sample
    u_rl = sample.proposal.u if sample.proposal is not None else None
    if again:
        age = proposal_age_s(held=held, now_ns=now_ns)
        if age > max_proposal_age_s:
            return fail_safe_decision(
                safety_filter=safety_filter, u_rl=u_rl,
                reason=f'stale proposal: {age:.3f} s old > max_proposal_age_s = '
                       f'{max_proposal_age_s}')
    if sample.undecodable:
        return fail_safe_decision(safety_filter=safety_filter,
                                  reason=f'undecodable proposal: {sample.error}')
    proposal = sample.proposal
    if (again and proposal is not None and proposal.state is not None
            and latest_state is not None and latest_state.received_ns > held.received_ns):
        proposal = replace(proposal, state=None)  # the state message is newer: filter at it
    return decide(safety_filter=safety_filter, proposal=proposal, proposal_error=sample.error,
                  latest_state=latest_state, now_ns=now_ns, max_state_age_s=max_state_age_s,
                  static_mean=static_mean, static_std=static_std,
                  slack_tolerance=slack_tolerance, sense=sense, latency_s=latency_s,
                  stamp_now_ns=stamp_now_ns, proposal_received_ns=held.received_ns)


HOLD_TIMER_DIVISOR = 4
"""The hold timer calls every ``control_period_s`` / 4: an answer goes out when the next call
would come more than ``control_period_s`` after the latest answer (:func:`hold_due`), so a
quiet node answers every 3/4 to 1 period."""
HOLD_TIMER_MIN_PERIOD_S = 0.001
"""The hold timer calls at most every millisecond (a ``control_period_s`` under 4 ms then
gets answers up to 1 ms + control_period_s * 3/4 apart): the timer's own cost stays bounded
whatever the parameter."""


def hold_timer_period_s(control_period_s: float) -> float | None:
    """The hold timer's period for ``control_period_s`` (None: no timer, T = 0)."""
    if not control_period_s > 0:
        return None
    return max(control_period_s / HOLD_TIMER_DIVISOR, HOLD_TIMER_MIN_PERIOD_S)


def hold_due(*, control_period_s: float, timer_period_s: float, last_answer_ns: int | None,
             now_ns: int) -> bool:
    """Whether the hold timer, called at ``now_ns``, answers: a sampled-data margin covers a
    command for ``control_period_s`` (T) after its state, so the next answer must go out within
    T of the latest (``last_answer_ns``, None: none yet, nothing to hold); it does when the
    timer's next call, ``timer_period_s`` later, would be too late. At most one answer per
    call."""
    if not control_period_s > 0 or last_answer_ns is None:
        return False
    return (now_ns - last_answer_ns) * 1e-9 + timer_period_s >= control_period_s


def answer_overrun_s(*, control_period_s: float, previous_ns: int | None,
                     now_ns: int) -> float | None:
    """By how much (s) an answer at ``now_ns`` comes later than ``control_period_s`` after the
    previous one (``previous_ns``): None when it does not, when there is no period (0: no
    promise to keep) or no previous answer. With a period the hold timer answers within it, so
    an overrun means the node could not answer meanwhile (a long callback, an overloaded
    machine)."""
    if not control_period_s > 0 or previous_ns is None:
        return None
    over_s = (now_ns - previous_ns) * 1e-9 - control_period_s
    return over_s if over_s > 0 else None


def decide_hold(*, held: HeldProposal | None, safety_filter: SafetyFilter,
                control_period_s: float, **kwargs: Any) -> Decision:
    """The hold timer's answer: the proposal in force filtered again at the newest state
    (:func:`decide_held`, ``again``), the fail-safe when none is held; a late state's fail-safe
    says that the command in force ran out (``control_period_s``) without a fresh state."""
    if held is None:
        return fail_safe_decision(
            safety_filter=safety_filter,
            reason=f'internal error: no proposal in force (lost to an earlier internal '
                   f'error), answered again within control_period_s = {control_period_s:g}')
    decision = decide_held(held=held, again=True, safety_filter=safety_filter, **kwargs)
    if decision.fail_safe and reason_key(decision.reason) == 'late state':
        decision = replace(decision, reason=f'{decision.reason}, and the command in force ran '
                                            f'out (control_period_s = {control_period_s:g})')
    return decision


class LogThrottle:
    """Say a repeated problem at most once per period (per reason key)."""

    def __init__(self, period_s: float) -> None:
        """Args: period_s: minimum seconds between two lines with the same key."""
        self.period_ns = int(period_s * 1e9)
        self._last: dict[str, int] = {}
        self.suppressed: dict[str, int] = {}

    def should_log(self, *, key: str, now_ns: int) -> bool:
        """True when ``key`` was not logged within the period (and record it as logged)."""
        last = self._last.get(key)
        if last is not None and now_ns - last < self.period_ns:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return False
        self._last[key] = now_ns
        return True

    def pop_suppressed(self, key: str) -> int:
        """How many lines with ``key`` were suppressed since the last one logged."""
        return self.suppressed.pop(key, 0)



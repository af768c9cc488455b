"""Decision logic of the safety_filter node, in plain functions (no messages, no middleware).

The node (:mod:`rcbf_ros.ros.safety_filter_node`) is a thin wrapper: it turns messages into the
arrays these functions take and publishes what they return. Everything that decides *what* is
published lives here and is unit-tested without launching anything (ros2cli's api/verb split):

- which parameters the node declares, and their validation into :class:`NodeSettings`;
- validating a state or a proposal (sections of a ``Float64MultiArray``) into arrays;
- pairing a proposal with a state (its own ``state`` section, else the latest state message if
  it is fresh enough), choosing the disturbance box, and the fail-safe on any problem
  (:func:`decide`);
- the diagnostic level, message and key/values of one decision (:func:`diagnostic_values`);
- throttling of repeated log lines (:class:`LogThrottle`).

Invariant: the published command is either within the actuator limits and meets every RCBF row
with a slack of at most ``slack_tolerance`` (checked by the filter from the rows themselves at the
published command, and again here), or the fail-safe action with an ERROR saying why. Every path
that cannot filter a proposal (bad, stale or out-of-bound input, no state yet, a failed,
unverified or infeasible solve) yields the fail-safe.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.config import FilterConfig, number
from rcbf_ros.core.filter import (
    FilterResult,
    InputBounds,
    OSQP_EPS,
    OSQP_MAX_ITER,
    SafetyFilter,
)

# diagnostic_msgs/DiagnosticStatus levels.
OK = 0
WARN = 1
ERROR = 2
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR'}

COMMAND_TYPES = ('array', 'twist')
TWIST_FIELDS = tuple(f'{group}.{axis}' for group in ('linear', 'angular') for axis in 'xyz')

# Parameters of the node itself (not of the filter), with their defaults.
NODE_PARAMETER_DEFAULTS: dict[str, Any] = {
    'command_type': 'array',
    'twist_fields': ['linear.x', 'angular.z'],
    'max_state_age_s': 0.5,
    'slack_tolerance': 1.0e-4,
    'input_bounds.state': InputBounds.state,
    'input_bounds.command': InputBounds.command,
    'input_bounds.disturbance': InputBounds.disturbance,
    'log_throttle_s': 1.0,
    'qos.reliable': True,
    'qos.depth': 10,
    'osqp.eps_abs': OSQP_EPS,
    'osqp.eps_rel': OSQP_EPS,
    'osqp.max_iter': OSQP_MAX_ITER,
    'diagnostics.min_period_s': 0.0,
    'diagnostics.name': 'safety_filter',
    'diagnostics.hardware_id': '',
}

# Keys of rcbf_ros.core.config.filter_config_from_params with a fixed name. ``None``: not set
# (the config's own default applies); such values are dropped by :func:`collect_parameters`.
FILTER_PARAMETER_KEYS: tuple[str, ...] = (
    'system', 'input_limits.min', 'input_limits.max', 'alpha', 'k_c', 'slack_weight',
    'input_weight',
    'obstacles.x', 'obstacles.y', 'obstacles.radius', 'obstacles.margin', 'obstacles.lookahead',
    'obstacles.heading_index', 'obstacles.position_indices', 'obstacles.gammas',
    'obstacles.speed_input',
    'gaps.a', 'gaps.b', 'gaps.delta', 'gaps.gammas',
    'walls.nx', 'walls.ny', 'walls.offset', 'walls.gammas',
    'disturbance.mean', 'disturbance.std', 'fail_safe_action', 'compile_assembly',
)
# Families of keys whose names are chosen by the user (``bands.operator.index``, ...).
OPEN_PARAMETER_PREFIXES: tuple[str, ...] = ('system_params.', 'bands.')


def parameter_declarations(override_names: Sequence[str] = ()) -> list[tuple[str, Any]]:
    """Every (name, default) the node declares.

    The fixed filter keys default to ``None`` (not set); keys under the open prefixes
    (``system_params.*``, ``bands.<name>.*``) are declared when the parameter overrides (YAML,
    ``-p``) name them, so that a ``bands.operator.*`` block is read without listing it anywhere.

    Args:
        override_names: names of the parameter overrides the node was started with.
    """
    declared: dict[str, Any] = dict(NODE_PARAMETER_DEFAULTS)
    declared.update({key: None for key in FILTER_PARAMETER_KEYS})
    for name in sorted(override_names):
        if name.startswith(OPEN_PARAMETER_PREFIXES) and name not in declared:
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


@dataclass(frozen=True)
class NodeSettings:
    """Settings of the safety_filter node besides the filter itself."""

    command_type: str
    """'array' (Float64MultiArray with labelled sections) or 'twist' (geometry_msgs/Twist)."""
    twist_fields: tuple[str, ...]
    """For 'twist': the Twist fields holding u in order, e.g. (linear.x, angular.z)."""
    max_state_age_s: float
    """A state message older than this (since its arrival) is stale: fail-safe."""
    slack_tolerance: float
    """The most slack the published command may need in any RCBF row; more (the rows are
    infeasible within the input limits) publishes the fail-safe.

    An active but feasible row still carries eps ~ |u_S| / (l |L_g h|) > 0 (the soft penalty
    l eps^2 of the paper's QP), about 1e-6 with l = 1e6, hence the default 1e-4."""
    input_bounds: InputBounds
    """Magnitude bounds of state, proposal and disturbance box; beyond them: fail-safe."""
    log_throttle_s: float
    """Minimum period of repeated log lines with the same reason."""
    qos_reliable: bool
    """Reliable (True) or best-effort QoS on every topic."""
    qos_depth: int
    """Keep-last history depth on every topic."""
    osqp_eps_abs: float
    """OSQP absolute tolerance."""
    osqp_eps_rel: float
    """OSQP relative tolerance."""
    osqp_max_iter: int
    """OSQP iteration cap (a starved solve yields the fail-safe)."""
    diagnostics_min_period_s: float
    """Minimum period of OK diagnostics (0: one per proposal); WARN / ERROR always go out."""
    diagnostics_name: str
    """DiagnosticStatus.name."""
    diagnostics_hardware_id: str
    """DiagnosticStatus.hardware_id."""


def _positive(params: Mapping[str, Any], key: str, *, allow_zero: bool = False) -> float:
    out = number(params, key, NODE_PARAMETER_DEFAULTS[key])  # a finite number, not a bool
    if out < 0 or (out == 0 and not allow_zero):
        raise ValueError(f'{key}: must be a finite number {">=" if allow_zero else ">"} 0, '
                         f'got {params.get(key)!r}')
    return out


def _count(params: Mapping[str, Any], key: str) -> int:
    value = params.get(key, NODE_PARAMETER_DEFAULTS[key])
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f'{key}: expected an integer >= 1, got {value!r}')
    return int(value)


def node_settings_from_params(params: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (missing ones take their defaults).

    Raises:
        ValueError: naming the bad key.
    """
    command_type = params.get('command_type', NODE_PARAMETER_DEFAULTS['command_type'])
    if command_type not in COMMAND_TYPES:
        raise ValueError(f'command_type: expected one of {list(COMMAND_TYPES)}, '
                         f'got {command_type!r}')
    fields = params.get('twist_fields', NODE_PARAMETER_DEFAULTS['twist_fields'])
    if isinstance(fields, str) or not all(isinstance(f, str) for f in fields):
        raise ValueError(f'twist_fields: expected a list of names like linear.x, got {fields!r}')
    bad = [f for f in fields if f not in TWIST_FIELDS]
    if bad or not fields:
        raise ValueError(f'twist_fields: {bad or "empty"} not in {list(TWIST_FIELDS)}')
    if len(set(fields)) != len(fields):
        raise ValueError(f'twist_fields: repeated field in {list(fields)}')
    reliable = params.get('qos.reliable', NODE_PARAMETER_DEFAULTS['qos.reliable'])
    if not isinstance(reliable, bool):
        raise ValueError(f'qos.reliable: expected true or false, got {reliable!r}')
    texts = {}
    for key in ('diagnostics.name', 'diagnostics.hardware_id'):
        texts[key] = params.get(key, NODE_PARAMETER_DEFAULTS[key])
        if not isinstance(texts[key], str):
            raise ValueError(f'{key}: expected a string, got {texts[key]!r}')
    return NodeSettings(
        command_type=command_type, twist_fields=tuple(fields),
        max_state_age_s=_positive(params, 'max_state_age_s'),
        slack_tolerance=_positive(params, 'slack_tolerance', allow_zero=True),
        input_bounds=InputBounds(**{name: _positive(params, f'input_bounds.{name}')
                                    for name in ('state', 'command', 'disturbance')}),
        log_throttle_s=_positive(params, 'log_throttle_s', allow_zero=True),
        qos_reliable=reliable, qos_depth=_count(params, 'qos.depth'),
        osqp_eps_abs=_positive(params, 'osqp.eps_abs'),
        osqp_eps_rel=_positive(params, 'osqp.eps_rel'),
        osqp_max_iter=_count(params, 'osqp.max_iter'),
        diagnostics_min_period_s=_positive(params, 'diagnostics.min_period_s', allow_zero=True),
        diagnostics_name=texts['diagnostics.name'],
        diagnostics_hardware_id=texts['diagnostics.hardware_id'])


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
        slack_tolerance=settings.slack_tolerance, input_bounds=settings.input_bounds)


def checked_vector(name: str, values: Any, size: int) -> np.ndarray:
    """A finite float64 vector (a writable copy) of exactly ``size`` values.

    Raises:
        ValueError: naming ``name`` (wrong length, NaN/inf, not numeric).
    """
    try:
        array = np.array(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: not a numeric vector ({exc})') from exc
    if array.size != size:
        raise ValueError(f'{name}: expected {size} values, got {array.size}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name}: contains NaN or inf')
    return array


def state_from_sections(*, sections: Mapping[str, np.ndarray], n_x: int) -> np.ndarray:
    """The ``state`` section of a state message, else its first section, validated.

    Raises:
        ValueError: naming ``state`` (empty message, wrong length, NaN/inf).
    """
    if not sections:
        raise ValueError('state: empty message')
    values = sections['state'] if 'state' in sections else next(iter(sections.values()))
    return checked_vector('state', values, n_x)


@dataclass(frozen=True)
class Proposal:
    """A validated proposed command and what rides on it (float64 arrays)."""

    u: np.ndarray
    """(n_u,) proposed command u_RL."""
    disturbance_mean: np.ndarray | None = None
    """(n_x,) learned disturbance mean for the proposal's state, or None."""
    disturbance_std: np.ndarray | None = None
    """(n_x,) learned disturbance std (>= 0), or None."""
    state: np.ndarray | None = None
    """(n_x,) the state the proposal was made for, or None (use the state topic)."""


PROPOSAL_SECTIONS = ('u', 'disturbance_mean', 'disturbance_std', 'state')


def proposal_from_sections(*, sections: Mapping[str, np.ndarray], n_u: int,
                           n_x: int) -> Proposal:
    """Validate the sections of a proposal message (``u`` required; unlabelled data is ``u``).

    Raises:
        ValueError: naming the section (missing ``u``, unknown label, wrong length, NaN/inf,
            negative std).
    """
    unknown = sorted(set(sections) - set(PROPOSAL_SECTIONS))
    if unknown:
        raise ValueError(f'{unknown[0]}: unknown proposal section (expected '
                         f'{list(PROPOSAL_SECTIONS)})')
    if 'u' not in sections:
        raise ValueError('u: proposal has no u section')
    u = checked_vector('u', sections['u'], n_u)
    extra = {key: checked_vector(key, sections[key], n_x)
             for key in PROPOSAL_SECTIONS[1:] if key in sections}
    std = extra.get('disturbance_std')
    if std is not None and np.any(std < 0):
        raise ValueError('disturbance_std: must be >= 0')
    return Proposal(u=u, disturbance_mean=extra.get('disturbance_mean'),
                    disturbance_std=std, state=extra.get('state'))


@dataclass(frozen=True)
class StateSample:
    """The latest state message as the node saw it."""

    received_ns: int
    """Monotonic arrival time in nanoseconds."""
    state: np.ndarray | None
    """(n_x,) validated state, or None when the message was bad."""
    error: str = ''
    """Why the message was rejected (empty when ``state`` is set)."""


def state_age_s(*, sample: StateSample, now_ns: int) -> float:
    """Seconds since the sample arrived."""
    return (now_ns - sample.received_ns) * 1e-9


@dataclass(frozen=True)
class Decision:
    """What the node publishes for one proposal."""

    u_safe: np.ndarray
    """(n_u,) the command to publish: the filtered proposal or the fail-safe action."""
    u_rl: np.ndarray
    """(n_u,) the proposal (NaN where it was unusable)."""
    level: int
    """OK, WARN or ERROR."""
    reason: str
    """Human-readable reason for the level ('' when OK)."""
    fail_safe: bool
    """True when u_safe is the fail-safe action."""
    result: FilterResult | None = None
    """The filter's result when the QP was solved (even if it failed), else None."""
    state_source: str = ''
    """'proposal', 'topic' or '' (no usable state)."""

    @property
    def u_s(self) -> np.ndarray:
        """(n_u,) u_safe - u_rl (NaN where the proposal was unusable)."""
        return self.u_safe - self.u_rl

    def command_sections(self, answered_state: np.ndarray | None = None
                         ) -> dict[str, np.ndarray]:
        """The sections of the ``cmd_safe`` array: ``u``, ``u_rl``, ``u_s``, and the state a
        proposal carried, echoed so that a lock-step simulator can drop a late answer to an
        earlier state instead of applying it to the next one."""
        sections = {'u': self.u_safe, 'u_rl': self.u_rl, 'u_s': self.u_s}
        if answered_state is not None:
            sections['state'] = answered_state
        return sections


def fail_safe_decision(*, safety_filter: SafetyFilter, reason: str,
                       u_rl: np.ndarray | None = None) -> Decision:
    """The fail-safe command with an ERROR and its reason."""
    n_u = safety_filter.n_u
    proposal = np.full(n_u, np.nan) if u_rl is None else np.asarray(u_rl, dtype=np.float64)
    return Decision(u_safe=safety_filter.fail_safe_action.copy(), u_rl=proposal, level=ERROR,
                    reason=reason, fail_safe=True)


def _disturbance(learned: np.ndarray | None, static: Sequence[float]) -> np.ndarray | None:
    if learned is not None:
        return learned
    return np.asarray(static, dtype=np.float64) if len(static) else None


def decide(*, safety_filter: SafetyFilter, proposal: Proposal | None, proposal_error: str = '',
           latest_state: StateSample | None, now_ns: int, max_state_age_s: float,
           static_mean: Sequence[float] = (), static_std: Sequence[float] = (),
           slack_tolerance: float = 1e-4) -> Decision:
    """Filter one proposal, or decide the fail-safe.

    State: the proposal's own ``state`` section when it has one (the proposer's state: no
    staleness check), else ``latest_state`` from the state topic, which must exist, be valid
    and be at most ``max_state_age_s`` old (measured from its arrival).
    Disturbance box: the proposal's learned mean / std when present, else the static ones from
    the parameters (each independently; empty: none).

    Args:
        proposal: the validated proposal, or None when it was rejected.
        proposal_error: why the proposal was rejected (used when ``proposal`` is None).
        latest_state: the latest state message, or None when none arrived yet.
        now_ns: monotonic time of the proposal's arrival in nanoseconds.

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
    mean = _disturbance(proposal.disturbance_mean, static_mean)
    std = _disturbance(proposal.disturbance_std, static_std)
    try:
        result = safety_filter.filter(state, proposal.u, mean, std)
    except ValueError as exc:  # validated above; kept so that no path skips the fail-safe
        return fail_safe_decision(safety_filter=safety_filter, u_rl=proposal.u,
                                  reason=f'bad input: {exc}')
    if result.fail_safe:
        return Decision(u_safe=result.u_safe, u_rl=proposal.u, level=ERROR,
                        reason=f'{result.status}: {result.reason}', fail_safe=True,
                        result=result, state_source=source)
    if not result.needed_slack <= slack_tolerance:  # NaN too
        return Decision(u_safe=safety_filter.fail_safe_action.copy(), u_rl=proposal.u,
                        level=ERROR, fail_safe=True, result=result, state_source=source,
                        reason=f'slack_exceeded: barrier rows need slack '
                               f'{result.needed_slack:.3g} > slack_tolerance '
                               f'{slack_tolerance:.3g}')
    return Decision(u_safe=result.u_safe, u_rl=proposal.u, level=OK, reason='',
                    fail_safe=False, result=result, state_source=source)


def diagnostic_values(*, decision: Decision,
                      barrier_names: Sequence[str]) -> tuple[int, str, dict[str, Any]]:
    """(level, message, key/values) of the DiagnosticStatus for one decision.

    Keys: ``status`` (solver status or 'not solved'), ``slack``, ``h.<barrier>`` and
    ``constraint.<barrier>`` for every barrier (NaN when not solved), ``min_h``,
    ``solve_time_s``, ``total_time_s``, ``needed_slack`` (what the rows need at the published
    command), ``proposal_clipped``, ``fail_safe``, ``active``, ``reason``,
    ``state_source``, ``u_rl``, ``u_safe``.
    """
    result = decision.result
    nan = float('nan')
    values: dict[str, Any] = {
        'status': result.status if result is not None else 'not solved',
        'slack': result.slack if result is not None else nan,
    }
    h = result.h if result is not None else np.full(len(barrier_names), np.nan)
    residual = (result.constraint_values if result is not None
                else np.full(len(barrier_names), np.nan))
    for name, value in zip(barrier_names, h):
        values[f'h.{name}'] = float(value)
    for name, value in zip(barrier_names, residual):
        values[f'constraint.{name}'] = float(value)
    values['min_h'] = float(np.min(h)) if len(h) else nan
    values['solve_time_s'] = result.solve_time_s if result is not None else nan
    values['total_time_s'] = result.total_time_s if result is not None else nan
    values['needed_slack'] = result.needed_slack if result is not None else nan
    values['proposal_clipped'] = bool(result is not None and result.proposal_clipped)
    values['fail_safe'] = decision.fail_safe
    values['active'] = bool(decision.fail_safe or np.any(decision.u_safe != decision.u_rl))
    values['reason'] = decision.reason
    values['state_source'] = decision.state_source
    values['u_rl'] = ' '.join(repr(float(v)) for v in decision.u_rl)
    values['u_safe'] = ' '.join(repr(float(v)) for v in decision.u_safe)
    if decision.level == OK:
        message = 'filtering' if values['active'] else 'pass-through'
    else:
        message = decision.reason
    return decision.level, message, values


def diagnostics_due(*, level: int, now_ns: int, last_ok_ns: int | None,
                    min_period_s: float) -> bool:
    """Whether to publish the diagnostics of a decision now.

    WARN and ERROR always; OK at most once per ``min_period_s`` (0: always), so that a 1 kHz
    loop need not pay for a DiagnosticArray per command.

    Args:
        last_ok_ns: when OK diagnostics were last published (None: never).
    """
    if level != OK or min_period_s <= 0 or last_ok_ns is None:
        return True
    return now_ns - last_ok_ns >= int(min_period_s * 1e9)


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


def reason_key(reason: str) -> str:
    """The throttling key of a reason: its text up to the first ':'."""
    return reason.split(':', 1)[0]

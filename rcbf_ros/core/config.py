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
    compile_assembly: bool (compile the per-step autograd assembly of a system or barrier
        without a closed form; see core/filter.py)
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping

from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    cascade,
    CircleObstacles,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.dynamics import ControlAffineSystem, load_system
from rcbf_ros.core.mappings import flatten
from rcbf_ros.core.rcbf import RCBFProblem


def float_list(params: Mapping[str, Any], key: str, length: int | None = None, *,
               default: Any = ()) -> tuple[float, ...]:
    """params[key] as floats (a scalar counts as one); errors name ``key``. An empty list is
    accepted whatever ``length`` (meaning: not set)."""
    value = params.get(key, default)
    if value is None:
        return ()
    if isinstance(value, (int, float)):
        value = [value]
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{key}: expected a list of numbers, got {value!r}') from exc
    if any(not math.isfinite(v) for v in out):
        raise ValueError(f'{key}: contains NaN or inf')
    if length is not None and out and len(out) != length:
        raise ValueError(f'{key}: expected {length} values, got {len(out)}')
    return out


def number(params: Mapping[str, Any], key: str, default: float, *,
           positive: bool = False) -> float:
    """params[key] (or ``default``) as a finite float, > 0 if ``positive``; errors name ``key``.

    A numeric string is taken (YAML 1.1 reads ``1.0e6`` as a string); a bool is not a number.
    """
    value = params.get(key, default)
    if isinstance(value, bool):
        raise ValueError(f'{key}: expected a number, got {value!r}')
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{key}: expected a number, got {value!r}') from exc
    if not math.isfinite(out):
        raise ValueError(f'{key}: must be finite, got {out}')
    if positive and out <= 0:
        raise ValueError(f'{key}: must be > 0, got {out}')
    return out


def flag(params: Mapping[str, Any], key: str, default: bool = False) -> bool:
    """params[key] (or ``default``) as a bool; anything else (1, 'true') is refused naming
    ``key``, as rcl types a YAML bool and nothing else as a bool parameter."""
    value = params.get(key, default)
    if not isinstance(value, bool):
        raise ValueError(f'{key}: expected true or false, got {value!r}')
    return value


def _index(params: Mapping[str, Any], key: str, default: int, size: int,
           allow_none: bool = False, kind: str = 'state') -> int | None:
    """An index into the state (``kind`` 'state', size n_x) or the input ('input', n_u)."""
    value = params.get(key, default)
    # int() would take True as 1 and truncate 1.5 to 1: a typo must not pick another index.
    # (Non-finite floats fail is_integer() here too.)
    if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
        raise ValueError(f'{key}: expected an integer, got {value!r}')
    try:
        out = int(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{key}: expected an integer, got {value!r}') from exc
    if allow_none and out < 0:
        return None
    if not 0 <= out < size:
        name = 'n_x' if kind == 'state' else 'n_u'
        raise ValueError(f'{key}: {kind} index {out} out of range for {name} = {size}')
    return out


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


def build_system(params: Mapping[str, Any]) -> ControlAffineSystem:
    """The system named by ``system`` with ``system_params.*`` and ``input_limits.*``."""
    name = params.get('system')
    if not isinstance(name, str) or not name:
        raise ValueError('system: required (unicycle, car_following, pvtol or a dotted path)')
    sys_params = {k[len('system_params.'):]: v for k, v in params.items()
                  if k.startswith('system_params.')}
    if 'input_limits.min' in params or 'input_limits.max' in params:
        lo = float_list(params, 'input_limits.min')
        hi = float_list(params, 'input_limits.max')
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


def build_families(params: Mapping[str, Any],
                   system: ControlAffineSystem) -> tuple[BarrierFamily, ...]:
    """Barrier families (cascaded as configured) from the flat parameters."""
    n_x = system.n_x
    families: list[BarrierFamily] = []
    xs = float_list(params, 'obstacles.x')
    if xs:
        ys = float_list(params, 'obstacles.y', len(xs))
        radius = float_list(params, 'obstacles.radius', len(xs))
        if len(ys) != len(xs) or len(radius) != len(xs):
            raise ValueError('obstacles.y/obstacles.radius: need one value per obstacles.x')
        if any(r < 0 for r in radius):
            raise ValueError(f'obstacles.radius: every radius must be >= 0, got {list(radius)}')
        margin = number(params, 'obstacles.margin', 0.0)
        if margin < 0:
            raise ValueError(f'obstacles.margin: must be >= 0 (it widens every obstacle), '
                             f'got {margin}')
        if min(radius) + margin <= 0:
            raise ValueError('obstacles.radius: radius + obstacles.margin must be > 0 for every '
                             'obstacle')
        lookahead = number(params, 'obstacles.lookahead', 0.0)
        if lookahead < 0:
            raise ValueError(f'obstacles.lookahead: must be >= 0, got {lookahead}')
        pos = params.get('obstacles.position_indices', [0, 1])
        if len(pos) != 2:
            raise ValueError('obstacles.position_indices: expected 2 indices')
        key = 'obstacles.position_indices'
        pos_idx = (_index({key: pos[0]}, key, 0, n_x), _index({key: pos[1]}, key, 1, n_x))
        base = CircleObstacles(
            centers=tuple(zip(xs, ys)), radii=radius,
            margin=margin,
            position_indices=pos_idx,  # type: ignore[arg-type]
            heading_index=_index(params, 'obstacles.heading_index', -1, n_x, allow_none=True),
            lookahead=lookahead,
            speed_input=_index(params, 'obstacles.speed_input', -1, system.n_u,
                               allow_none=True, kind='input'))
        gammas = float_list(params, 'obstacles.gammas')
        if base.speed_input is not None and gammas:
            raise ValueError('obstacles.speed_input: the look-ahead point follows the direction '
                             'of travel only at relative degree 1 (no obstacles.gammas)')
        families.append(_cascade(base, system, gammas, 'obstacles.gammas'))
    band_names = sorted({k.split('.')[1] for k in params
                         if k.startswith('bands.') and k.count('.') == 2})
    for band in band_names:
        key = f'bands.{band}.'
        sub = {k[len(key):]: v for k, v in params.items() if k.startswith(key)}
        try:
            base = BandBarrier(
                index=_index(sub, 'index', 0, n_x),  # type: ignore[arg-type]
                half_width=number(sub, 'half_width', 0.0),
                center=number(sub, 'center', 0.0),
                center_index=_index(sub, 'center_index', -1, n_x, allow_none=True),
                name=band, form=str(sub.get('form', 'quadratic')))
            families.append(cascade(base, system, float_list(sub, 'gammas')))
        except ValueError as exc:
            raise ValueError(f'{key}{exc}') from exc
    gap_a = params.get('gaps.a') or []
    if gap_a:
        gap_b = params.get('gaps.b') or []
        if len(gap_b) != len(gap_a):
            raise ValueError('gaps.b: need one index per gaps.a')
        pairs = tuple((_index({'gaps.a': a}, 'gaps.a', 0, n_x),
                       _index({'gaps.b': b}, 'gaps.b', 0, n_x)) for a, b in zip(gap_a, gap_b))
        delta = number(params, 'gaps.delta', 0.0)
        if delta < 0:
            raise ValueError(f'gaps.delta: must be >= 0, got {delta}')
        base = PairGap(pairs=pairs, delta=delta)  # type: ignore
        families.append(_cascade(base, system, float_list(params, 'gaps.gammas'),
                                 'gaps.gammas'))
    nxs = float_list(params, 'walls.nx')
    if nxs:
        nys = float_list(params, 'walls.ny', len(nxs))
        offsets = float_list(params, 'walls.offset', len(nxs))
        if any(a == 0.0 and b == 0.0 for a, b in zip(nxs, nys)):
            raise ValueError('walls.nx/walls.ny: every wall needs a non-zero normal')
        base = HalfPlane(normals=tuple(zip(nxs, nys)), offsets=offsets)
        families.append(_cascade(base, system, float_list(params, 'walls.gammas'),
                                 'walls.gammas'))
    if not families:
        raise ValueError('barriers: configure at least one of obstacles.*, bands.*, gaps.*, '
                         'walls.*')
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
    """Validate flat (or nested) parameters into a :class:`FilterConfig`."""
    params = flatten(params)
    system = build_system(params)
    k_c = number(params, 'k_c', 2.0)
    if k_c < 0:
        raise ValueError(f'k_c: must be >= 0 (the box is mean +/- k_c std), got {k_c}')
    problem = RCBFProblem(
        system=system, families=build_families(params, system),
        alpha=number(params, 'alpha', 1.0, positive=True), k_c=k_c,
        slack_weight=number(params, 'slack_weight', 1.0e6, positive=True),
        input_weight=float_list(params, 'input_weight', system.n_u) or None)
    mean = float_list(params, 'disturbance.mean', system.n_x)
    std = float_list(params, 'disturbance.std', system.n_x)
    if any(s < 0 for s in std):
        raise ValueError('disturbance.std: must be >= 0')
    fail_safe = float_list(params, 'fail_safe_action', system.n_u) or None
    if fail_safe is not None and system.u_min is not None and any(
            not lo <= a <= hi for a, lo, hi in zip(fail_safe, system.u_min, system.u_max)):
        raise ValueError(f'fail_safe_action: {list(fail_safe)} lies outside the input limits '
                         f'[{list(system.u_min)}, {list(system.u_max)}]')
    compile_flag = params.get('compile_assembly', False)
    if not isinstance(compile_flag, bool):
        raise ValueError(f'compile_assembly: expected true or false, got {compile_flag!r}')
    return FilterConfig(problem=problem, static_mean=mean, static_std=std,
                        fail_safe_action=fail_safe, compile_assembly=compile_flag)

"""Control-affine dynamics x_dot = f(x) + g(x) u (the nominal prior of the paper, eq. main_system).

The disturbance d(x) of the paper is NOT part of these models: it is what the GP learns and what
the simulators add as the unknown "truth" (see ``rcbf_ros.envs``). Every system is batched in
torch: ``f(x): (B, n_x) -> (B, n_x)`` and ``g(x): (B, n_x) -> (B, n_x, n_u)``; the same code runs
at B = 1 for the per-step filter and at B = minibatch for the differentiable layer.

A user's own system plugs in by implementing :class:`ControlAffineSystem` (``n_x``, ``n_u``,
``u_min``, ``u_max``, ``f``, ``g``) and naming it in YAML by dotted path (:func:`load_system`).
A system of the table (:mod:`rcbf_ros.messages.systems`) is built from the
:class:`NamedDynamics` that declares its name.

The built-in systems also give f, its Jacobian and g at one state as Python source on floats
(:meth:`Unicycle.closed_form_source` and the same on the others, returning a
:class:`DriftSource`): the per-step filter's closed-form constraint assembly
(:mod:`rcbf_ros.core.lie_closed_form`) inlines it into the code it generates; the tests check
it, through :meth:`DriftSource.function`, against autograd through ``f`` and ``g``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import (
    Any,
    Callable,
    ClassVar,
    Mapping,
    NamedTuple,
    Protocol,
    runtime_checkable,
    TYPE_CHECKING,
    Union,
)

import numpy as np

from rcbf_ros.core.torch_import import import_error_line, LazyTorch
from rcbf_ros.messages import systems

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


@runtime_checkable
class ControlAffineSystem(Protocol):
    """The small protocol every system implements.

    Attributes:
        n_x: state dimension n.
        n_u: input dimension m.
        u_min: lower actuator limits, length m (``None``: unbounded).
        u_max: upper actuator limits, length m (``None``: unbounded).

    Optional: ``heading_indices``, the state entries that are headings (angles, rad); where a
    system declares it, a barrier's heading index is checked against it
    (:func:`heading_indices`).
    """

    n_x: int
    n_u: int
    u_min: tuple[float, ...] | None
    u_max: tuple[float, ...] | None

    def f(self, x: Tensor) -> Tensor:
        """Drift f(x). x: (B, n_x) -> (B, n_x)."""

    def g(self, x: Tensor) -> Tensor:
        """Input matrix g(x). x: (B, n_x) -> (B, n_x, n_u)."""


class DriftJet(NamedTuple):
    """The drift, its Jacobian and the input matrix at one state (numpy float64)."""

    f: np.ndarray
    """(n_x,) f(x)."""
    jacobian: np.ndarray
    """(n_x, n_x) J_ij = d f_i / d x_j."""
    g: np.ndarray
    """(n_x, n_u) g(x)."""


DriftJetFunction = Callable[[np.ndarray], DriftJet]
"""x: (n_x,) float64 (or a list of Python floats) -> :class:`DriftJet` at x."""

Entry = Union[float, str]
"""An entry of a :class:`DriftSource`: a constant, or the name of a variable its lines assign."""

SOURCE_NAMESPACE: dict[str, Any] = {'cos': math.cos, 'sin': math.sin, 'inf': math.inf,
                                    'nan': math.nan}
"""The functions the generated source may call besides the builtins, and the names ``repr``
gives the floats inf and nan (a constant of an absurd config can overflow)."""


def state_names(n_x: int) -> list[str]:
    """The names the source gives the state entries: x0, x1, ..."""
    return [f'x{i}' for i in range(n_x)]


class DriftSource(NamedTuple):
    """f, its Jacobian J and g at one state as Python source on floats.

    ``lines`` are statements (``if`` blocks allowed, indented by four spaces) that read the
    state entries as ``x0``, ``x1``, ... (Python floats, finite), may call ``cos`` and
    ``sin`` (:data:`SOURCE_NAMESPACE`) and assign every variable an entry names; those
    variables start with ``d_`` (the code generated around the lines uses no such name).
    ``jacobian`` and ``g`` leave out their structural zeros and f holds 0.0 for its own:
    :mod:`rcbf_ros.core.lie_closed_form` folds every constant into the code it generates, so
    that a zero costs nothing.

    The closed form of the cascades needs J not to change along f: sum_k f_k dJ/dx_k = 0, which
    holds for the three built-in systems (see each ``closed_form_source``; tested against
    autograd)."""

    lines: tuple[str, ...]
    """Statements computing the named entries from x0, x1, ..."""
    f: tuple[Entry, ...]
    """n_x entries of f(x)."""
    jacobian: Mapping[tuple[int, int], Entry]
    """(i, j) -> J_ij = d f_i / d x_j, the nonzero entries."""
    g: Mapping[tuple[int, int], Entry]
    """(i, j) -> g_ij(x), the nonzero entries."""
    n_u: int
    """Columns of g."""

    def function(self) -> DriftJetFunction:
        """The source compiled into one function of a state (numpy in and out), as the
        generated code evaluates it (what the tests compare with autograd)."""
        n_x = len(self.f)

        def table(entries: Mapping[tuple[int, int], Entry], columns: int) -> str:
            rows = [['0.0'] * columns for _ in range(n_x)]
            for (i, j), entry in entries.items():
                rows[i][j] = entry if isinstance(entry, str) else repr(float(entry))
            return '[' + ', '.join('[' + ', '.join(row) + ']' for row in rows) + ']'

        f = ', '.join(e if isinstance(e, str) else repr(float(e)) for e in self.f)
        source = '\n'.join([
            'def jet(values):',
            f'    {", ".join(state_names(n_x))}, = values',
            *(f'    {line}' for line in self.lines),
            f'    return [{f}], {table(self.jacobian, n_x)}, {table(self.g, self.n_u)}'])
        namespace = dict(SOURCE_NAMESPACE)
        exec(compile(source, '<drift source>', 'exec'), namespace)  # noqa: S102 - own source
        evaluate = namespace['jet']

        def jet(x: np.ndarray | list[float]) -> DriftJet:
            # a list is taken as Python floats (the filter's state), as tolist() gives them
            values = x if type(x) is list else np.asarray(x, dtype=np.float64).tolist()
            f_values, jacobian, g = evaluate(values)
            return DriftJet(np.array(f_values), np.array(jacobian).reshape(n_x, n_x),
                            np.array(g).reshape(n_x, self.n_u))

        return jet


def heading_indices(system: ControlAffineSystem) -> tuple[int, ...] | None:
    """The state entries of ``system`` that are headings, or None where it does not say."""
    indices = getattr(system, 'heading_indices', None)
    return None if indices is None else tuple(int(i) for i in indices)


def nominal_derivative(system: ControlAffineSystem, x: Tensor, u: Tensor) -> Tensor:
    """x_dot = f(x) + g(x) u of the nominal model (no disturbance).

    Args:
        x: (B, n_x) states.
        u: (B, n_u) inputs.

    Returns:
        (B, n_x) state derivatives.
    """
    return system.f(x) + (system.g(x) @ u.unsqueeze(-1)).squeeze(-1)


def step_euler(system: ControlAffineSystem, x: Tensor, u: Tensor, dt: float,
               disturbance: Tensor | None = None) -> Tensor:
    """One explicit Euler step of x_dot = f + g u (+ d) (paper eq. discrete_dynamics):
    x + dt ((f(x) + g(x) u) + d), in that order of operations.

    Args:
        x: (B, n_x) states.
        u: (B, n_u) inputs.
        dt: step size in seconds.
        disturbance: optional (B, n_x) additive d(x).

    Returns:
        (B, n_x) next states.
    """
    x_dot = nominal_derivative(system, x, u)
    if disturbance is not None:
        x_dot = x_dot + disturbance
    return x + dt * x_dot


class NamedDynamics:
    """Base of the dynamics of a system of the table (:mod:`rcbf_ros.messages.systems`): a
    subclass that sets ``system_name`` itself joins that entry when it is defined, and
    :func:`load_system` builds it from the name."""

    system_name: ClassVar[str] = ''
    """The table name this class is the dynamics of ('' or unset: none)."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        systems.join(cls, 'dynamics')


@dataclass(frozen=True)
class Unicycle(NamedDynamics):
    """Unicycle [x, y, theta] with input [v, omega] (paper, "Unicycle Environment").

    x_dot = g(x) u with g = [[cos th, 0], [sin th, 0], [0, 1]] and f = 0.
    """

    u_min: tuple[float, ...] | None = (-2.5, -2.5)
    """Lower input limits [v, omega] used by the safety QP (ref: |u| <= 2.5)."""
    u_max: tuple[float, ...] | None = (2.5, 2.5)
    """Upper input limits [v, omega]."""
    n_x: int = field(default=3, init=False)
    """State dimension: [x, y, theta]."""
    n_u: int = field(default=2, init=False)
    """Input dimension: [v, omega]."""
    heading_indices: ClassVar[tuple[int, ...]] = (2,)
    """State entries that are headings (angles in rad): theta."""
    system_name: ClassVar[str] = 'unicycle'

    def f(self, x: Tensor) -> Tensor:
        """Zero drift. x: (B, 3) -> (B, 3)."""
        return torch.zeros_like(x)

    def g(self, x: Tensor) -> Tensor:
        """x: (B, 3) -> (B, 3, 2)."""
        theta = x[:, 2]
        zeros, ones = torch.zeros_like(theta), torch.ones_like(theta)
        return torch.stack([
            torch.stack([torch.cos(theta), zeros], dim=-1),
            torch.stack([torch.sin(theta), zeros], dim=-1),
            torch.stack([zeros, ones], dim=-1),
        ], dim=1)

    def drift_jacobian(self, x: Tensor) -> Tensor:
        """d f / d x = 0. x: (B, 3) -> (B, 3, 3)."""
        return x.new_zeros(x.shape[0], 3, 3)

    def closed_form_source(self) -> DriftSource:
        """f = 0, J = 0 (so J does not change along f) and g = [[cos th, 0], [sin th, 0],
        [0, 1]] at one state."""
        return DriftSource(lines=('d_cos = cos(x2)', 'd_sin = sin(x2)'), f=(0.0, 0.0, 0.0),
                           jacobian={}, g={(0, 0): 'd_cos', (1, 0): 'd_sin', (2, 1): 1.0},
                           n_u=2)


@dataclass(frozen=True)
class CarFollowing(NamedDynamics):
    """Chain of five double-integrator cars; the agent drives car 4 (paper, "Car Following").

    State [p1, v1, p2, v2, ..., p5, v5] (n_x = 10), input [u4] (acceleration of car 4).
    The prior f holds the *nominal* behaviour of the other cars as the paper states it (their
    input gain 1 + d_i with d_i = 0.1 unknown, so the prior uses gain 1): cars 2 and 3 track
    v_des and brake on the car ahead within ``brake_gap``; car 5 brakes on car 3 within
    ``rear_brake_gap``. Car 1's sinusoid u_1 = 10 sin(0.2 t) depends on time, which the state
    does not hold, so the prior sets it to 0 and leaves it to the learned disturbance; it does
    not enter the barriers' derivatives (h_3, h_5 involve cars 3, 4, 5 only).
    """

    v_des: float = 30.0
    """Desired velocity of the other cars [m/s]."""
    k_v: float = 4.0
    """Velocity-tracking gain (ref)."""
    k_b: float = 20.0
    """Braking gain (ref)."""
    brake_gap: float = 6.0
    """Cars 2 and 3 brake when closer than this to the car ahead [m]."""
    rear_brake_gap: float = 12.0
    """Car 5 brakes on car 3 when closer than this [m]."""
    u_min: tuple[float, ...] | None = None
    """Lower input limit for car 4 (None: unbounded, as in the paper)."""
    u_max: tuple[float, ...] | None = None
    """Upper input limit for car 4."""
    n_x: int = field(default=10, init=False)
    """State dimension: position and velocity of five cars."""
    n_u: int = field(default=1, init=False)
    """Input dimension: acceleration of car 4."""
    heading_indices: ClassVar[tuple[int, ...]] = ()
    """State entries that are headings: none (positions and speeds along one road)."""
    system_name: ClassVar[str] = 'car_following'

    def nominal_accelerations(self, x: Tensor) -> Tensor:
        """Nominal accelerations of cars 1..5 with car 1 and car 4 set to 0. (B, 10) -> (B, 5)."""
        p, v = x[:, 0::2], x[:, 1::2]
        track = self.k_v * (self.v_des - v)
        zeros = torch.zeros_like(p[:, 0])

        def braking(ahead: int, me: int, gap: float) -> Tensor:
            dp = p[:, ahead] - p[:, me]
            return torch.where(dp.abs() < gap, track[:, me] - self.k_b * dp, track[:, me])

        return torch.stack([
            zeros,
            braking(0, 1, self.brake_gap),
            braking(1, 2, self.brake_gap),
            zeros,
            braking(2, 4, self.rear_brake_gap),
        ], dim=-1)

    def f(self, x: Tensor) -> Tensor:
        """x: (B, 10) -> (B, 10): p_dot = v, v_dot = nominal acceleration."""
        v = x[:, 1::2]
        a = self.nominal_accelerations(x)
        return torch.stack([v, a], dim=-1).reshape(x.shape)

    def g(self, x: Tensor) -> Tensor:
        """x: (B, 10) -> (B, 10, 1): the input drives v_4 only."""
        out = torch.zeros(x.shape[0], 10, 1, dtype=x.dtype, device=x.device)
        out[:, 7, 0] = 1.0
        return out

    def drift_jacobian(self, x: Tensor) -> Tensor:
        """d f / d x, x: (B, 10) -> (B, 10, 10): p_dot = v, the speed tracking -k_v, and
        +/- k_b on the gap of each follower inside its braking gap (the branch :meth:`f`
        takes, as autograd sees it)."""
        out = x.new_zeros(x.shape[0], 10, 10)
        for car in range(5):
            out[:, 2 * car, 2 * car + 1] = 1.0
        for me, ahead, gap in ((1, 0, self.brake_gap), (2, 1, self.brake_gap),
                               (4, 2, self.rear_brake_gap)):
            out[:, 2 * me + 1, 2 * me + 1] = -self.k_v
            braking = ((x[:, 2 * ahead] - x[:, 2 * me]).abs() < gap).to(x.dtype) * self.k_b
            out[:, 2 * me + 1, 2 * ahead] = -braking
            out[:, 2 * me + 1, 2 * me] = braking
        return out

    def closed_form_source(self) -> DriftSource:
        """f, J and g at one state. f is affine wherever no braking switch sits exactly at the
        state, so J is piecewise constant (the branch :meth:`nominal_accelerations` takes, as
        autograd sees it: -k_b and k_b on the gap inside it, 0 outside) and does not change
        along f. The operations are those of :meth:`nominal_accelerations`, in its order."""
        lines: list[str] = []
        f: list[Entry] = [entry for car in range(5) for entry in (f'x{2 * car + 1}', 0.0)]
        jacobian: dict[tuple[int, int], Entry] = {(2 * car, 2 * car + 1): 1.0
                                                  for car in range(5)}
        v_des, k_v, k_b = (repr(float(v)) for v in (self.v_des, self.k_v, self.k_b))
        for me, ahead, gap in ((1, 0, self.brake_gap), (2, 1, self.brake_gap),
                               (4, 2, self.rear_brake_gap)):
            row = 2 * me + 1
            gap_name, track = f'd_gap{me}', f'd_track{me}'
            lines += [f'{gap_name} = x{2 * ahead} - x{2 * me}',
                      f'{track} = {k_v} * ({v_des} - x{row})',
                      f'if abs({gap_name}) < {float(gap)!r}:',
                      f'    d_f{row} = {track} - {k_b} * {gap_name}',
                      f'    d_j{row}_{2 * ahead} = -{k_b}',
                      f'    d_j{row}_{2 * me} = {k_b}',
                      'else:',
                      f'    d_f{row} = {track}',
                      f'    d_j{row}_{2 * ahead} = 0.0',
                      f'    d_j{row}_{2 * me} = 0.0']
            f[row] = f'd_f{row}'
            jacobian[row, row] = -float(self.k_v)
            jacobian[row, 2 * ahead] = f'd_j{row}_{2 * ahead}'
            jacobian[row, 2 * me] = f'd_j{row}_{2 * me}'
        return DriftSource(lines=tuple(lines), f=tuple(f), jacobian=jacobian, g={(7, 0): 1.0},
                           n_u=1)


@dataclass(frozen=True)
class PVTOL(NamedDynamics):
    """Modified planar VTOL of the paper, optionally with the safety operator as a state.

    State [x1, x2, v1, v2, theta, f] (+ [x_h] when ``with_operator``), input [omega, u_f]:
    x1_dot = v1, x2_dot = v2, v1_dot = -sin(theta) f, v2_dot = cos(theta) f - 1,
    theta_dot = omega, f_dot = u_f. The operator moves along x1 tracking the drone with a
    low-gain P controller, x_h_dot = k_h (x1 - x_h); it is part of the state so that the band
    barrier delta^2 - (x1 - x_h)^2 is a function of the state and cascades like any other.
    """

    with_operator: bool = True
    """Append the operator's position x_h as the 7th state."""
    operator_gain: float = 3.5
    """k_h of the operator's P controller [1/s] (ref: 0.07 per 0.02 s step)."""
    u_min: tuple[float, ...] | None = (-2.5, -2.5)
    """Lower limits of [omega, u_f] (ref: |u| <= 2.5)."""
    u_max: tuple[float, ...] | None = (2.5, 2.5)
    """Upper limits of [omega, u_f]."""
    n_u: int = field(default=2, init=False)
    """Input dimension: [omega, u_f]."""
    heading_indices: ClassVar[tuple[int, ...]] = (4,)
    """State entries that are headings (angles in rad): theta."""
    system_name: ClassVar[str] = 'pvtol'

    @property
    def n_x(self) -> int:
        """6, or 7 with the operator."""
        return 7 if self.with_operator else 6

    def f(self, x: Tensor) -> Tensor:
        """x: (B, n_x) -> (B, n_x)."""
        v1, v2, theta, thrust = x[:, 2], x[:, 3], x[:, 4], x[:, 5]
        zeros = torch.zeros_like(v1)
        cols = [v1, v2, -torch.sin(theta) * thrust, torch.cos(theta) * thrust - 1.0, zeros, zeros]
        if self.with_operator:
            cols.append(self.operator_gain * (x[:, 0] - x[:, 6]))
        return torch.stack(cols, dim=-1)

    def g(self, x: Tensor) -> Tensor:
        """x: (B, n_x) -> (B, n_x, 2): omega drives theta, u_f drives the thrust."""
        out = torch.zeros(x.shape[0], self.n_x, 2, dtype=x.dtype, device=x.device)
        out[:, 4, 0] = 1.0
        out[:, 5, 1] = 1.0
        return out

    def drift_jacobian(self, x: Tensor) -> Tensor:
        """d f / d x, x: (B, n_x) -> (B, n_x, n_x)."""
        theta, thrust = x[:, 4], x[:, 5]
        sin, cos = torch.sin(theta), torch.cos(theta)
        out = x.new_zeros(x.shape[0], self.n_x, self.n_x)
        out[:, 0, 2] = out[:, 1, 3] = 1.0
        out[:, 2, 4] = -cos * thrust
        out[:, 2, 5] = -sin
        out[:, 3, 4] = -sin * thrust
        out[:, 3, 5] = cos
        if self.with_operator:
            out[:, 6, 0] = self.operator_gain
            out[:, 6, 6] = -self.operator_gain
        return out

    def closed_form_source(self) -> DriftSource:
        """f, J and g at one state, with the operations of :meth:`f` in its order.

        J's only state-dependent entries, d(-sin th f, cos th f - 1)/d(th, f), depend on theta
        and the thrust, whose drift entries are 0: J does not change along f."""
        lines = ['d_sin = sin(x4)', 'd_cos = cos(x4)', 'd_f2 = -d_sin * x5',
                 'd_f3 = d_cos * x5 - 1.0', 'd_j2_4 = -d_cos * x5', 'd_j2_5 = -d_sin',
                 'd_j3_4 = -d_sin * x5']
        f: list[Entry] = ['x2', 'x3', 'd_f2', 'd_f3', 0.0, 0.0]
        jacobian: dict[tuple[int, int], Entry] = {
            (0, 2): 1.0, (1, 3): 1.0, (2, 4): 'd_j2_4', (2, 5): 'd_j2_5', (3, 4): 'd_j3_4',
            (3, 5): 'd_cos'}
        if self.with_operator:
            k_h = float(self.operator_gain)
            lines.append(f'd_f6 = {k_h!r} * (x0 - x6)')
            f.append('d_f6')
            jacobian[6, 0], jacobian[6, 6] = k_h, -k_h
        return DriftSource(lines=tuple(lines), f=tuple(f), jacobian=jacobian,
                           g={(4, 0): 1.0, (5, 1): 1.0}, n_u=2)


CLOSED_FORM_SYSTEMS: tuple[type, ...] = (Unicycle, CarFollowing, PVTOL)
"""Systems whose ``closed_form_source`` is exact, by exact type: a subclass may override f or g,
so it keeps the autograd path."""


def load_system(name: str, params: Mapping[str, Any] | None = None) -> ControlAffineSystem:
    """Build a system from a name of the table or a dotted path ``package.module.ClassName``.

    Args:
        name: a name of :mod:`rcbf_ros.messages.systems` (``unicycle``, ``car_following``,
            ``pvtol``) or a dotted path to a class (or factory) whose instances implement
            :class:`ControlAffineSystem`.
        params: keyword arguments for the constructor (e.g. from YAML).

    Raises:
        ValueError: naming ``system`` when the name cannot be resolved or the object does not
            implement the protocol.
    """
    params = dict(params or {})
    for key in ('u_min', 'u_max'):
        if params.get(key) is not None:
            params[key] = tuple(float(v) for v in params[key])
    if name in systems.system_names():
        factory = systems.lookup(name).part('dynamics')
    elif '.' in name:
        factory = systems.import_object(name, explain=import_error_line)
    else:
        raise ValueError(f'system: unknown system {name!r}; the table has '
                         f'{list(systems.system_names())} or give a dotted path')
    try:
        system = factory(**params)
    except TypeError as exc:
        raise ValueError(f'system_params: {exc}') from exc
    if not isinstance(system, ControlAffineSystem):
        raise ValueError(f'system: {name!r} does not implement ControlAffineSystem '
                         '(n_x, n_u, u_min, u_max, f, g)')
    return system

"""Control-affine dynamics x_dot = f(x) + g(x) u (the nominal prior of the paper, eq. main_system).

The disturbance d(x) of the paper is NOT part of these models: it is what the GP learns and what
the simulators add as the unknown "truth" (see ``rcbf_ros.envs``). Every system is batched in
torch: ``f(x): (B, n_x) -> (B, n_x)`` and ``g(x): (B, n_x) -> (B, n_x, n_u)``; the same code runs
at B = 1 for the per-step filter and at B = minibatch for the differentiable layer.

A user's own system plugs in by implementing :class:`ControlAffineSystem` (``n_x``, ``n_u``,
``u_min``, ``u_max``, ``f``, ``g``) and naming it in YAML by dotted path (:func:`load_system`).

The built-in systems also give f, its Jacobian and g in closed form for one state in numpy
(:meth:`Unicycle.closed_form_drift` and the same on the others, returning a :class:`DriftJet`):
the per-step filter's closed-form constraint assembly (:mod:`rcbf_ros.core.lie_closed_form`)
uses them; the tests check them against autograd through ``f`` and ``g``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import importlib
import math
from typing import Any, Callable, Mapping, NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor


@runtime_checkable
class ControlAffineSystem(Protocol):
    """The small protocol every system implements.

    Attributes:
        n_x: state dimension n.
        n_u: input dimension m.
        u_min: lower actuator limits, length m (``None``: unbounded).
        u_max: upper actuator limits, length m (``None``: unbounded).
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
    """The drift, its Jacobian and the input matrix at one state (numpy float64).

    Enough for cascades of depth <= 2 over barriers with a constant Hessian (see
    :mod:`rcbf_ros.core.lie_closed_form`) for drifts whose Jacobian does not change along f:
    sum_k f_k dJ/dx_k = 0, which holds for the three built-in systems (see each
    ``closed_form_drift``; tested against autograd)."""

    f: np.ndarray
    """(n_x,) f(x)."""
    jacobian: np.ndarray
    """(n_x, n_x) J_ij = d f_i / d x_j."""
    g: np.ndarray
    """(n_x, n_u) g(x)."""


DriftJetFunction = Callable[[np.ndarray], DriftJet]
"""x: (n_x,) float64 -> :class:`DriftJet` at x."""


def _constant(array: np.ndarray) -> np.ndarray:
    """``array``, read-only (shared between calls)."""
    array.setflags(write=False)
    return array


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


@dataclass(frozen=True)
class Unicycle:
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

    def closed_form_drift(self) -> DriftJetFunction:
        """f = 0, J = 0 (so J does not change along f) and g = [[cos th, 0], [sin th, 0],
        [0, 1]] at one state."""
        zero_f = _constant(np.zeros(3))
        zero_j = _constant(np.zeros((3, 3)))

        def jet(x: np.ndarray) -> DriftJet:
            theta = float(x[2])
            g = np.zeros((3, 2))
            g[0, 0] = math.cos(theta)
            g[1, 0] = math.sin(theta)
            g[2, 1] = 1.0
            return DriftJet(zero_f, zero_j, g)

        return jet


@dataclass(frozen=True)
class CarFollowing:
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

    def closed_form_drift(self) -> DriftJetFunction:
        """f, J and g at one state. f is affine wherever no braking switch sits exactly at the
        state, so J is piecewise constant (the branch :meth:`nominal_accelerations` takes, as
        autograd sees it) and does not change along f."""
        # (car, car ahead, braking gap) of every car with a nominal controller
        followers = ((1, 0, self.brake_gap), (2, 1, self.brake_gap),
                     (4, 2, self.rear_brake_gap))
        base = np.zeros((10, 10))
        for car in range(5):
            base[2 * car, 2 * car + 1] = 1.0  # p_dot = v
        for me, _, _ in followers:
            base[2 * me + 1, 2 * me + 1] = -self.k_v
        base = _constant(base)
        g = np.zeros((10, 1))
        g[7, 0] = 1.0
        g = _constant(g)
        v_des, k_v, k_b = self.v_des, self.k_v, self.k_b

        def jet(x: np.ndarray) -> DriftJet:
            values = x.tolist()
            p, v = values[0::2], values[1::2]
            f = [0.0] * 10
            f[0::2] = v
            jacobian = base.copy()
            for me, ahead, gap in followers:
                track = k_v * (v_des - v[me])
                dp = p[ahead] - p[me]
                if abs(dp) < gap:
                    f[2 * me + 1] = track - k_b * dp
                    jacobian[2 * me + 1, 2 * ahead] = -k_b
                    jacobian[2 * me + 1, 2 * me] = k_b
                else:
                    f[2 * me + 1] = track
            return DriftJet(np.array(f), jacobian, g)

        return jet


@dataclass(frozen=True)
class PVTOL:
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

    def closed_form_drift(self) -> DriftJetFunction:
        """f, J and g at one state.

        J's only state-dependent entries, d(-sin th f, cos th f - 1)/d(th, f), depend on theta
        and the thrust, whose drift entries are 0: J does not change along f."""
        n_x, k_h = self.n_x, self.operator_gain
        base = np.zeros((n_x, n_x))
        base[0, 2] = base[1, 3] = 1.0
        if self.with_operator:
            base[6, 0], base[6, 6] = k_h, -k_h
        base = _constant(base)
        g = np.zeros((n_x, 2))
        g[4, 0] = g[5, 1] = 1.0
        g = _constant(g)
        with_operator = self.with_operator

        def jet(x: np.ndarray) -> DriftJet:
            values = x.tolist()
            theta, thrust = values[4], values[5]
            sin, cos = math.sin(theta), math.cos(theta)
            f = [values[2], values[3], -sin * thrust, cos * thrust - 1.0, 0.0, 0.0]
            if with_operator:
                f.append(k_h * (values[0] - values[6]))
            jacobian = base.copy()
            jacobian[2, 4] = -cos * thrust
            jacobian[2, 5] = -sin
            jacobian[3, 4] = -sin * thrust
            jacobian[3, 5] = cos
            return DriftJet(np.array(f), jacobian, g)

        return jet


BUILTIN_SYSTEMS: dict[str, type] = {
    'unicycle': Unicycle,
    'car_following': CarFollowing,
    'pvtol': PVTOL,
}

CLOSED_FORM_SYSTEMS: tuple[type, ...] = (Unicycle, CarFollowing, PVTOL)
"""Systems whose ``closed_form_drift`` is exact, by exact type: a subclass may override f or g,
so it keeps the autograd path."""


def load_system(name: str, params: Mapping[str, Any] | None = None) -> ControlAffineSystem:
    """Build a system from a built-in name or a dotted path ``package.module.ClassName``.

    Args:
        name: ``unicycle``, ``car_following``, ``pvtol`` or a dotted path to a class (or
            factory) whose instances implement :class:`ControlAffineSystem`.
        params: keyword arguments for the constructor (e.g. from YAML).

    Raises:
        ValueError: naming ``system`` when the name cannot be resolved or the object does not
            implement the protocol.
    """
    params = dict(params or {})
    for key in ('u_min', 'u_max'):
        if params.get(key) is not None:
            params[key] = tuple(float(v) for v in params[key])
    if name in BUILTIN_SYSTEMS:
        factory = BUILTIN_SYSTEMS[name]
    elif '.' in name:
        module_name, _, attr = name.rpartition('.')
        try:
            factory = getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f'system: cannot import {name!r}: {exc}') from exc
    else:
        raise ValueError(f'system: unknown system {name!r}; built-ins are '
                         f'{sorted(BUILTIN_SYSTEMS)} or give a dotted path')
    try:
        system = factory(**params)
    except TypeError as exc:
        raise ValueError(f'system_params: {exc}') from exc
    if not isinstance(system, ControlAffineSystem):
        raise ValueError(f'system: {name!r} does not implement ControlAffineSystem '
                         '(n_x, n_u, u_min, u_max, f, g)')
    return system

"""Margins that make the RCBF rows hold between samples and under latency (sampled-data CBF).

A command computed from the state x_k sampled at t_k is applied from t_k + L (the latency) and
held for T (the control period); before t_k + L the previous command acts, whose own margin
covered [t_k - T, t_k + L]. Following Breeden, Garg and Panagou, "Control Barrier Functions in
Sampled-Data Systems", IEEE L-CSS 6, 2022, the row of barrier i is required at x_k with a
margin

    phi_i(x_k, u) >= nu_i,   nu_i >= sup_{x in R(x_k, tau)} |phi_i(x, u) - phi_i(x_k, u)|,

phi_i(x, u) = grad h_i(x)^T (f(x) + g(x) u) + rho_i(x) + alpha h_i(x) the row's left side (rho_i
the least of grad h_i^T psi over the disturbance box), R(x_k, tau) the states reachable within
tau = L + T under any input within the limits and any disturbance in the box. Then phi_i >= 0
along the whole interval, so h_i_dot >= -alpha h_i there while the true disturbance stays in the
box, and h_i >= 0 holds between samples, not only at them.

nu_i is bounded here in closed form, a guaranteed bound (no sampling), for the uncascaded
barrier families on the :class:`~rcbf_ros.core.dynamics.Unicycle` (f = 0, g = [[cos th, 0],
[sin th, 0], [0, 1]]), from per-entry bounds of the displacement |x(t) - x_k| <= tau r,
r = (V + w_0, V + w_1, W + w_2), V and W the largest |v| and |omega| within the limits and
w = |mean| + k_c std the box's reach per entry:

- :class:`~rcbf_ros.core.barriers.CircleObstacles` (the look-ahead point p = (x, y) +/- l_p e,
  e = (cos th, sin th), l_p = 0 included; each sensor point is one such row), with
  d = p - c, rho_k = |(x, y) - c| + l_p >= |d_k| for either point,
  E = min(tau r_2, 2) >= |e - e_k|, P = tau (V + |(w_0, w_1)|) + l_p E >= |p - p_k| and
  Q = P + (rho_k + P) E >= the change of d^T e and of d^T n (n = (-sin th, cos th)):

      nu = 2 (V + l_p W) Q + 2 P (w_0 + w_1) + 2 l_p Q w_2 + alpha (2 rho_k P + P^2);

- the quadratic families (:class:`~rcbf_ros.core.barriers.HalfPlane`,
  :class:`~rcbf_ros.core.barriers.BandBarrier`, :class:`~rcbf_ros.core.barriers.PairGap`),
  h = c + a^T x + 1/2 x^T H x, with D = tau r, G = (V, V, W) >= |g(x) u| and
  B = (V E, V E, 0) >= |(g(x) - g(x_k)) u|:

      nu = (|H| D)^T (G + w) + |grad h(x_k)|^T B + alpha (|grad h(x_k)|^T D + 1/2 D^T |H| D).

Anything else (another system, a cascaded family, a system without input limits) has no
derived bound: :func:`sampled_data_margin` refuses it in one line naming the key and the
system rather than filter with rows that hold at the samples only.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    CircleObstacles,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.dynamics import Unicycle
from rcbf_ros.core.rcbf import RCBFProblem

TIMING_LIMIT_S = 1.0
"""The longest control period and the largest latency (s) the filter takes: a command held or
late by more than a second is no 10-50 Hz controller's, and the margins grow with the square of
the horizon."""

_QUADRATIC = (HalfPlane, BandBarrier, PairGap)
"""Families whose margin comes from their quadratic coefficients."""


def _timing_key(control_period_s: float, latency_s: float) -> str:
    """The key a refusal names: the one that asks for the margin (the period where both do)."""
    return 'control_period_s' if control_period_s > 0.0 else 'latency_s'


def check_timing(control_period_s: float, latency_s: float) -> None:
    """Refuse a period or latency that is not a finite number in [0, :data:`TIMING_LIMIT_S`],
    in one line naming the key."""
    for key, value in (('control_period_s', control_period_s), ('latency_s', latency_s)):
        if isinstance(value, bool) or not (isinstance(value, (int, float))
                                           and 0.0 <= value <= TIMING_LIMIT_S):
            raise ValueError(f'{key}: must be a number in [0, {TIMING_LIMIT_S:g}] s, '
                             f'got {value!r}')


class SampledDataMargin:
    """The margins nu_i of one problem's rows (module docstring); build with
    :func:`sampled_data_margin`. ``rows(x, mean, std)`` gives the K problem rows' margins,
    ``points(x, mean, std, cx, cy)`` those of sensor points."""

    def __init__(self, problem: RCBFProblem, horizon: float, lookahead: float) -> None:
        system = problem.system
        low = np.asarray(system.u_min, dtype=np.float64)
        high = np.asarray(system.u_max, dtype=np.float64)
        reach = np.maximum(np.abs(low), np.abs(high))
        self.horizon = float(horizon)
        """tau = L + T (s)."""
        self._speed, self._turn = float(reach[0]), float(reach[1])
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self._point_lookahead = float(lookahead)
        self._parts: list[tuple[str, object]] = []
        for family in problem.families:
            if type(family) is CircleObstacles:
                centers = np.array(family.centers, dtype=np.float64).reshape(-1, 2)
                offset = float(family.lookahead) if family.has_lookahead else 0.0
                self._parts.append(('circles', (centers[:, 0], centers[:, 1], offset)))
            else:
                rows = family.quadratic_rows(system.n_x)  # type: ignore[attr-defined]
                self._parts.append(('quadratic', (rows.linear, rows.hessian,
                                                  np.abs(rows.hessian))))

    def _box(self, mean: Sequence[float], std: Sequence[float]) -> np.ndarray:
        """w = |mean| + k_c std per state entry."""
        return np.abs(np.asarray(mean, dtype=np.float64)) + self._k_c * np.asarray(
            std, dtype=np.float64)

    def _circles(self, x: Sequence[float], w: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                 lookahead: float) -> np.ndarray:
        """nu of circle rows around centres (cx, cy), the look-ahead l_p (module docstring)."""
        tau, speed, turn = self.horizon, self._speed, self._turn
        turned = min(tau * (turn + w[2]), 2.0)  # E >= |e - e_k|
        moved = tau * (speed + math.hypot(w[0], w[1])) + lookahead * turned  # P >= |p - p_k|
        rho = np.hypot(x[0] - cx, x[1] - cy) + lookahead  # >= |d_k| at either point
        change = moved + (rho + moved) * turned  # Q >= |d^T e - d_k^T e_k|, same with n
        return (2.0 * (speed + lookahead * turn + lookahead * w[2]) * change
                + 2.0 * moved * (w[0] + w[1])
                + self._alpha * (2.0 * rho * moved + moved * moved))

    def _quadratic(self, x: np.ndarray, w: np.ndarray, linear: np.ndarray, hessian: np.ndarray,
                   absolute: np.ndarray) -> np.ndarray:
        """nu of quadratic rows (module docstring)."""
        tau, speed, turn = self.horizon, self._speed, self._turn
        shift = tau * np.array([speed + w[0], speed + w[1], turn + w[2]])  # D
        turned = min(shift[2], 2.0)
        gain = np.array([speed, speed, turn])  # G >= |g(x) u|
        rotated = np.array([speed * turned, speed * turned, 0.0])  # B >= |(g(x) - g(x_k)) u|
        grad = np.abs(linear + hessian @ x)  # (k, n_x) |grad h(x_k)|
        spread = absolute @ shift  # (k, n_x) >= |grad h(x) - grad h(x_k)|
        return (spread @ (gain + w) + grad @ rotated
                + self._alpha * (grad @ shift + 0.5 * spread @ shift))

    def rows(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
             ) -> np.ndarray:
        """(K,) nu_i >= 0 of the problem's rows at the sampled state x and the box."""
        w = self._box(mean, std)
        state = np.asarray(x, dtype=np.float64)
        out = []
        for kind, data in self._parts:
            if kind == 'circles':
                cx, cy, lookahead = data  # type: ignore[misc]
                out.append(self._circles(x, w, cx, cy, lookahead))
            else:
                out.append(self._quadratic(state, w, *data))  # type: ignore[misc]
        return np.concatenate(out) if out else np.zeros(0)

    def points(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float],
               cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        """(N,) nu of the sensor points' circle rows, centres (cx, cy)."""
        return self._circles(x, self._box(mean, std), cx, cy, self._point_lookahead)


def sampled_data_margin(problem: RCBFProblem, *, control_period_s: float = 0.0,
                        latency_s: float = 0.0, footprint: BarrierFamily | None = None
                        ) -> SampledDataMargin | None:
    """The margins of ``problem``'s rows (and of sensor points around ``footprint``) for a
    command held ``control_period_s`` and applied ``latency_s`` after its state was sampled;
    None when both are 0 (the continuous-time rows, unchanged).

    Raises:
        ValueError: one line naming ``control_period_s`` or ``latency_s``: out of range, or a
            system, barrier family or missing input limits for which no bound is derived.
    """
    check_timing(control_period_s, latency_s)
    horizon = float(control_period_s) + float(latency_s)
    if horizon == 0.0:
        return None
    key = _timing_key(control_period_s, latency_s)
    system = problem.system
    name = getattr(system, 'system_name', '') or type(system).__name__
    if type(system) is not Unicycle:
        raise ValueError(f'{key}: no sampled-data margin is derived for the {name} system '
                         '(the unicycle only); set control_period_s and latency_s to 0')
    if not problem.has_limits:
        raise ValueError(f'{key}: the sampled-data margin needs input limits on the {name} '
                         'system (input_limits.min/max)')
    families = list(problem.families) + ([] if footprint is None else [footprint])
    for family in families:
        if type(family) is CircleObstacles:
            if tuple(family.position_indices) != (0, 1) or family.heading_index not in (None, 2):
                raise ValueError(f'{key}: the sampled-data margin of obstacles on the {name} '
                                 'system needs position_indices [0, 1] and heading_index 2')
        elif type(family) not in _QUADRATIC:
            raise ValueError(f'{key}: no sampled-data margin is derived for the '
                             f'{type(family).__name__} barriers on the {name} system (cascaded '
                             'or user-defined rows); set control_period_s and latency_s to 0')
    lookahead = 0.0
    if footprint is not None and footprint.has_lookahead:  # type: ignore[attr-defined]
        lookahead = float(footprint.lookahead)  # type: ignore[attr-defined]
    return SampledDataMargin(problem, horizon, lookahead)

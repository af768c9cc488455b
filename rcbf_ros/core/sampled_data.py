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

The margin follows the command: the change of phi_i is that of L_g h_i times u plus the rest,
so nu_i(u) = nu0_i + c_i^T |u|, c_i >= 0 (n_u,) bounding the change of L_g h_i per input
(``split_rows`` and ``split_points`` give (nu0, c)). The motion over the interval stays a
worst case over the whole input box (the previous command acts over [t_k, t_k + L], and the
state may move under any input): only the factor |u| of the row's own command is the
command's. The tightened row a_i + b_i^T u - nu0_i - c_i^T |u| >= 0 is concave in u, and as
c_i^T |u| = max_s (c_i * s)^T u over the sign vectors s in {-1, +1}^{n_u}, it is exactly the
linear rows (b_i - c_i * s)^T u >= nu0_i - a_i for every s (:func:`split_rows`, over the
inputs with c_ij > 0), whose least at u is the tightened row's value. The constant margin of
the largest input, nu0_i + c_i^T U >= nu0_i + c_i^T |u| for every u within the limits, is
``rows`` and ``points`` (``command_linear`` False: what ``split_*`` give, c = 0, for
comparison: benchmarks/bench_sampled_data.py, ``python benchmarks/bench_sampled_data.py
--no-write``).

nu0 and c are bounded here in closed form, a guaranteed bound (no sampling), for the
uncascaded barrier families on the :class:`~rcbf_ros.core.dynamics.Unicycle` (f = 0,
g = [[cos th, 0], [sin th, 0], [0, 1]]), from per-entry bounds of the displacement
|x(t) - x_k| <= tau r, r = (V + w_0, V + w_1, W + w_2), V and W the largest |v| and |omega|
within the limits and w = |mean| + k_c std the box's reach per entry:

- :class:`~rcbf_ros.core.barriers.CircleObstacles` (the look-ahead point p = (x, y) +/- l_p e,
  e = (cos th, sin th), l_p = 0 included; each sensor point is one such row), with
  d = p - c, rho_k = |(x, y) - c| + l_p >= |d_k| for either point,
  E = min(tau r_2, 2) >= |e - e_k|, P = tau (V + |(w_0, w_1)|) + l_p E >= |p - p_k| and
  Q = P + (rho_k + P) E >= the change of d^T e and of d^T n (n = (-sin th, cos th)), and
  L_g h = (2 d^T e, 2 l_p d^T n):

      c = (2 Q, 2 l_p Q),  nu0 = 2 P (w_0 + w_1) + 2 l_p Q w_2 + alpha (2 rho_k P + P^2);

- the quadratic families (:class:`~rcbf_ros.core.barriers.HalfPlane`,
  :class:`~rcbf_ros.core.barriers.BandBarrier`, :class:`~rcbf_ros.core.barriers.PairGap`),
  h = c + a^T x + 1/2 x^T H x, with D = tau r, |g(x) u| <= (|v|, |v|, |omega|) and
  |(g(x) - g(x_k)) u| <= (E |v|, E |v|, 0):

      c_v = (|H| D)_0 + (|H| D)_1 + E (|grad h(x_k)|_0 + |grad h(x_k)|_1),
      c_omega = (|H| D)_2,
      nu0 = (|H| D)^T w + alpha (|grad h(x_k)|^T D + 1/2 D^T |H| D).

Every other problem with a closed form (:mod:`rcbf_ros.core.lie_closed_form`: PVTOL with its
cascaded obstacles, bands and arena, a cascaded family on the Unicycle) gets
:class:`IntervalMargin`: the same Breeden et al. margin, bounded by interval arithmetic over an
a priori enclosure, as validated ODE solvers do. The enclosure is a box x_k +/- D with
tau sup |f(x) + g(x) u + psi| <= D over the box, every u within the limits and psi in the
disturbance box (f and g evaluated from the system's ``closed_form_source`` in ball arithmetic,
:mod:`rcbf_ros.core.ball`); then every state reachable within tau lies in it. Over that box the
filter's own generated code for h, grad h, L_f h and L_g h runs on jets (balls with their
gradients), and each change is bounded by the smaller of the values' enclosure and the mean
value bound sum_k sup|d/dx_k| D_k (the latter only where no comparison of the code is undecided
over the box: across a switch the values' hull over both branches holds, a gradient does not):

    nu0_i = sup|dL_f h_i| + sup|d grad h_i|^T (|mean| + k_c std) + alpha sup|d h_i|,
    c_i = sup|dL_g h_i| per input

(|d rho_i| <= |d grad h_i|^T (|mean| + k_c std), rho_i as
:func:`~rcbf_ros.core.qp.robust_margin` forms it). Where no enclosure closes the margin is
infinite and the filter answers with its fail-safe.

Car Following's cascaded gap rows have a closed-form bound (benchmarks/_car_following_bound.py:
the cars' speeds and gaps bounded from their relative motion, each braking switch's reach
decided per follower, its jump paid only where it can be reached; docs/SAFETY_FILTER.md, "Car
Following: the bound, and why it is refused"). No filter takes it: its margin of car 4's own
motion is a share (gamma + alpha) tau of the command's authority on a row (1.5 at T = L = 50
ms with the shipped gains), and at T = L >= 20 ms most decisions of the shipped scenario meet
no command, each then answered by the fail-safe 0, which coasts into the car ahead
(benchmarks/bench_sampled_data.py).

Refused, in one line naming the key and the system, rather than filter with rows that hold at
the samples only: a system without input limits; Car Following (above); sensor points on
another system than the Unicycle; a problem without a closed form (a system or family given by
dotted path, a cascaded look-ahead point).
"""
from __future__ import annotations

from dataclasses import replace
import functools
from itertools import product
import math
from typing import Callable, Sequence

import numpy as np

from rcbf_ros.core.ball import Ball, BALL_NAMESPACE, hull_over_branches, Jet, JET_NAMESPACE
from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    CircleObstacles,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.dynamics import CarFollowing, DriftSource, state_names, Unicycle
from rcbf_ros.core.lie_closed_form import ClosedFormTerms, has_closed_form
from rcbf_ros.core.rcbf import RCBFProblem

TIMING_LIMIT_S = 1.0
"""The longest control period and the largest latency (s) the filter takes: a command held or
late by more than a second is no 10-50 Hz controller's, and the margins grow with the square of
the horizon."""

_QUADRATIC = (HalfPlane, BandBarrier, PairGap)
"""Families whose margin comes from their quadratic coefficients."""

REFUSED_SYSTEMS: dict[type, str] = {
    CarFollowing: "its bound charges car 4's own motion a share (gamma + alpha) tau of the "
                  "command's authority and k_b times the gap where its braking switches can "
                  'be reached, and its fail-safe 0 coasts: at T = L >= 20 ms most decisions '
                  'of its scenario meet no command (docs/SAFETY_FILTER.md)'}
"""Built-in systems whose interval margin is refused, and why (module docstring)."""


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
    :func:`sampled_data_margin`. ``split_rows(x, mean, std)`` gives the K problem rows'
    margins as (nu0, c), nu_i(u) = nu0_i + c_i^T |u|, ``split_points(x, mean, std, cx, cy)``
    those of sensor points; ``rows`` and ``points`` the constant margins nu0 + c^T U at the
    largest input U (``command_linear`` False: ``split_*`` give those, c = 0)."""

    def __init__(self, problem: RCBFProblem, horizon: float, lookahead: float,
                 command_linear: bool = True) -> None:
        system = problem.system
        low = np.asarray(system.u_min, dtype=np.float64)
        high = np.asarray(system.u_max, dtype=np.float64)
        reach = np.maximum(np.abs(low), np.abs(high))
        self.horizon = float(horizon)
        """tau = L + T (s)."""
        self.command_linear = bool(command_linear)
        """Whether the margin follows the command (else the constant nu0 + c^T U, c = 0)."""
        self._reach = reach
        self._speed, self._turn = float(reach[0]), float(reach[1])
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self._point_lookahead = abs(float(lookahead))  # the bound takes |l_p|: either side
        self._parts: list[tuple[str, object]] = []
        for family in problem.families:
            if type(family) is CircleObstacles:
                centers = np.array(family.centers, dtype=np.float64).reshape(-1, 2)
                offset = abs(float(family.lookahead)) if family.has_lookahead else 0.0
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
                 lookahead: float) -> tuple[np.ndarray, np.ndarray]:
        """(nu0 (N,), c (N, 2)) of circle rows around centres (cx, cy), the look-ahead l_p
        (module docstring): c = (2 Q, 2 l_p Q), the change of L_g h times |v| and |omega|."""
        tau, speed, turn = self.horizon, self._speed, self._turn
        turned = min(tau * (turn + w[2]), 2.0)  # E >= |e - e_k|
        moved = tau * (speed + math.hypot(w[0], w[1])) + lookahead * turned  # P >= |p - p_k|
        rho = np.hypot(x[0] - cx, x[1] - cy) + lookahead  # >= |d_k| at either point
        change = moved + (rho + moved) * turned  # Q >= |d^T e - d_k^T e_k|, same with n
        rest = (2.0 * lookahead * w[2] * change + 2.0 * moved * (w[0] + w[1])
                + self._alpha * (2.0 * rho * moved + moved * moved))
        return rest, np.stack([2.0 * change, 2.0 * lookahead * change], axis=-1)

    def _quadratic(self, x: np.ndarray, w: np.ndarray, linear: np.ndarray, hessian: np.ndarray,
                   absolute: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nu0 (k,), c (k, 2)) of quadratic rows (module docstring): c_v = |H| D's first two
        entries plus |grad h(x_k)|'s times E, c_omega = |H| D's third."""
        tau, speed, turn = self.horizon, self._speed, self._turn
        shift = tau * np.array([speed + w[0], speed + w[1], turn + w[2]])  # D
        turned = min(shift[2], 2.0)
        grad = np.abs(linear + hessian @ x)  # (k, n_x) |grad h(x_k)|
        spread = absolute @ shift  # (k, n_x) >= |grad h(x) - grad h(x_k)|
        # |g(x) u| <= (|v|, |v|, |omega|), |(g(x) - g(x_k)) u| <= (E |v|, E |v|, 0)
        linear_part = np.stack([spread[:, 0] + spread[:, 1]
                                + turned * (grad[:, 0] + grad[:, 1]), spread[:, 2]], axis=-1)
        rest = spread @ w + self._alpha * (grad @ shift + 0.5 * spread @ shift)
        return rest, linear_part

    def _as_asked(self, parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(nu0, c) as they are, or (nu0 + c^T U, 0) where the margin is the constant one."""
        if self.command_linear:
            return parts
        rest, linear = parts
        return rest + linear @ self._reach, np.zeros_like(linear)

    def split_rows(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(nu0 (K,), c (K, 2)) >= 0 of the problem's rows at the sampled state x and the box:
        the margin of a command u is nu0 + c^T |u|."""
        w = self._box(mean, std)
        state = np.asarray(x, dtype=np.float64)
        rests, linears = [], []
        for kind, data in self._parts:
            if kind == 'circles':
                cx, cy, lookahead = data  # type: ignore[misc]
                rest, linear = self._circles(x, w, cx, cy, lookahead)
            else:
                rest, linear = self._quadratic(state, w, *data)  # type: ignore[misc]
            rests.append(rest)
            linears.append(linear)
        if not rests:
            return np.zeros(0), np.zeros((0, 2))
        return self._as_asked((np.concatenate(rests), np.concatenate(linears)))

    def split_points(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float],
                     cx: np.ndarray, cy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nu0 (N,), c (N, 2)) of the sensor points' circle rows, centres (cx, cy)."""
        return self._as_asked(self._circles(x, self._box(mean, std), cx, cy,
                                            self._point_lookahead))

    def rows(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
             ) -> np.ndarray:
        """(K,) the constant nu_i = nu0_i + c_i^T U >= 0 of the problem's rows at the sampled
        state x and the box: the margin of the largest command within the limits."""
        rest, linear = self.split_rows(x, mean, std)
        return rest + linear @ self._reach

    def points(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float],
               cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        """(N,) the constant nu of the sensor points' circle rows, centres (cx, cy)."""
        rest, linear = self.split_points(x, mean, std, cx, cy)
        return rest + linear @ self._reach


class IntervalMargin:
    """The margins nu_i of a problem with a closed form (:mod:`rcbf_ros.core.lie_closed_form`)
    on any built-in system, bounded by ball arithmetic (:mod:`rcbf_ros.core.ball`) over an a
    priori enclosure of the reachable states (module docstring); build with
    :func:`sampled_data_margin`. ``rows(x, mean, std)`` gives the K rows' margins (inf where no
    enclosure closes: the filter then answers with its fail-safe)."""

    def __init__(self, problem: RCBFProblem, horizon: float, command_linear: bool = True
                 ) -> None:
        system = problem.system
        low = np.asarray(system.u_min, dtype=np.float64)
        high = np.asarray(system.u_max, dtype=np.float64)
        self.horizon = float(horizon)
        """tau = L + T (s)."""
        self.command_linear = bool(command_linear)
        """Whether the margin follows the command (else the constant nu0 + c^T U, c = 0)."""
        self._reach = np.maximum(np.abs(low), np.abs(high)).tolist()
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self._n_x, self._n_u, self._count = system.n_x, system.n_u, problem.n_barriers
        self._drift = _ball_drift(system.closed_form_source(), system.n_x)
        terms = ClosedFormTerms.from_problem(problem)
        if terms is None:  # sampled_data_margin checks it first
            raise ValueError(f'{problem!r} has no closed form')
        namespace = dict(JET_NAMESPACE)
        exec(compile(terms.source, '<closed form over jets>', 'exec'),  # noqa: S102
             namespace)
        self._terms_over_jets = namespace['barrier_terms']
        self._terms = terms
        # the look-ahead point each proposal can choose: ahead, and behind where it reverses
        speeds = sorted({s for s in (getattr(f, 'speed_input', None) for f in problem.families)
                         if s is not None})
        self._proposals = [[0.0] * self._n_u]
        if speeds:
            backwards = [0.0] * self._n_u
            for j in speeds:
                backwards[j] = -1.0
            self._proposals.append(backwards)

    def enclosure(self, x: Sequence[float], w: Sequence[float]) -> list[float] | None:
        """(n_x,) D with every state reachable from x within tau in x +/- D, or None where no
        enclosure closes (the module docstring's a priori bound)."""
        rate = self._rate
        spread = [self.horizon * v for v in rate(x, [0.0] * self._n_x, w)]
        for _ in range(ENCLOSURE_TRIES):
            trial = [1.25 * v + 1e-9 for v in spread]
            spread = [self.horizon * v for v in rate(x, trial, w)]
            if all(s <= t for s, t in zip(spread, trial)):
                return spread
        return None

    def _rate(self, x: Sequence[float], radius: Sequence[float], w: Sequence[float]
              ) -> list[float]:
        """sup of |f + g u + psi| per entry over x +/- radius, u within the limits, psi in the
        box."""
        (f, g), _ = hull_over_branches(self._drift, [Ball(c, r) for c, r in zip(x, radius)])
        return [_magnitude(fi) + sum(_magnitude(gij) * uj for gij, uj in zip(gi, self._reach))
                + wi for fi, gi, wi in zip(f, g, w)]

    def split_rows(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(nu0 (K,), c (K, n_u)) >= 0 of the problem's rows at the sampled state x and the
        box: the margin of a command u is nu0 + c^T |u|, c_ij = sup|dL_g h_ij| (the largest
        over the look-ahead points a proposal can choose, as nu0). A row without a bound has
        nu0 = inf and c = 0 (then its data is refused and the filter answers with its
        fail-safe)."""
        state = [float(v) for v in x]
        w = (np.abs(np.asarray(mean, dtype=np.float64))
             + self._k_c * np.asarray(std, dtype=np.float64)).tolist()
        count = self._count
        rest = np.zeros(count)
        linear = np.zeros((count, self._n_u))
        spread = self.enclosure(state, w) if all(map(math.isfinite, state + w)) else None
        if spread is None:
            return np.full(count, math.inf), linear
        box = [Jet.variable(c, r, k) for k, (c, r) in enumerate(zip(state, spread))]
        for proposal in self._proposals:
            at = self._terms.terms(state, np.array(proposal))
            at_h, at_grad, at_lf, at_lg = (v.tolist() for v in at)  # floats: NaN, no warning
            (h, grad, lf, lg), smooth = hull_over_branches(self._terms_over_jets, box, proposal)
            radii = spread if smooth else None
            for i in range(count):
                value = (_change(lf[i], at_lf[i], radii)
                         + sum(_change(b, v, radii) * wk
                               for b, v, wk in zip(grad[i], at_grad[i], w))
                         + self._alpha * _change(h[i], at_h[i], radii))
                rest[i] = max(rest[i], value if value == value else math.inf)
                for j, (b, v) in enumerate(zip(lg[i], at_lg[i])):
                    change = _change(b, v, radii)
                    linear[i, j] = max(linear[i, j], change if change == change else math.inf)
        unbounded = ~np.isfinite(rest) | ~np.isfinite(linear).all(axis=1)
        rest[unbounded], linear[unbounded] = math.inf, 0.0
        if not self.command_linear:
            return rest + linear @ np.asarray(self._reach), np.zeros_like(linear)
        return rest, linear

    def rows(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
             ) -> np.ndarray:
        """(K,) the constant nu_i = nu0_i + c_i^T U >= 0 of the problem's rows at the sampled
        state x and the box, U the largest |u| per input (inf where no bound is found)."""
        rest, linear = self.split_rows(x, mean, std)
        return rest + linear @ np.asarray(self._reach)


ENCLOSURE_TRIES = 30
"""Inflations of the reachable box :meth:`IntervalMargin.enclosure` tries before it gives up
(the margin is then infinite): a few where tau is small against the drift's rates of growth,
many or none (no box closes) as tau approaches their inverse (PVTOL's operator: 1 / k_h)."""


def _magnitude(value: Ball | float) -> float:
    """The largest |v| over a ball or of a float."""
    return value.magnitude() if isinstance(value, Ball) else abs(float(value))


def _change(value: Jet | Ball | float, at: float, radii: list[float] | None) -> float:
    """A bound of |v(x) - at| over the box, ``at`` = v(x_k): from the enclosure of the values,
    and for a jet with ``radii`` (the box's, the code smooth over it) from the mean value
    theorem too, the smaller."""
    if isinstance(value, Jet):
        bound = abs(value.value.centre - at) + value.value.radius
        return bound if radii is None else min(bound, value.change(radii))
    if isinstance(value, Ball):
        return abs(value.centre - at) + value.radius
    return abs(float(value) - at)


def _ball_drift(source: DriftSource, n_x: int) -> Callable:
    """A system's f and g (:class:`DriftSource`) as a function of n_x balls -> (f (n_x),
    g (n_x lists of n_u)), run by :func:`hull_over_branches`."""
    g = [['0.0'] * source.n_u for _ in range(n_x)]
    for (i, j), entry in source.g.items():
        g[i][j] = entry if isinstance(entry, str) else repr(float(entry))
    f = ', '.join(e if isinstance(e, str) else repr(float(e)) for e in source.f)
    text = '\n'.join(['def drift(values):', f'    {", ".join(state_names(n_x))}, = values',
                      *(f'    {line}' for line in source.lines),
                      f'    return [{f}], [{", ".join("[" + ", ".join(row) + "]" for row in g)}]',
                      ''])
    namespace = dict(BALL_NAMESPACE)
    exec(compile(text, '<drift over balls>', 'exec'), namespace)  # noqa: S102 - own source
    return namespace['drift']


def sampled_data_margin(problem: RCBFProblem, *, control_period_s: float = 0.0,
                        latency_s: float = 0.0, footprint: BarrierFamily | None = None,
                        command_linear: bool = True
                        ) -> SampledDataMargin | IntervalMargin | None:
    """The margins of ``problem``'s rows (and of sensor points around ``footprint``) for a
    command held ``control_period_s`` and applied ``latency_s`` after its state was sampled;
    None when both are 0 (the continuous-time rows, unchanged). ``command_linear`` False: the
    constant margin of the largest input, c = 0 (for comparison; the default follows the
    command).

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
    if not problem.has_limits:
        raise ValueError(f'{key}: the sampled-data margin needs input limits on the {name} '
                         'system (input_limits.min/max)')
    if type(system) is Unicycle and all(_unicycle_closed_form(f) for f in problem.families) and (
            footprint is None or _unicycle_closed_form(footprint)):
        lookahead = 0.0
        if footprint is not None and footprint.has_lookahead:  # type: ignore[attr-defined]
            lookahead = float(footprint.lookahead)  # type: ignore[attr-defined]
        return SampledDataMargin(problem, horizon, lookahead, command_linear)
    if type(system) in REFUSED_SYSTEMS:
        raise ValueError(f'{key}: no sampled-data margin is derived for the {name} system '
                         f'({REFUSED_SYSTEMS[type(system)]}); set control_period_s and '
                         'latency_s to 0')
    if footprint is not None:
        raise ValueError(f'{key}: the sampled-data margin of sensor points is derived on the '
                         f'unicycle beside uncascaded barriers only, not here (the {name} '
                         'system); set control_period_s and latency_s to 0')
    for family in problem.families:
        if not has_closed_form(replace(problem, families=(family,))):
            raise ValueError(f'{key}: no sampled-data margin is derived for the '
                             f'{type(family).__name__} barriers on the {name} system (no '
                             'closed form: a cascaded look-ahead point or user-defined rows); '
                             'set control_period_s and latency_s to 0')
    if not has_closed_form(problem):
        raise ValueError(f'{key}: no sampled-data margin is derived for the {name} system '
                         '(no closed form: a user-defined system); set control_period_s and '
                         'latency_s to 0')
    return IntervalMargin(problem, horizon, command_linear)


def split_rows(lg: np.ndarray, upper: np.ndarray, applied: Sequence[float],
               rest: np.ndarray, linear: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear rows that are exactly the rows tightened by command-linear margins.

    Row i at an action u is v_i(u) = upper_i + lg_i^T (u - applied) (``upper`` written at the
    proposal ``applied``); tightened by nu0_i + c_i^T |u| (``rest``, ``linear`` >= 0) it is
    v_i(u) - nu0_i - c_i^T |u|, concave in u (|u| is convex, c_i >= 0). As
    c_i^T |u| = max over the sign vectors s in {-1, +1}^{n_u} of (c_i * s)^T u, the row holds
    exactly when every one of the linear rows

        upper_i - nu0_i - (c_i * s)^T applied + (lg_i - c_i * s)^T (u - applied) >= 0

    holds, and the least of them at u is the tightened row's value there. A row takes the sign
    vectors that are +1 wherever its c is 0 (the others repeat them): one row where c_i = 0,
    2^m where m entries of c_i are > 0.

    Args:
        lg: (K, n_u) L_g h of each row.
        upper: (K,) the right-hand sides at ``applied``.
        applied: (n_u,) the proposal the rows are written at.
        rest: (K,) nu0 of each row.
        linear: (K, n_u) c of each row, >= 0.

    Returns:
        (lg (M, n_u), upper (M,), starts (K,)): the rows of row i are starts[i] to
        starts[i + 1] (the last to M), in the order of the rows.
    """
    count, n_u = lg.shape
    signs = _signs(n_u)
    shifted = linear[:, None, :] * signs[None]  # (K, S, n_u)
    split_lg = lg[:, None, :] - shifted
    split_upper = (upper - rest)[:, None] - shifted @ np.asarray(applied, dtype=np.float64)
    positive = linear > 0.0
    if positive.all():  # every row takes every sign vector
        return (split_lg.reshape(-1, n_u), split_upper.reshape(-1),
                np.arange(0, count * signs.shape[0], signs.shape[0]))
    taken = ~((signs < 0.0)[None] & ~positive[:, None, :]).any(axis=2)  # (K, S)
    starts = np.zeros(count, dtype=np.int64)
    np.cumsum(taken.sum(axis=1)[:-1], out=starts[1:])
    return split_lg[taken], split_upper[taken], starts


@functools.cache
def _signs(n_u: int) -> np.ndarray:
    """(2^n_u, n_u) the sign vectors in {-1, +1}^n_u, all +1 first."""
    return np.array(list(product((1.0, -1.0), repeat=n_u))).reshape(-1, n_u)


def least_per_row(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(K,) the least of each row's split rows' ``values`` (:func:`split_rows`): the tightened
    row's own value."""
    return np.minimum.reduceat(values, starts) if starts.size else values[:0]


def _unicycle_closed_form(family: BarrierFamily) -> bool:
    """Whether the Unicycle's closed-form margin covers ``family`` (module docstring)."""
    if type(family) is CircleObstacles:
        return tuple(family.position_indices) == (0, 1) and family.heading_index in (None, 2)
    return type(family) in _QUADRATIC

"""Barrier terms and RCBF-QP rows of ONE state in closed form (numpy float64).

The same math as :func:`rcbf_ros.core.rcbf.barrier_terms` and
:func:`rcbf_ros.core.qp.build_rcbf_qp`, evaluated without autograd for the per-step filter
(B = 1, where torch's per-operation overhead is most of the cost). The batched torch path stays
the definition the learner differentiates through; the tests hold the two equal.

Every built-in base barrier except a look-ahead circle is a quadratic of the state,
h(x) = c + a^T x + 1/2 x^T Q x (:class:`~rcbf_ros.core.barriers.QuadraticRows`). With J the
Jacobian of f (:class:`DriftJet`), the cascades h1 = L_f h + gamma_1 h and
h2 = L_f h1 + gamma_2 h1 have the gradients

    grad h   = a + Q x
    grad h1  = Q f + J^T grad h + gamma_1 grad h
    grad h2  = Q J f + J^T Q f + R^T grad h + gamma_1 Q f + J^T grad h1 + gamma_2 grad h1

(the Hessian of h1 is Q J + J^T Q + sum_m (grad h)_m Hess f_m + gamma_1 Q, applied to f), where
R = sum_k f_k dJ/dx_k is the rate of J along f. R = 0 for the built-in systems (the drift jet
test checks it against autograd), so the closed form leaves that term out; a system with R != 0
would need it.
A look-ahead circle, h = ||p - c||^2 - delta^2 with p = (x_i, x_j) + s l_p (cos th, sin th),
has grad h = 2 (p - c) on (x_i, x_j) and 2 s l_p (p - c)^T (-sin th, cos th) on th; it is used
uncascaded only, with the direction-of-travel switch of :func:`barrier_terms`.

:meth:`ClosedFormTerms.from_problem` is the one place that decides whether a problem has a
closed form: a built-in system (by exact type) and built-in families, cascaded at most twice,
no look-ahead circle inside a cascade, every cascade over the problem's own system. Anything else
(a system or family given by dotted path) keeps the autograd path.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    Cascaded,
    CircleObstacles,
    HalfPlane,
    PairGap,
    QuadraticRows,
)
from rcbf_ros.core.dynamics import CLOSED_FORM_SYSTEMS, DriftJet, DriftJetFunction
from rcbf_ros.core.rcbf import RCBFProblem

MAX_CASCADE_DEPTH = 2
"""Deepest cascade with a closed form here (the built-in configs use up to 2)."""
_QUADRATIC_FAMILIES = (BandBarrier, CircleObstacles, HalfPlane, PairGap)
_PAIR_SUM = np.ones(2)
_PAIR_SUM.setflags(write=False)
"""Sums the two columns of a (k, 2) array in one product (cheaper than ``sum(axis=1)``)."""


class NumpyTerms(NamedTuple):
    """:class:`~rcbf_ros.core.rcbf.BarrierTerms` of one state (K barriers), numpy float64."""

    h: np.ndarray
    """(K,) h_i(x)."""
    grad_h: np.ndarray
    """(K, n_x) grad h_i(x)."""
    lf_h: np.ndarray
    """(K,) L_f h_i(x)."""
    lg_h: np.ndarray
    """(K, n_u) L_g h_i(x)."""


def _unwrap(family: BarrierFamily) -> tuple[BarrierFamily, list[Cascaded]]:
    """The base family under a stack of cascades, and the cascade levels (innermost first)."""
    levels = []
    while type(family) is Cascaded:
        levels.append(family)
        family = family.base
    return family, levels[::-1]


class _QuadraticStack:
    """Every quadratic row of the problem, cascaded 0, 1 or 2 times, in one set of arrays."""

    def __init__(self, rows: Sequence[tuple[QuadraticRows, tuple[float, ...]]], n_x: int):
        constant = np.concatenate([r.constant for r, _ in rows])
        linear = np.concatenate([r.linear for r, _ in rows])
        hessian = np.concatenate([r.hessian for r, _ in rows])
        k = constant.size
        depth = np.concatenate([np.full(r.constant.size, len(g), dtype=np.intp)
                                for r, g in rows])
        gammas = np.zeros((MAX_CASCADE_DEPTH, k))
        start = 0
        for r, g in rows:
            gammas[:len(g), start:start + r.constant.size] = np.array(g, dtype=np.float64)[:, None]
            start += r.constant.size
        self.count = k
        self.depth = int(depth.max(initial=0))
        self._constant = constant
        self._linear = linear
        # Q stacked as (n_x, K n_x) so that one product gives Q x, Q f, Q J f for every row.
        self._hessian_t = np.ascontiguousarray(hessian.reshape(k * n_x, n_x).T)
        self._n_x = n_x
        self._gamma1 = gammas[0]
        self._gamma2 = gammas[1]
        # the gains repeated along each row (an elementwise product without broadcasting)
        self._gamma1_rows = np.repeat(gammas[0][:, None], n_x, axis=1)
        self._gamma2_rows = np.repeat(gammas[1][:, None], n_x, axis=1)
        # Row i's top level is level depth[i]: index into the levels stacked row-wise.
        self._select = None if np.all(depth == self.depth) else depth * k + np.arange(k)

    def __call__(self, x: np.ndarray, jet: DriftJet | None) -> tuple[np.ndarray, np.ndarray]:
        """(h (k,), grad h (k, n_x)) at the top level of every row (the formulas of the module
        docstring; ``.dot`` rather than ``@``: half the call overhead at these sizes)."""
        k, n_x = self.count, self._n_x
        linear = self._linear
        if self.depth == 0:
            qx = x.dot(self._hessian_t).reshape(k, n_x)
            return self._constant + (linear + 0.5 * qx).dot(x), qx + linear
        f, jacobian = jet.f, jet.jacobian
        if self.depth == 1:
            qx, qf = np.array((x, f)).dot(self._hessian_t).reshape(2, k, n_x)
        else:
            qx, qf, qjf = np.array((x, f, jacobian.dot(f))).dot(self._hessian_t).reshape(
                3, k, n_x)
        g0 = qx + linear
        h0 = self._constant + (linear + 0.5 * qx).dot(x)
        h1 = g0.dot(f) + self._gamma1 * h0
        g1 = qf + g0.dot(jacobian) + self._gamma1_rows * g0
        if self.depth == 1:
            levels_h, levels_g = (h0, h1), (g0, g1)
        else:
            h2 = g1.dot(f) + self._gamma2 * h1
            g2 = qjf + self._gamma1_rows * qf + (qf + g1).dot(jacobian) + self._gamma2_rows * g1
            levels_h, levels_g = (h0, h1, h2), (g0, g1, g2)
        if self._select is None:
            return levels_h[-1], levels_g[-1]
        return (np.concatenate(levels_h).take(self._select),
                np.concatenate(levels_g).take(self._select, axis=0))


class _LookaheadCircles:
    """An uncascaded :class:`CircleObstacles` with a look-ahead point, and its direction-of-travel
    switch (the point behind for a reversing proposal, when that point is clear).

    With d = p - c (k, 2), grad h = d M, M = [[2 on x_i, -2 s l_p sin th on th],
    [2 on x_j, 2 s l_p cos th on th]] (2, n_x): one product for every obstacle."""

    def __init__(self, family: CircleObstacles, n_x: int):
        delta = np.array(family.radii, dtype=np.float64) + family.margin
        self.count = family.count
        self._centers = np.array(family.centers, dtype=np.float64).reshape(-1, 2)
        self._delta_sq = delta ** 2
        self._i, self._j = family.position_indices
        self._heading = family.heading_index
        self._lookahead = family.lookahead
        self._speed = family.speed_input
        position = np.zeros((2, n_x))
        position[0, self._i] += 2.0
        position[1, self._j] += 2.0
        position.setflags(write=False)
        self._position = position  # M without the heading's column

    def _point(self, values: list[float], side: float) -> tuple[np.ndarray, np.ndarray]:
        theta = values[self._heading]
        cos, sin = math.cos(theta), math.sin(theta)
        offset = self._lookahead * side
        d = (values[self._i] + offset * cos, values[self._j] + offset * sin) - self._centers
        h = (d * d).dot(_PAIR_SUM) - self._delta_sq
        m = self._position.copy()
        m[0, self._heading] += -2.0 * offset * sin
        m[1, self._heading] += 2.0 * offset * cos
        return h, d.dot(m)

    def __call__(self, values: list[float], u: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(h (k,), grad h (k, n_x)) at the point the proposal u chooses."""
        if self._speed is not None and u is not None and u[self._speed] < 0:
            h, grad = self._point(values, -1.0)
            if np.minimum.reduce(h, initial=math.inf) >= 0:
                return h, grad
        return self._point(values, 1.0)


class ClosedFormTerms:
    """h, grad h, L_f h and L_g h of one state for a problem with a closed form (module doc)."""

    def __init__(self, jet: DriftJetFunction, n_x: int,
                 quadratic: _QuadraticStack | None, lookahead: list[_LookaheadCircles],
                 order: np.ndarray | None) -> None:
        self._jet = jet
        self._n_x = n_x
        self._quadratic = quadratic
        self._lookahead = lookahead
        self._order = order

    @classmethod
    def from_problem(cls, problem: RCBFProblem) -> ClosedFormTerms | None:
        """The closed form of ``problem``, or None where it has none (module docstring): the one
        place that decides between the closed form and autograd."""
        system = problem.system
        if type(system) not in CLOSED_FORM_SYSTEMS:
            return None
        n_x = system.n_x
        quadratic: list[tuple[QuadraticRows, tuple[float, ...]]] = []
        lookahead: list[_LookaheadCircles] = []
        # row positions in the problem's order: quadratic rows first, then look-ahead ones
        quadratic_rows: list[np.ndarray] = []
        lookahead_rows: list[np.ndarray] = []
        start = 0
        for family in problem.families:
            base, levels = _unwrap(family)
            if type(base) not in _QUADRATIC_FAMILIES or len(levels) > MAX_CASCADE_DEPTH:
                return None
            if any(level.system != system or type(level.system) is not type(system)
                   for level in levels):
                return None
            rows = np.arange(start, start + base.count)
            start += base.count
            if type(base) is CircleObstacles and base.has_lookahead:
                if levels:
                    return None
                lookahead.append(_LookaheadCircles(base, n_x))
                lookahead_rows.append(rows)
                continue
            quadratic.append((base.quadratic_rows(n_x),
                              tuple(float(level.gamma) for level in levels)))
            quadratic_rows.append(rows)
        position = np.concatenate(quadratic_rows + lookahead_rows)
        order = None if np.array_equal(position, np.arange(start)) else np.argsort(position)
        stack = _QuadraticStack(quadratic, n_x) if quadratic else None
        return cls(system.closed_form_drift(), n_x, stack, lookahead, order)

    def terms(self, x: np.ndarray, u_rl: np.ndarray | None = None) -> NumpyTerms:
        """Barrier terms at x: (n_x,); u_rl: (n_u,) picks the look-ahead point of obstacles with
        a ``speed_input`` (None: the point ahead), as in :func:`barrier_terms`."""
        jet = self._jet(x)
        parts = []
        if self._quadratic is not None:
            parts.append(self._quadratic(x, jet))
        if self._lookahead:
            values = x.tolist()
            parts += [family(values, u_rl) for family in self._lookahead]
        if len(parts) == 1:
            h, grad = parts[0]
        else:
            h = np.concatenate([p[0] for p in parts])
            grad = np.concatenate([p[1] for p in parts])
            if self._order is not None:
                h, grad = h[self._order], grad[self._order]
        return NumpyTerms(h, grad, grad.dot(jet.f), grad.dot(jet.g))


def robust_margin(grad_h: np.ndarray, mean: np.ndarray, std: np.ndarray,
                  k_c: float) -> np.ndarray:
    """:func:`rcbf_ros.core.qp.robust_margin` at one state: grad_h (K, n_x), mean and std (n_x,)
    -> (K,) rho = grad_h mean - k_c |grad_h| std."""
    return grad_h.dot(mean) - k_c * np.abs(grad_h).dot(std)


class RCBFRows:
    """G and the right-hand side of :func:`rcbf_ros.core.qp.build_rcbf_qp` for one state.

    The constant part of G (the slack column, the limit rows) is built once; a call writes
    -L_g h into a copy. Rows: [-L_g h_i, -1] z <= L_f h_i + L_g h_i u_RL + alpha h_i + rho_i,
    then [e_j, 0] z <= u_max_j - u_RL_j and [-e_j, 0] z <= u_RL_j - u_min_j with limits."""

    def __init__(self, *, n_barriers: int, n_u: int, alpha: float,
                 u_min: Sequence[float] | None = None,
                 u_max: Sequence[float] | None = None) -> None:
        """Args: n_barriers (K), n_u (m), alpha (the class-K gain), u_min and u_max (m actuator
        limits each, or both None)."""
        if (u_min is None) != (u_max is None):
            raise ValueError('u_min/u_max: give both actuator limits or neither')
        k, m = n_barriers, n_u
        self._k, self._m = k, m
        self._alpha = float(alpha)
        self._u_min = None if u_min is None else np.array(u_min, dtype=np.float64)
        self._u_max = None if u_max is None else np.array(u_max, dtype=np.float64)
        template = np.zeros((k if u_min is None else k + 2 * m, m + 1))
        template[:k, m] = -1.0
        if u_min is not None:
            template[k:k + m, :m] = np.eye(m)
            template[k + m:, :m] = -np.eye(m)
        template.setflags(write=False)
        self._template = template

    def __call__(self, *, h: np.ndarray, lf_h: np.ndarray, lg_h: np.ndarray, rho: np.ndarray,
                 u_rl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """h, lf_h, rho: (K,); lg_h: (K, m); u_rl: (m,) -> (G (nc, m + 1), right-hand side
        (nc,)), nc = K (+ 2 m with limits)."""
        upper = lf_h + lg_h.dot(u_rl) + self._alpha * h + rho
        g_matrix = self._template.copy()
        np.negative(lg_h, out=g_matrix[:self._k, :self._m])
        if self._u_min is None:
            return g_matrix, upper
        return g_matrix, np.concatenate((upper, self._u_max - u_rl, u_rl - self._u_min))


NumpyAssembly = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                         tuple[np.ndarray, np.ndarray, np.ndarray]]
"""(x, u_rl, mean, std), each 1-D float64 -> (h (K,), G (nc, nz), h_qp (nc,))."""


class ClosedFormAssembly:
    """The filter's per-call constraint assembly in closed form: :meth:`RCBFProblem.qp` at one
    state, numpy in and out. Build with :meth:`from_problem`."""

    def __init__(self, problem: RCBFProblem, terms: ClosedFormTerms) -> None:
        self.terms = terms
        """The barrier terms' evaluator."""
        self._k_c = float(problem.k_c)
        limits = problem.has_limits
        self.rows = RCBFRows(n_barriers=problem.n_barriers, n_u=problem.system.n_u,
                             alpha=problem.alpha,
                             u_min=problem.system.u_min if limits else None,
                             u_max=problem.system.u_max if limits else None)
        """The QP rows' builder."""

    @classmethod
    def from_problem(cls, problem: RCBFProblem) -> ClosedFormAssembly | None:
        """The closed-form assembly, or None where :meth:`ClosedFormTerms.from_problem` finds
        no closed form."""
        terms = ClosedFormTerms.from_problem(problem)
        return None if terms is None else cls(problem, terms)

    def __call__(self, x: np.ndarray, u_rl: np.ndarray, mean: np.ndarray, std: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h (K,), G (nc, m + 1), right-hand side (nc,)) at state x, proposal u_rl and the
        disturbance box mean +/- k_c std (all 1-D float64), as :meth:`RCBFProblem.qp`."""
        terms = self.terms.terms(x, u_rl)
        rho = robust_margin(terms.grad_h, mean, std, self._k_c)
        g_matrix, upper = self.rows(h=terms.h, lf_h=terms.lf_h, lg_h=terms.lg_h, rho=rho,
                                    u_rl=u_rl)
        return terms.h, g_matrix, upper

"""Barrier terms and RCBF-QP rows of ONE state in closed form (numpy float64).

The same math as :func:`rcbf_ros.core.rcbf.barrier_terms` and
:func:`rcbf_ros.core.qp.build_rcbf_qp`, evaluated without autograd for the per-step filter
(B = 1, where torch's per-operation overhead is most of the cost). The batched torch path stays
the definition the learner differentiates through; the tests hold the two equal.

Every built-in base barrier except a look-ahead circle is a quadratic of the state,
h(x) = c + a^T x + 1/2 x^T Q x (:class:`~rcbf_ros.core.barriers.QuadraticRows`). With J the
Jacobian of f (:class:`DriftJet`), the Lie derivatives along f (L^0 h = h, L^1 h = L_f h,
L^2 h = L_f L_f h) and their gradients are

    L^0 h = c + a^T x + 1/2 x^T Q x          grad L^0 h = a + Q x
    L^1 h = a^T f + x^T Q f                  grad L^1 h = Q f + J^T (a + Q x)
    L^2 h = f^T Q f + a^T J f + x^T Q J f    grad L^2 h = Q J f + 2 J^T Q f + (J^2)^T (a + Q x)

leaving out R = sum_k f_k dJ/dx_k, the rate of J along f: R = 0 for the built-in systems (the
drift jet test checks it against autograd); a system with R != 0 would need it. The cascades
h1 = L_f h + gamma_1 h and h2 = L_f h1 + gamma_2 h1 are sums of these levels,

    h_top = beta_0 L^0 h + beta_1 L^1 h + beta_2 L^2 h    (and grad h_top likewise), with
    beta = (1, 0, 0) uncascaded, (gamma_1, 1, 0) cascaded once,
    (gamma_1 gamma_2, gamma_1 + gamma_2, 1) cascaded twice.

With w = (x, f, J f) (3 n_x entries), T the symmetric 3 x 3 matrix
[[beta_0, beta_1, beta_2], [beta_1, 2 beta_2, 0], [beta_2, 0, 0]] and M = T (x) Q (Kronecker),
b = (beta_0 a, beta_1 a, beta_2 a), the coefficients C = b + M w (three n_x blocks) give

    grad h_top^T = C [I; J; J^2]          h_top = beta_0 c + 1/2 (b + C)^T w

(expand the products to see the table above). M, b and beta_0 c are fixed per row, so one
product w M for every row, of any cascade depth, gives C; one more gives every gradient
(:class:`_QuadraticStack`). Where no row is cascaded twice, the third blocks (beta_2 = 0) are
left out: w = (x, f) and [I; J]; where none is cascaded, w = x and I.

A look-ahead circle, h = ||p - c||^2 - delta^2 with p = (x_i, x_j) + s l_p (cos th, sin th),
has grad h = 2 (p - c) on (x_i, x_j) and 2 s l_p (p - c)^T (-sin th, cos th) on th; it is used
uncascaded only, with the direction-of-travel switch of :func:`barrier_terms`, and evaluated on
Python floats (a handful of values per obstacle, fewer operations than numpy's per-call cost).

The QP rows then take a few more products, in the order of
:func:`rcbf_ros.core.qp.build_rcbf_qp` (so that the row values round as there):
L_f h = grad h^T f, L_g h = grad h^T g, rho = grad h^T mean - k_c |grad h|^T std and the right-hand
side L_f h + L_g h u + alpha h + rho.

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


def unwrap_cascades(family: BarrierFamily) -> tuple[BarrierFamily, list[Cascaded]]:
    """The base family under a stack of cascades, and the cascade levels (innermost first)."""
    levels = []
    while type(family) is Cascaded:
        levels.append(family)
        family = family.base
    return family, levels[::-1]


class _QuadraticStack:
    """Every quadratic row of the problem, cascaded 0, 1 or 2 times, in one set of arrays
    (the products of the module docstring)."""

    def __init__(self, rows: Sequence[tuple[QuadraticRows, tuple[float, ...]]], n_x: int):
        blocks, offsets, constants = [], [], []
        self.depth = max(len(gammas) for _, gammas in rows)
        levels = self.depth + 1
        for quadratic, gammas in rows:
            weights = _cascade_weights(gammas)
            # T of the module docstring, truncated to the levels the deepest row needs
            t = np.array([[weights[0], weights[1], weights[2]],
                          [weights[1], 2.0 * weights[2], 0.0],
                          [weights[2], 0.0, 0.0]])[:levels, :levels]
            for c, a, q in zip(quadratic.constant, quadratic.linear, quadratic.hessian):
                blocks.append(np.kron(t, q))  # M = T (x) Q, symmetric
                offsets.append(np.concatenate([w * a for w in weights[:levels]]))
                constants.append(weights[0] * c)
        self.count = len(constants)
        self._n_x = n_x
        self._levels = levels
        # w M for every row in one product: row i's M as columns [i L n_x, (i + 1) L n_x)
        self._product = np.ascontiguousarray(np.concatenate(blocks, axis=1))
        self._offset = np.concatenate(offsets)  # b of every row, flat like w M
        self._offsets = self._offset.reshape(self.count, levels * n_x)
        self._constant = np.array(constants)  # beta_0 c
        self._identity = np.eye(n_x)

    def __call__(self, x: np.ndarray, jet: DriftJet) -> tuple[np.ndarray, np.ndarray]:
        """(h (k,), grad h (k, n_x)) at the top level of every row (``.dot`` rather than
        ``@``: a third of the call overhead at these sizes)."""
        levels = self._levels
        jacobian = jet.jacobian
        if levels == 1:
            w, powers = x, self._identity
        elif levels == 2:
            w = np.concatenate((x, jet.f))
            powers = np.concatenate((self._identity, jacobian))
        else:
            w = np.concatenate((x, jet.f, jacobian.dot(jet.f)))
            powers = np.concatenate((self._identity, jacobian, jacobian.dot(jacobian)))
        # C = b + M w, one row of C per barrier
        coefficients = (w.dot(self._product) + self._offset).reshape(self.count, -1)
        h = (coefficients + self._offsets).dot(0.5 * w) + self._constant
        return h, coefficients.dot(powers)


def _cascade_weights(gammas: Sequence[float]) -> tuple[float, float, float]:
    """beta of the module docstring: h_top = sum_l beta_l L_f^l h for a cascade's gains."""
    if len(gammas) == 0:
        return 1.0, 0.0, 0.0
    if len(gammas) == 1:
        return float(gammas[0]), 1.0, 0.0
    g1, g2 = (float(g) for g in gammas)
    return g1 * g2, g1 + g2, 1.0


class _LookaheadCircles:
    """An uncascaded :class:`CircleObstacles` with a look-ahead point, and its direction-of-travel
    switch (the point behind for a reversing proposal, when that point is clear), on Python
    floats.

    With d = p - c, h = d_x^2 + d_y^2 - delta^2 and grad h = 2 d_x on x_i, 2 d_y on x_j and
    2 s l_p (-d_x sin th + d_y cos th) on th."""

    def __init__(self, family: CircleObstacles, n_x: int):
        delta = [radius + family.margin for radius in family.radii]
        self.count = family.count
        self._obstacles = [(float(cx), float(cy), float(d * d))
                           for (cx, cy), d in zip(family.centers, delta)]
        self._i, self._j = family.position_indices
        self._heading = family.heading_index
        self._lookahead = float(family.lookahead)
        self._speed = family.speed_input
        self._n_x = n_x

    def _point(self, values: list[float], side: float
               ) -> tuple[list[float], list[list[float]]]:
        i, j, heading = self._i, self._j, self._heading
        theta = values[heading]
        cos, sin = math.cos(theta), math.sin(theta)
        offset = self._lookahead * side
        px, py = values[i] + offset * cos, values[j] + offset * sin
        turn_x, turn_y = -2.0 * offset * sin, 2.0 * offset * cos  # 2 dp/dth
        h, grad = [], []
        for cx, cy, delta_sq in self._obstacles:
            dx, dy = px - cx, py - cy
            h.append(dx * dx + dy * dy - delta_sq)
            row = [0.0] * self._n_x
            row[i] += 2.0 * dx
            row[j] += 2.0 * dy
            row[heading] += dx * turn_x + dy * turn_y
            grad.append(row)
        return h, grad

    def __call__(self, values: list[float], u: np.ndarray | None
                 ) -> tuple[list[float], list[list[float]]]:
        """(h (k values), grad h (k rows of n_x)) at the point the proposal u chooses."""
        if self._speed is not None and u is not None and u[self._speed] < 0:
            h, grad = self._point(values, -1.0)
            if all(value >= 0.0 for value in h):
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
            base, levels = unwrap_cascades(family)
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

    def jet(self, x: np.ndarray) -> DriftJet:
        """f, J and g of the problem's system at x: (n_x,)."""
        return self._jet(x)

    def top(self, x: np.ndarray, jet: DriftJet, u_rl: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
        """(h (K,), grad h (K, n_x)) at x: (n_x,), in the problem's row order; ``jet`` at x
        (:meth:`jet`); u_rl (n_u,) picks the look-ahead point (see :meth:`terms`)."""
        if self._quadratic is not None and not self._lookahead:
            return self._quadratic(x, jet)
        values = x.tolist()
        circles = [family(values, u_rl) for family in self._lookahead]
        h = np.array([value for family_h, _ in circles for value in family_h])
        grad = np.array([row for _, family_grad in circles for row in family_grad]
                        ).reshape(h.size, self._n_x)
        if self._quadratic is None:
            return h, grad
        quadratic_h, quadratic_grad = self._quadratic(x, jet)
        h = np.concatenate((quadratic_h, h))
        grad = np.concatenate((quadratic_grad, grad))
        if self._order is not None:
            h, grad = h[self._order], grad[self._order]
        return h, grad

    def terms(self, x: np.ndarray, u_rl: np.ndarray | None = None) -> NumpyTerms:
        """Barrier terms at x: (n_x,); u_rl: (n_u,) picks the look-ahead point of obstacles with
        a ``speed_input`` (None: the point ahead), as in :func:`barrier_terms`."""
        jet = self._jet(x)
        h, grad = self.top(x, jet, u_rl)
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
        return self.complete(upper=lf_h + lg_h.dot(u_rl) + self._alpha * h + rho, lg_h=lg_h,
                             u_rl=u_rl)

    def complete(self, *, upper: np.ndarray, lg_h: np.ndarray, u_rl: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """G and the right-hand side from the RCBF rows' right-hand sides upper (K,) =
        L_f h + L_g h u_RL + alpha h + rho, lg_h (K, m) and u_rl (m,)."""
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
        # alpha and k_c once per row: array * array costs a third of array * Python float
        self._alpha_rows = np.full(problem.n_barriers, float(problem.alpha))
        self._k_c_rows = np.full(problem.n_barriers, self._k_c)
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
        jet = self.terms.jet(x)
        h, grad = self.terms.top(x, jet, u_rl)
        lg_h = grad.dot(jet.g)
        rho = grad.dot(mean) - self._k_c_rows * np.abs(grad).dot(std)  # robust_margin
        upper = grad.dot(jet.f) + lg_h.dot(u_rl) + self._alpha_rows * h + rho
        g_matrix, upper = self.rows.complete(upper=upper, lg_h=lg_h, u_rl=u_rl)
        return h, g_matrix, upper

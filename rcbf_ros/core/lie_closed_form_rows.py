"""The RCBF rows of one state for MANY circle obstacles: numpy over the rows, not code per row.

:mod:`rcbf_ros.core.lie_closed_form` generates straight-line Python per row: the fastest for a
few dozen rows, but its cost and its code grow with the row count (Python's compiler refuses
the function past about 750 rows). A :class:`~rcbf_ros.core.barriers.CircleObstacles` family
of at least :data:`VECTOR_ROWS` obstacles is evaluated here instead, as one expression over
arrays of centres and radii (its rows differ in their centre and radius only):

- with a look-ahead point p = (x_i, x_j) + s l_p (cos th, sin th), uncascaded,
  d = p - c_o, h_o = |d|^2 - delta_o^2, grad h_o = 2 d on (x_i, x_j) and
  2 s l_p d^T (-sin th, cos th) on th (s = -1, the point behind, for a proposal with a
  negative ``speed_input`` whose point behind is clear of every obstacle, as
  :func:`~rcbf_ros.core.rcbf.barrier_terms` chooses);
- without one, h_o = (x_i - c_o,x)^2 + (x_j - c_o,y)^2 - delta_o^2 (Hessian Q = 2 on
  (x_i, x_j), the same for every row) and its cascades (g0 = grad h_o, J the Jacobian of f):

      h1 = g0^T f + gamma_1 h_o              grad h1 = Q f + J^T g0 + gamma_1 g0
      h2 = grad h1^T f + gamma_2 h1          grad h2 = Q J f + gamma_1 Q f + J^T (Q f + grad h1)
                                                       + gamma_2 grad h1

  (the formulas of :mod:`rcbf_ros.core.lie_closed_form_batch`).

Then the rows of :meth:`~rcbf_ros.core.rcbf.RCBFProblem.qp`: L_g h = grad h^T g and the
right-hand side grad h^T (x_dot + psi) + alpha h, psi the vertex of the disturbance box by the
sign of each gradient entry, as the generated code evaluates it. The other families of the
problem (bands, walls, gaps, small circle sets) keep the generated code; f, J and g come from
the system's :class:`~rcbf_ros.core.dynamics.DriftSource`. Nothing here imports torch.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

import numpy as np

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.lie_closed_form import (
    _closed_form_families,
    ClosedFormAssembly,
)
from rcbf_ros.core.rcbf import RCBFProblem

_least = np.minimum.reduce
"""An array's least value (its ``min`` without the method's wrapper)."""
VECTOR_ROWS = 64
"""The fewest obstacles of a :class:`CircleObstacles` family evaluated over arrays; a smaller
family keeps the generated per-row code (faster there: a numpy call costs about a microsecond,
a generated row a fraction of one; benchmarks/bench_obstacle_scale.py)."""
SMALL_PRODUCT = 16_384
"""The most entries (both operands together) of a product :func:`product` takes by
``ndarray.dot``; larger ones by ``@``."""


def product(left: np.ndarray, right: np.ndarray | list[float]) -> np.ndarray:
    """``left @ right`` of float64 arrays (``right`` may be a list of floats), the same values
    bit for bit where both are C- or F-contiguous, as every caller's are (a strided view may
    round differently: ``dot`` copies it, ``@`` may not): ``ndarray.dot`` makes the same BLAS
    call with the same arguments, without
    matmul's ufunc overhead (about a microsecond a call, most of a small product's time); from
    :data:`SMALL_PRODUCT` entries on ``@`` itself, faster there (measured: by about 10 % at
    100k rows)."""
    listed = type(right) is list
    if left.size + (len(right) if listed else right.size) <= SMALL_PRODUCT:
        return left.dot(right)
    return left @ (np.array(right) if listed else right)


class ManyRows(NamedTuple):
    """The RCBF rows of one state (K barriers, numpy float64), as the filter's many-row path
    takes them: row i is [-lg_i, -1] z <= upper_i."""

    h: np.ndarray
    """(K,) h_i(x)."""
    lg: np.ndarray
    """(K, n_u) L_g h_i(x)."""
    upper: np.ndarray
    """(K,) L_f h_i + L_g h_i u + alpha h_i + rho_i at the proposal u."""
    limit_upper: list[float]
    """The limit rows' right-hand sides: u_max_j - u_j, then u_j - u_min_j ([] without
    limits)."""
    size: float
    """The sum of the squares of h, the rows (with their -1) and every right-hand side, as
    :data:`~rcbf_ros.core.lie_closed_form.RowAssembly` returns it (the one-sum data check)."""


class _Circles:
    """One :class:`CircleObstacles` family over arrays (module docstring)."""

    def __init__(self, family: CircleObstacles, gammas: tuple[float, ...], n_x: int) -> None:
        self.cx = np.array([c[0] for c in family.centers], dtype=np.float64)
        self.cy = np.array([c[1] for c in family.centers], dtype=np.float64)
        delta = np.array(family.radii, dtype=np.float64) + float(family.margin)
        self.delta_sq = delta * delta
        self.i, self.j = family.position_indices
        self.heading = family.heading_index if family.has_lookahead else None
        self.lookahead = float(family.lookahead)
        self.speed = family.speed_input
        self.gammas = gammas
        self.n_x = n_x

    def terms(self, x: list[float], u: list[float], f: np.ndarray | None,
              jacobian: np.ndarray | None) -> tuple[np.ndarray, list[int], np.ndarray]:
        """(h (k,), the state indices where the gradient can be nonzero, the gradient there
        (c, k)) at x, the look-ahead point chosen by the proposal u."""
        if self.heading is not None:
            cos, sin = math.cos(x[self.heading]), math.sin(x[self.heading])
            offset = self.lookahead
            grads = np.empty((3, self.cx.size))
            dx, dy, d_heading = grads[0], grads[1], grads[2]  # (indexing: cheaper than iterating)
            squares = np.empty((2, self.cx.size))
            h, square = squares[0], squares[1]  # dx^2 + dy^2 - delta^2, and a buffer
            behind = False
            if self.speed is not None and u[self.speed] < 0.0:
                # the point behind, kept where it is clear of every circle: its differences
                # and h are then the rows' own (x + (-l) cos = x - l cos)
                np.subtract(x[self.i] - offset * cos, self.cx, out=dx)
                np.subtract(x[self.j] - offset * sin, self.cy, out=dy)
                np.multiply(grads[:2], grads[:2], out=squares)
                h += square
                h -= self.delta_sq
                # clear: every dx^2 + dy^2 >= delta^2, i.e. every h >= 0 (a rounded difference
                # has the exact one's sign, and is 0 only where the two are equal); a NaN in h
                # (inf - inf, or NaN) takes the comparisons themselves
                least = _least(h) if h.size else math.inf
                behind = least >= 0.0 or (least != least and bool(
                    (dx * dx + dy * dy >= self.delta_sq).all()))
            if behind:
                offset = -offset
            else:
                np.subtract(x[self.i] + offset * cos, self.cx, out=dx)
                np.subtract(x[self.j] + offset * sin, self.cy, out=dy)
                np.multiply(grads[:2], grads[:2], out=squares)
                h += square
                h -= self.delta_sq
            # d h / d th = 2 s l_p d^T (-sin th, cos th)
            np.multiply(dy, 2.0 * offset * cos, out=d_heading)
            d_heading -= np.multiply(dx, 2.0 * offset * sin, out=square)
            grads[:2] *= 2.0
            return h, [self.i, self.j, self.heading], grads
        dx, dy = x[self.i] - self.cx, x[self.j] - self.cy
        h = dx * dx + dy * dy - self.delta_sq
        if not self.gammas:
            return h, [self.i, self.j], np.array([2.0 * dx, 2.0 * dy])
        assert f is not None and jacobian is not None
        grad = np.zeros((h.size, self.n_x))
        grad[:, self.i] = 2.0 * dx
        grad[:, self.j] = 2.0 * dy
        qf = np.zeros(self.n_x)  # Q f, the same for every row
        qf[self.i], qf[self.j] = 2.0 * f[self.i], 2.0 * f[self.j]
        gamma1 = self.gammas[0]
        h1 = grad @ f + gamma1 * h
        grad1 = qf + grad @ jacobian + gamma1 * grad
        if len(self.gammas) == 1:
            return h1, list(range(self.n_x)), grad1.T
        gamma2 = self.gammas[1]
        jf = jacobian @ f
        qjf = np.zeros(self.n_x)
        qjf[self.i], qjf[self.j] = 2.0 * jf[self.i], 2.0 * jf[self.j]
        h2 = grad1 @ f + gamma2 * h1
        grad2 = qjf + gamma1 * qf + (qf + grad1) @ jacobian + gamma2 * grad1
        return h2, list(range(self.n_x)), grad2.T


def _circle_rows(part: _Circles, x: list[float], u: list[float], f_values: np.ndarray,
                 jacobian: np.ndarray, g_rows: list[list[float]], motion: list[float],
                 spread: list[float], alpha: float, n_u: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h (k,), L_g h (k, n_u), right-hand sides (k,)) of one circle family over arrays;
    ``motion`` is x_dot + mean, ``spread`` k_c std (one value per state entry)."""
    h, index, grads = part.terms(x, u, f_values, jacobian)  # grads: (c, k)
    # grad h^T (x_dot + psi) + alpha h, psi_k = mean_k - k_c std_k sign(grad_k):
    # grad_k (x_dot_k + mean_k) - k_c std_k |grad_k| per entry; over the columns that can be
    # nonzero, as three small matrix products (a few numpy calls whatever the row count)
    upper = product(np.array([motion[k] for k in index]), grads)
    upper += alpha * h
    widths = [spread[k] for k in index]
    if any(widths):
        upper -= product(np.array(widths), np.abs(grads))
    lg = product(grads.T, np.array([g_rows[k] for k in index]).reshape(len(index), n_u))
    return h, lg, upper


class VectorAssembly:
    """The filter's per-call constraint assembly for a problem with a large circle family
    (module docstring); build with :meth:`from_problem`. ``evaluate(x, u, mean, std)`` (lists
    of floats) -> :class:`ManyRows`."""

    def __init__(self, problem: RCBFProblem, parts: list[tuple[str, object, int]],
                 small: Callable | None) -> None:
        system = problem.system
        self.n_x, self.n_u = system.n_x, system.n_u
        self._parts = parts
        self._small = small
        self._jet = system.closed_form_source().function()
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self._cascaded = any(isinstance(p, _Circles) and p.gammas for _, p, _ in parts)
        if problem.has_limits:
            self._u_min = [float(v) for v in system.u_min]
            self._u_max = [float(v) for v in system.u_max]
        else:
            self._u_min = self._u_max = None

    @classmethod
    def from_problem(cls, problem: RCBFProblem, *, threshold: int = VECTOR_ROWS
                     ) -> VectorAssembly | None:
        """The vectorised assembly where ``problem`` has a closed form and a circle family of
        at least ``threshold`` obstacles; else None (the generated code serves it whole)."""
        families = _closed_form_families(problem)
        if families is None:
            return None
        n_x = problem.system.n_x
        parts: list[tuple[str, object, int]] = []
        small = []
        for family, (base, gammas) in zip(problem.families, families):
            if type(base) is CircleObstacles and base.count >= threshold:
                parts.append(('circles', _Circles(base, gammas, n_x), base.count))
            else:
                parts.append(('small', None, family.count))
                small.append(family)
        if all(kind == 'small' for kind, _, _ in parts):
            return None
        evaluate = None
        if small:
            sub = dataclasses.replace(problem, families=tuple(small), use_input_limits=False)
            assembly = ClosedFormAssembly.from_problem(sub)
            assert assembly is not None  # the same families have a closed form in problem
            evaluate = assembly.evaluate
        return cls(problem, parts, evaluate)

    def evaluate(self, x: list[float], u: list[float], mean: list[float], std: list[float]
                 ) -> ManyRows:
        """The rows at state x, proposal u (within the limits) and the box mean +/- k_c std."""
        f_values, jacobian, g = self._jet(np.array(x))
        # x_dot + mean, and k_c std: the vertex of the box for a gradient entry of either sign
        motion = (f_values + g @ np.array(u) + np.array(mean)).tolist()
        spread = (self._k_c * np.array(std)).tolist()
        g_rows = g.tolist()
        small = None if self._small is None else self._small(x, u, mean, std)
        hs, lgs, uppers = [], [], []
        start = 0
        for kind, part, count in self._parts:
            if kind == 'small':
                assert small is not None
                hs.append(np.array(small[0][start:start + count]))
                lgs.append(-np.array(small[1][start:start + count])[:, :self.n_u]
                           .reshape(count, self.n_u))
                uppers.append(np.array(small[2][start:start + count]))
                start += count
                continue
            h, lg, upper = _circle_rows(part, x, u, f_values, jacobian,  # type: ignore[arg-type]
                                        g_rows, motion, spread, self._alpha, self.n_u)
            hs.append(h)
            lgs.append(lg)
            uppers.append(upper)
        h = np.concatenate(hs) if len(hs) > 1 else hs[0]
        lg = np.concatenate(lgs) if len(lgs) > 1 else lgs[0]
        upper = np.concatenate(uppers) if len(uppers) > 1 else uppers[0]
        limit_upper: list[float] = []
        if self._u_min is not None:
            limit_upper = ([hi_j - u_j for hi_j, u_j in zip(self._u_max, u)]
                           + [u_j - lo_j for lo_j, u_j in zip(self._u_min, u)])
        flat = lg.ravel()
        size = (float(h @ h) + float(flat @ flat) + float(upper @ upper) + h.size
                + sum(v * v for v in limit_upper) + len(limit_upper))
        return ManyRows(h, lg, upper, limit_upper, size)


class PointRows:
    """Circle rows around points that change with every sensor message, without a rebuild.

    Built once from a one-obstacle circle family (its radius the footprint's radius, its
    margin, look-ahead, indices and cascade gains those of the obstacles); :meth:`set` replaces
    the centres by a message's points (arrays, microseconds), :meth:`evaluate` gives their rows
    at a state as :class:`VectorAssembly` does for a fixed family (module docstring). Point i
    keeps the guarded point at least footprint radius + margin + spread_i from it.
    """

    def __init__(self, problem: RCBFProblem, template: object) -> None:
        """Raises:
            ValueError: naming ``footprint``, where the system or the family has no closed
                form here (a built-in system; a look-ahead without cascades).
        """
        sub = dataclasses.replace(problem, families=(template,), use_input_limits=False)
        families = _closed_form_families(sub)
        if families is None or type(families[0][0]) is not CircleObstacles:
            raise ValueError('footprint: sensor points need a built-in system with a closed '
                             'form and circle rows (a look-ahead point without obstacles.gammas)')
        base, gammas = families[0]
        system = problem.system
        self.n_x, self.n_u = system.n_x, system.n_u
        self._circles = _Circles(base, gammas, self.n_x)
        self.reach = float(base.radii[0]) + float(base.margin)
        """footprint radius + margin (m): the least distance kept from every point."""
        self._jet = system.closed_form_source().function()
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self.set(np.zeros((0, 2)))

    @property
    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(x (N,), y (N,)) of the points."""
        return self._circles.cx, self._circles.cy

    @property
    def count(self) -> int:
        """The points whose rows :meth:`evaluate` gives."""
        return int(self._circles.cx.size)

    def set(self, points: np.ndarray, spread: np.ndarray | float = 0.0) -> None:
        """Replace the points: (N, 2) float64, finite; ``spread`` (N,) or one value >= 0 widens
        each point's circle (a thinned cloud's cell)."""
        circles = self._circles
        circles.cx = points[:, 0].copy()
        circles.cy = points[:, 1].copy()
        delta = self.reach + spread
        circles.delta_sq = delta * delta  # one value for every point, or one per point

    def evaluate(self, x: list[float], u: list[float], mean: list[float], std: list[float]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h (N,), L_g h (N, n_u), right-hand sides (N,)) at state x, proposal u and the box
        mean +/- k_c std, as :class:`ManyRows` holds them."""
        f_values, jacobian, g = self._jet(x)
        # (f + g u) + mean and k_c std, the sums and products of arrays, on a few floats
        motion = [value + m for value, m in zip((f_values + product(g, u)).tolist(), mean)]
        spread = [self._k_c * s for s in std]
        return _circle_rows(self._circles, x, u, f_values, jacobian, g.tolist(), motion,
                            spread, self._alpha, self.n_u)

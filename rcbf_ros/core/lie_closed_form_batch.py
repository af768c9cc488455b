"""Barrier terms of a BATCH of states in closed form (torch, no autograd through barriers).

The learner's differentiable layer needs h, grad h, L_f h and L_g h at the minibatch's states.
They are constants of the QP (the states are data; gradients flow through u_RL only), so the
formulas of :mod:`rcbf_ros.core.lie_closed_form` apply unchanged, evaluated for B states at
once: for a quadratic base barrier h = c + a^T x + 1/2 x^T Q x and the cascades
h1 = L_f h + gamma_1 h, h2 = L_f h1 + gamma_2 h1 (row vectors, J the Jacobian of f),

    grad h  = a + Q x
    grad h1 = Q f + grad h J + gamma_1 grad h
    grad h2 = Q J f + gamma_1 Q f + (Q f + grad h1) J + gamma_2 grad h1

and for a look-ahead circle h = ||p - c||^2 - delta^2, p = (x_i, x_j) + s l_p (cos th, sin th):
grad h = 2 (p - c) on (x_i, x_j) and 2 s l_p (p - c) . (-sin th, cos th) on th, with the
direction-of-travel switch of :func:`rcbf_ros.core.rcbf.barrier_terms`.

J comes from each built-in system's ``drift_jacobian`` (tested against autograd through its
``f``). The closed form applies exactly where
:func:`~rcbf_ros.core.lie_closed_form.has_closed_form` finds one (built-in systems, whose J
does not change along f); elsewhere :meth:`BatchClosedForm.from_problem` returns None and the
caller keeps :meth:`RCBFProblem.terms`. The tests hold both equal to 1e-10.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.dynamics import ControlAffineSystem
from rcbf_ros.core.lie_closed_form import has_closed_form, unwrap_cascades
from rcbf_ros.core.rcbf import BarrierTerms, RCBFProblem
from rcbf_ros.core.torch_import import LazyTorch

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


class _Quadratics:
    """Every quadratic base row, cascaded 0, 1 or 2 times, as stacked coefficients."""

    def __init__(self, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]]):
        self.constant = torch.from_numpy(np.concatenate([r[0] for r in rows]))
        self.linear = torch.from_numpy(np.concatenate([r[1] for r in rows]))
        hessian = np.concatenate([r[2] for r in rows])
        k, n_x = hessian.shape[:2]
        # Q stacked as (n_x, k n_x): one product gives Q x, Q f and Q J f of every row.
        self.hessian_t = torch.from_numpy(np.ascontiguousarray(hessian.reshape(k * n_x, n_x).T))
        gammas = torch.zeros(2, k, dtype=torch.float64)
        depth = torch.zeros(k, dtype=torch.int64)
        start = 0
        for constant, _, _, levels in rows:
            count = constant.size
            for level, gamma in enumerate(levels):
                gammas[level, start:start + count] = gamma
            depth[start:start + count] = len(levels)
            start += count
        self.gamma1, self.gamma2 = gammas[0], gammas[1]
        self.max_depth = int(depth.max())
        # Rows whose top level is below the deepest one (None: every row at the deepest).
        self.below = (None if bool((depth == self.max_depth).all())
                      else [depth == level for level in range(self.max_depth)])

    def __call__(self, x: Tensor, f: Tensor | None, jacobian: Tensor | None
                 ) -> tuple[Tensor, Tensor]:
        """(h (B, k), grad h (B, k, n_x)) at each row's top level."""
        batch, n_x = x.shape
        linear = self.linear
        if self.max_depth == 0:
            qx = (x @ self.hessian_t).reshape(batch, -1, n_x)
            return (self.constant + ((linear + 0.5 * qx) @ x[:, :, None])[..., 0],
                    qx + linear)
        assert f is not None and jacobian is not None
        vectors = [x, f]
        if self.max_depth == 2:
            vectors.append((jacobian @ f[:, :, None])[..., 0])
        products = (torch.cat(vectors) @ self.hessian_t).reshape(len(vectors), batch, -1, n_x)
        qx, qf = products[0], products[1]
        g0 = qx + linear
        h0 = self.constant + ((linear + 0.5 * qx) @ x[:, :, None])[..., 0]
        f_column = f[:, :, None]
        h1 = (g0 @ f_column)[..., 0] + self.gamma1 * h0
        g1 = qf + g0 @ jacobian + self.gamma1[:, None] * g0
        levels_h, levels_g = [h0, h1], [g0, g1]
        if self.max_depth == 2:
            h2 = (g1 @ f_column)[..., 0] + self.gamma2 * h1
            g2 = (products[2] + self.gamma1[:, None] * qf + (qf + g1) @ jacobian
                  + self.gamma2[:, None] * g1)
            levels_h.append(h2)
            levels_g.append(g2)
        h, grad = levels_h[-1], levels_g[-1]
        if self.below is not None:
            for level, rows in enumerate(self.below):
                h = torch.where(rows, levels_h[level], h)
                grad = torch.where(rows[:, None], levels_g[level], grad)
        return h, grad


class _Lookahead:
    """An uncascaded :class:`CircleObstacles` with a look-ahead point (module docstring)."""

    def __init__(self, family: CircleObstacles):
        self.centers = torch.tensor(family.centers, dtype=torch.float64).reshape(-1, 2)
        delta = torch.tensor(family.radii, dtype=torch.float64) + family.margin
        self.delta_sq = delta ** 2
        self.i, self.j = family.position_indices
        assert family.heading_index is not None
        self.heading = family.heading_index
        self.lookahead = float(family.lookahead)
        self.speed = family.speed_input
        # Signed look-ahead distances: the point ahead, and behind (for reversing).
        self.ahead = torch.tensor([[self.lookahead]], dtype=torch.float64)
        self.both = torch.tensor([[self.lookahead], [-self.lookahead]], dtype=torch.float64)

    def _at(self, x: Tensor, offset: Tensor) -> tuple[Tensor, Tensor]:
        """h (S, B, k) and grad h (S, B, k, n_x) at the S look-ahead points offset: (S, 1)."""
        theta = x[:, self.heading]
        cos, sin = torch.cos(theta), torch.sin(theta)
        dx = (x[:, self.i] + offset * cos)[..., None] - self.centers[:, 0]  # (S, B, k)
        dy = (x[:, self.j] + offset * sin)[..., None] - self.centers[:, 1]
        h = dx * dx + dy * dy - self.delta_sq
        grad = torch.zeros(*h.shape, x.shape[1], dtype=x.dtype, device=x.device)
        grad[..., self.i] += 2.0 * dx
        grad[..., self.j] += 2.0 * dy
        grad[..., self.heading] += (2.0 * offset[..., None]) * (dy * cos[:, None]
                                                               - dx * sin[:, None])
        return h, grad

    def __call__(self, x: Tensor, u: Tensor | None) -> tuple[Tensor, Tensor]:
        if self.speed is None or u is None:
            h, grad = self._at(x, self.ahead)
            return h[0], grad[0]
        # Both points in one pass; behind where reversing and every circle is clear of it.
        h, grad = self._at(x, self.both)
        use = (u.detach()[:, self.speed] < 0) & (h[1] >= 0).all(dim=1)
        return (torch.where(use[:, None], h[1], h[0]),
                torch.where(use[:, None, None], grad[1], grad[0]))


class BatchClosedForm:
    """:meth:`RCBFProblem.terms` for a batch of states in closed form; build with
    :meth:`from_problem`."""

    def __init__(self, system: ControlAffineSystem, quadratics: _Quadratics | None,
                 lookahead: list[_Lookahead], order: Tensor | None) -> None:
        self._system = system
        self._quadratics = quadratics
        self._lookahead = lookahead
        self._order = order

    @classmethod
    def from_problem(cls, problem: RCBFProblem) -> BatchClosedForm | None:
        """The closed form of ``problem``'s terms, or None where it has none
        (:func:`~rcbf_ros.core.lie_closed_form.has_closed_form`)."""
        if not has_closed_form(problem):
            return None
        n_x = problem.system.n_x
        quadratic, lookahead = [], []
        quadratic_rows: list[np.ndarray] = []
        lookahead_rows: list[np.ndarray] = []
        start = 0
        for family in problem.families:
            base, levels = unwrap_cascades(family)
            gammas = [float(level.gamma) for level in levels]
            rows = np.arange(start, start + base.count)
            start += base.count
            if type(base) is CircleObstacles and base.has_lookahead:
                lookahead.append(_Lookahead(base))
                lookahead_rows.append(rows)
                continue
            coefficients = base.quadratic_rows(n_x)
            quadratic.append((coefficients.constant, coefficients.linear,
                              coefficients.hessian, gammas))
            quadratic_rows.append(rows)
        position = np.concatenate(quadratic_rows + lookahead_rows)
        order = (None if np.array_equal(position, np.arange(start))
                 else torch.from_numpy(np.argsort(position)))
        return cls(problem.system, _Quadratics(quadratic) if quadratic else None, lookahead,
                   order)

    def terms(self, x: Tensor, u_rl: Tensor | None = None) -> BarrierTerms:
        """Barrier terms at x: (B, n_x) float64, as :meth:`RCBFProblem.terms` (detached)."""
        x = x.detach()
        system = self._system
        f = system.f(x)
        parts = []
        if self._quadratics is not None:
            jacobian = (system.drift_jacobian(x) if self._quadratics.max_depth > 0
                        else None)
            parts.append(self._quadratics(x, f, jacobian))
        parts += [family(x, u_rl) for family in self._lookahead]
        if len(parts) == 1:
            h, grad = parts[0]
        else:
            h = torch.cat([p[0] for p in parts], dim=1)
            grad = torch.cat([p[1] for p in parts], dim=1)
            if self._order is not None:
                h, grad = h[:, self._order], grad[:, self._order]
        return BarrierTerms(h, grad, torch.einsum('bkn,bn->bk', grad, f),
                            torch.einsum('bkn,bnm->bkm', grad, system.g(x)))

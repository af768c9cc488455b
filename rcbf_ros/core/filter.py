"""Per-step RCBF safety filter: OSQP set up once, ``update()`` + warm-started solve per call.

Given a state x, a proposal u_RL and (optionally) a disturbance box mean +/- k_c std, returns
u* = u_RL + u_S with u_S from the RCBF-QP built by :meth:`RCBFProblem.qp` (the same builder the
learner's differentiable layer uses). The sparsity pattern of the constraint matrix is fixed at
construction (dense RCBF rows, one entry per actuator-limit row) so that every call is
``OSQP.update(Ax=, u=)`` + ``solve()``.

Failure policy (never raises on a solve): when OSQP does not report ``solved`` (or
``solved inaccurate``), or its answer is not finite, the filter returns the *fail-safe action*
(configurable; default all zeros, clipped to the actuator limits) with ``fail_safe=True`` and the
solver status in ``status``. Bad *inputs* (wrong length, NaN/inf, negative std) are the caller's
bug and raise ``ValueError`` naming the field; the ROS node turns those into the fail-safe too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable, Sequence

import numpy as np
import osqp
import scipy.sparse as sp
import torch

from rcbf_ros.core.diffqp import solve_qp_batch_full
from rcbf_ros.core.qp import cost_weights
from rcbf_ros.core.rcbf import RCBFProblem

_OK_STATUS = {1: 'solved', 2: 'solved_inaccurate'}
ACTIVE_TOLERANCE = 1e-7
"""|u_S| above this counts as the filter acting."""


@dataclass(frozen=True)
class FilterResult:
    """Outcome of one :meth:`SafetyFilter.filter` call (all arrays float64 numpy)."""

    u_safe: np.ndarray
    """(n_u,) the action to apply: u_RL + u_S, or the fail-safe action."""
    u_s: np.ndarray
    """(n_u,) the correction u_S (u_safe - u_RL)."""
    slack: float
    """eps of the QP (> 0: a barrier row could not be met within the limits)."""
    h: np.ndarray
    """(K,) barrier values h_i(x) (top level of each cascade)."""
    constraint_values: np.ndarray
    """(K,) L_f h + L_g h u_safe + alpha h + rho per barrier: >= 0 means the RCBF row holds
    without slack at the returned action."""
    status: str
    """'solved', 'solved_inaccurate', 'solved_interior_point' (OSQP stalled, the fallback
    solved it), or the OSQP status that triggered the fail-safe."""
    solve_time_s: float
    """Wall time of OSQP update + solve."""
    total_time_s: float
    """Wall time of the whole call (constraint assembly included)."""
    fail_safe: bool
    """True when u_safe is the fail-safe action."""
    barrier_names: list[str] = field(default_factory=list)
    """K names in row order."""

    @property
    def active(self) -> bool:
        """Whether the filter changed the proposal by more than the solver's tolerance (1e-7;
        an inactive QP can return |u_S| ~ 1e-12 depending on the warm start)."""
        return bool(np.any(np.abs(self.u_s) > ACTIVE_TOLERANCE)) or self.fail_safe


def _vector(name: str, value: object, size: int) -> np.ndarray:
    """Validate a 1-D float input; raise ValueError naming the field."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: not a numeric vector ({exc})') from exc
    if array.shape != (size,):
        raise ValueError(f'{name}: expected {size} values, got {array.size}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name}: contains NaN or inf')
    return array


Assembly = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
                   tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
"""(x, u_rl, mean, std), each (1, .) float64 -> (h (1, K), G (1, nc, nz), h_qp (1, nc))."""


def eager_assembly(problem: RCBFProblem) -> Assembly:
    """The filter's per-call constraint assembly: barrier terms, then the QP rows."""

    def assemble(x: torch.Tensor, u: torch.Tensor, mean: torch.Tensor,
                 std: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        terms = problem.terms(x, u)
        qp = problem.qp(x, u, mean, std, terms=terms)
        return terms.h, qp.G, qp.h

    return assemble


def _inductor_compile(graph: torch.fx.GraphModule, example: tuple[torch.Tensor, ...]
                      ) -> Assembly:
    """Compile an already flat aten graph with TorchInductor.

    ``make_fx`` has done what TorchDynamo would (capture), so the graph goes to Inductor
    directly: no frame evaluation or guard checks on every call. Measured per call, warm / with
    the caches flushed: 29 / 138 us this way, 54 / 357 us through ``torch.compile``
    (unicycle, measured when this was chosen). Inductor's entry point is not public API, so
    any failure there falls back to ``torch.compile``.
    """
    try:
        from torch._inductor.compile_fx import compile_fx
        return compile_fx(graph, list(example))
    except Exception:  # noqa: BLE001 - private API moved or refused: the public route works
        return torch.compile(graph, dynamic=False, fullgraph=True)


def compiled_assembly(problem: RCBFProblem, *, checks: int = 8, seed: int = 0) -> Assembly:
    """:func:`eager_assembly` for one state, traced into one flat graph and compiled.

    ``make_fx`` records every aten op the eager computation runs, the autograd passes of the
    cascades included, into one flat graph; TorchInductor turns that into one kernel. The
    trace specialises Python-level control flow to the example inputs, so a system or barrier
    that branches in Python on tensor *values* would be compiled wrongly: the result is
    compared with the eager one on ``checks`` random inputs, raising ValueError naming
    ``compile_assembly`` on a mismatch (``torch.where``-style branching is fine).
    """
    from torch.fx.experimental.proxy_tensor import make_fx

    eager = eager_assembly(problem)
    n_x, n_u = problem.system.n_x, problem.system.n_u
    generator = torch.Generator().manual_seed(seed)

    def sample(scale: float = 1.0) -> tuple[torch.Tensor, ...]:
        x, mean, std = (scale * torch.rand(1, n, generator=generator, dtype=torch.float64)
                        + 0.1 for n in (n_x, n_x, n_x))
        # signed proposals: the direction of travel picks a barrier's look-ahead point
        u = scale * (2.0 * torch.rand(1, n_u, generator=generator, dtype=torch.float64) - 1.0)
        return x, u, mean, std

    example = sample(0.5)
    try:
        graph = make_fx(eager)(*example)
    except RuntimeError as exc:  # make_fx refuses to read tensor values (data-dependent flow)
        raise ValueError(f'compile_assembly: cannot trace the constraint assembly ({exc}); '
                         'use compile_assembly: false') from exc
    compiled = _inductor_compile(graph, example)
    for _ in range(checks):
        inputs = sample(2.0)
        for got, want in zip(compiled(*inputs), eager(*inputs)):
            if not torch.allclose(got, want, rtol=1e-9, atol=1e-9, equal_nan=True):
                raise ValueError('compile_assembly: the compiled constraint assembly differs '
                                 'from the eager one (value-dependent Python control flow in '
                                 'the system or a barrier?); use compile_assembly: false')
    return compiled


OSQP_EPS = 1e-9
"""Default OSQP absolute and relative tolerance, of this class and of the safety_filter node
(one value, so the node and the in-process trainer take the same actions)."""
OSQP_MAX_ITER = 4000
"""Default OSQP iteration cap (the node's ``osqp.max_iter``)."""


class SafetyFilter:
    """RCBF-QP safety filter for one :class:`RCBFProblem` (see module docstring)."""

    def __init__(self, problem: RCBFProblem, *, fail_safe_action: Sequence[float] | None = None,
                 eps_abs: float = OSQP_EPS, eps_rel: float = OSQP_EPS,
                 max_iter: int = OSQP_MAX_ITER,
                 polish: bool = False, fallback: bool = True,
                 compile_assembly: bool = False) -> None:
        """Set OSQP up once with the fixed sparsity pattern.

        Args:
            problem: system, barriers and gains.
            fail_safe_action: n_u values applied when the solve fails (default zeros), clipped
                to the actuator limits.
            eps_abs: OSQP absolute tolerance.
            eps_rel: OSQP relative tolerance.
            max_iter: OSQP iteration cap.
            polish: OSQP solution polishing (off by default: at these tolerances the answer
                already matches an interior-point reference to < 1e-6, see
                benchmarks/bench_filter_step.py, and OSQP prints a notice on every call whose
                active set is empty).
            fallback: when OSQP does not converge, solve the same QP with the batched interior
                point of :mod:`rcbf_ros.core.diffqp` (status ``solved_interior_point``) before
                resorting to the fail-safe action.
            compile_assembly: trace the constraint assembly (autograd through the cascades
                included) into one flat graph and compile it (see :func:`compiled_assembly`):
                several times faster per call for cascaded barriers, at a one-off compile of
                seconds to tens of seconds at construction.
        """
        self.fallback = fallback
        self._assemble = (compiled_assembly(problem) if compile_assembly
                          else eager_assembly(problem))
        self.problem = problem
        system = problem.system
        self.n_x, self.n_u = system.n_x, system.n_u
        self.n_barriers = problem.n_barriers
        self.barrier_names = problem.barrier_names
        nz, nc = self.n_u + 1, problem.n_constraints
        if problem.has_limits:
            self._u_min = np.asarray(system.u_min, dtype=np.float64)
            self._u_max = np.asarray(system.u_max, dtype=np.float64)
        else:
            self._u_min = np.full(self.n_u, -np.inf)
            self._u_max = np.full(self.n_u, np.inf)
        action = np.zeros(self.n_u) if fail_safe_action is None else _vector(
            'fail_safe_action', fail_safe_action, self.n_u)
        self.fail_safe_action = np.clip(action, self._u_min, self._u_max)

        # Fixed pattern: RCBF rows are dense in (u_S, eps); limit rows hold one entry each.
        pattern = np.zeros((nc, nz), dtype=bool)
        pattern[:self.n_barriers, :] = True
        for j in range(self.n_u if problem.has_limits else 0):
            pattern[self.n_barriers + j, j] = True
            pattern[self.n_barriers + self.n_u + j, j] = True
        cols, rows = np.nonzero(pattern.T)  # column-major = CSC order
        self._rows, self._cols = rows, cols
        a_matrix = sp.csc_matrix((np.ones(rows.size), (rows, cols)), shape=(nc, nz))
        a_matrix.sort_indices()
        diag = 2.0 * np.asarray(cost_weights(self.n_u, problem.slack_weight,
                                             problem.input_weight))
        self._solver = osqp.OSQP()
        self._solver.setup(P=sp.csc_matrix(np.diag(diag)), q=np.zeros(nz), A=a_matrix,
                           l=np.full(nc, -np.inf), u=np.ones(nc), verbose=False, polishing=polish,
                           eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter,
                           warm_starting=True)
        self._nc = nc

    def filter(self, state: Sequence[float], u_rl: Sequence[float],
               mean: Sequence[float] | None = None,
               std: Sequence[float] | None = None) -> FilterResult:
        """Make u_rl safe at state under the disturbance box mean +/- k_c std.

        Args:
            state: n_x values.
            u_rl: n_u proposed values.
            mean: n_x disturbance mean (None: zero).
            std: n_x disturbance std >= 0 (None: zero).

        Raises:
            ValueError: naming the field, for a wrong length, NaN/inf, or negative std.
        """
        start = time.perf_counter()
        x = _vector('state', state, self.n_x)
        u = _vector('u_rl', u_rl, self.n_u)
        mu = None if mean is None else _vector('disturbance_mean', mean, self.n_x)
        sd = None if std is None else _vector('disturbance_std', std, self.n_x)
        if sd is not None and np.any(sd < 0):
            raise ValueError('disturbance_std: must be >= 0')

        mu = np.zeros(self.n_x) if mu is None else mu
        sd = np.zeros(self.n_x) if sd is None else sd
        h_t, g_t, upper_t = self._assemble(*(torch.from_numpy(a).unsqueeze(0)
                                             for a in (x, u, mu, sd)))
        g_matrix = g_t[0].numpy()
        upper = upper_t[0].numpy()
        h_values = h_t[0].numpy()

        solve_start = time.perf_counter()
        if np.all(upper >= 0.0):
            # z = 0 is feasible, hence optimal (the objective's minimum): the proposal passes
            # through exactly, without a solve.
            ok, z, status = True, np.zeros(self.n_u + 1), 'solved'
        else:
            self._solver.update(Ax=g_matrix[self._rows, self._cols], u=upper)
            result = self._solver.solve(raise_error=False)
            status_val = int(result.info.status_val)
            z = None if result.x is None else np.asarray(result.x, dtype=np.float64)
            ok = status_val in _OK_STATUS and z is not None and bool(np.all(np.isfinite(z)))
            status = _OK_STATUS.get(status_val, str(result.info.status))
            if not ok and self.fallback:
                # ADMM can stall when the slack is far from 0 (the 1 : l diagonal); the
                # interior point of the differentiable layer solves the same QP robustly.
                solution = solve_qp_batch_full(*self.problem.qp(
                    *(torch.from_numpy(a).unsqueeze(0) for a in (x, u, mu, sd))))
                if bool(solution.converged[0]):
                    z = solution.z[0].detach().numpy()
                    ok = bool(np.all(np.isfinite(z)))
                    status = 'solved_interior_point'
        solve_time = time.perf_counter() - solve_start

        if ok:
            u_safe = np.clip(u + z[:self.n_u], self._u_min, self._u_max)
            slack = float(z[-1])
        else:
            u_safe = self.fail_safe_action.copy()
            slack = float('nan')
        # RCBF row at the applied action without slack: rhs + L_g h (u_safe - u_rl) >= 0.
        lg_h = -g_matrix[:self.n_barriers, :self.n_u]
        residual = upper[:self.n_barriers] + lg_h @ (u_safe - u)
        return FilterResult(
            u_safe=u_safe, u_s=u_safe - u, slack=slack, h=h_values,
            constraint_values=residual, status=status, solve_time_s=solve_time,
            total_time_s=time.perf_counter() - start, fail_safe=not ok,
            barrier_names=list(self.barrier_names))

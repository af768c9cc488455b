"""Per-step RCBF safety filter: an exact small active-set solve per call, OSQP as its fallback.

Given a state, a proposal u_RL and (optionally) a disturbance box, returns u* = u_RL + u_S with
u_S from the RCBF-QP of ``RCBFProblem.qp`` (the builder the learner's differentiable layer
uses). Every answer is checked against the rows themselves: the result is within the actuator
limits and meets every row within ``slack_tolerance``, or it is the fail-safe action with the
reason. A call works on Python floats and generated straight-line code, because on a few dozen
values a numpy call costs more than the work it does.

The invariant and how each input is treated: docs/SAFETY_FILTER.md#the-core-filter.
Design notes (the solve steps, the assembly paths): docs/DESIGN.md#the-per-step-filter
"""
from __future__ import annotations

from dataclasses import dataclass, field
import functools
from itertools import chain
import math
import operator
import time
from types import SimpleNamespace
from typing import Callable, NamedTuple, Sequence, TYPE_CHECKING

import numpy as np

from rcbf_ros.core.filter_info import PointValues
from rcbf_ros.core.lie_closed_form import ClosedFormAssembly, RowAssembly
from rcbf_ros.core.lie_closed_form_rows import (
    ManyRows,
    PointRows,
    product,
    VECTOR_ROWS,
    VectorAssembly,
)
from rcbf_ros.core.qp import cost_weights
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import (
    IntervalMargin,
    least_per_row,
    sampled_data_margin,
    SampledDataMargin,
    split_rows,
)
from rcbf_ros.core.torch_import import bind_torch, LazyTorch
from rcbf_ros.parameters.reader import setting

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    import osqp

_OK_STATUS = {1: 'solved', 2: 'solved_inaccurate'}
ACTIVE_TOLERANCE = 1e-7
"""|u_S| above this counts as the filter acting."""
QP_DATA_LIMIT = 1e15
"""Largest |value| of the assembled QP data (rows and right-hand sides) the filter passes to the
solver. OSQP refuses data beyond about 1e30 and keeps the previous problem; far below that,
float64 rows lose the absolute precision the row check needs. Larger data: ``input_refused``."""
_QP_DATA_SQUARES = 0.5 * QP_DATA_LIMIT ** 2
"""A sum of squares of the QP data at most this has every |value| below :data:`QP_DATA_LIMIT`
(by a factor of 0.7, far beyond the sum's rounding): the one-sum data check (the assembly
returns the sum); data that fails it goes through the exact one."""
LIMIT_TOLERANCE = 1e-9
"""How far past an actuator limit the solver's answer may land before it is projected back (a
solve at tolerance 1e-9 ends there); farther is a failed check."""


@dataclass(frozen=True)
class InputBounds:
    """Magnitude bounds on the filter's inputs: anything larger is refused (fail-safe).

    Finite but absurd values (a proposal of 1e10, a learned std of 1e300) are not a command or
    an estimate anyone meant; they also push the QP data past what the solver takes. A bound
    itself is at most :data:`QP_DATA_LIMIT`: an input beyond it could never be filtered."""

    state: float = setting(1e6, positive=True, maximum=QP_DATA_LIMIT,
                           description='largest |x_i| of a state; beyond: fail-safe')
    """Largest |x_i| of the state."""
    command: float = setting(
        1e6, positive=True, maximum=QP_DATA_LIMIT,
        description='largest |u_i| of a proposal (below it, a proposal outside the limits is '
                    'clipped); beyond: fail-safe')
    """Largest |u_i| of the proposal (below it, a proposal outside the limits is clipped)."""
    disturbance: float = setting(
        1e6, positive=True, maximum=QP_DATA_LIMIT,
        description='largest |mean_i| and std_i of the disturbance box; beyond: fail-safe')
    """Largest |mean_i| and std_i of the disturbance box."""

    def __post_init__(self) -> None:
        for name in ('state', 'command', 'disturbance'):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float))
                                               and math.isfinite(value) and value > 0):
                raise ValueError(f'input_bounds.{name}: must be a finite number > 0, '
                                 f'got {value!r}')


@dataclass(frozen=True)
class FilterResult:
    """Outcome of one :meth:`SafetyFilter.filter` call (all arrays float64 numpy)."""

    u_safe: np.ndarray
    """(n_u,) the action to apply: u_RL + u_S, or the fail-safe action."""
    u_s: np.ndarray
    """(n_u,) the correction u_S (u_safe - u_RL, u_RL as proposed, before clipping)."""
    slack: float
    """eps of the QP (> 0: a barrier row could not be met within the limits); NaN when not
    solved."""
    h: np.ndarray
    """(K,) barrier values h_i(x) (top level of each cascade); NaN when refused."""
    constraint_values: np.ndarray
    """(K,) L_f h + L_g h u_safe + alpha h + rho per barrier, at the proposal's rows: >= 0
    means the RCBF row holds without slack at the returned action."""
    status: str
    """'solved', 'solved_inaccurate', 'solved_interior_point' (the fallback solved it), or why
    the fail-safe was returned: 'input_refused', 'unverified', 'slack_exceeded'."""
    solve_time_s: float
    """Wall time of the solve (the active-set method, OSQP update + solve, the fallback, as
    far as the call went) and the row check."""
    total_time_s: float
    """Wall time of the whole call (constraint assembly included)."""
    fail_safe: bool
    """True when u_safe is the fail-safe action."""
    barrier_names: list[str] = field(default_factory=list)
    """K names in row order."""
    needed_slack: float = 0.0
    """max(0, -min constraint_values): the slack the returned action needs in the rows,
    evaluated from the rows (not the solver's eps); NaN when refused."""
    reason: str = ''
    """Why the fail-safe was returned ('' otherwise)."""
    proposal_clipped: bool = False
    """Whether the proposal lay outside the actuator limits and was clipped before the QP."""
    points: PointValues | None = None
    """Every sensor point's row (a filter with a footprint whose rows were evaluated), else
    None; :func:`rcbf_ros.core.filter_info.binding_points` picks those closest to binding."""

    @classmethod
    def _filled(cls, *, u_safe: np.ndarray, u_s: np.ndarray, slack: float, h: np.ndarray,
                constraint_values: np.ndarray, status: str, solve_time_s: float,
                total_time_s: float, fail_safe: bool, barrier_names: list[str],
                needed_slack: float, reason: str, proposal_clipped: bool,
                points: PointValues | None) -> FilterResult:
        """The result with every field given, as ``FilterResult(...)`` builds it.

        The filter's per-call constructor: the ``__init__`` a frozen dataclass generates sets
        each field through ``object.__setattr__`` (about 3 us for these 14 fields, a tenth of
        a pass-through call); this fills the instance's ``__dict__`` in one update. Every field
        is a required keyword, so none can be left out."""
        result = object.__new__(cls)
        result.__dict__.update(
            u_safe=u_safe, u_s=u_s, slack=slack, h=h, constraint_values=constraint_values,
            status=status, solve_time_s=solve_time_s, total_time_s=total_time_s,
            fail_safe=fail_safe, barrier_names=barrier_names, needed_slack=needed_slack,
            reason=reason, proposal_clipped=proposal_clipped, points=points)
        return result

    @property
    def active(self) -> bool:
        """Whether the filter changed the proposal by more than the solver's tolerance (1e-7;
        an inactive QP can return |u_S| ~ 1e-12 depending on the warm start)."""
        return bool(np.any(np.abs(self.u_s) > ACTIVE_TOLERANCE)) or self.fail_safe


_FLOAT64 = np.dtype(np.float64)
_least, _largest = np.minimum.reduce, np.maximum.reduce
"""An array's least and largest value (its ``min`` and ``max`` without the method's wrapper)."""
ACTIVE_SET_TOLERANCE = 1e-12
"""How far (relative to the largest right-hand side) the active-set solution may exceed a row
or limit, or miss the equality of an active one, and still count as meeting it: round-off only,
far below OSQP's eps."""
ROW_SPREAD = 1e3
"""Where the rows' scales 1 + |upper_i| spread by more than this factor, the active-set solve
meets each RCBF row to :data:`ACTIVE_SET_TOLERANCE` of its own scale (:func:`_each_row_own`),
not of the largest: a far row's right-hand side (1e12) must not loosen the others."""
ACTIVE_SET_STEPS = 40
"""Most steps (a row added or dropped) of :func:`active_set_solution` before it gives up (a
degenerate or cycling case in floating point; then OSQP solves the QP). The filter's QPs take
one to four."""
STATIONARITY_TOLERANCE = 1e-12
"""How large the stationarity residual |y + sum_i lambda_i row_i| of the active-set solution may
be, relative to the terms summed (sum_i lambda_i |row_i|): round-off only."""
DEPENDENT_ROW = 1e-20
"""A row whose part orthogonal to the active rows has a squared norm below this fraction of its
own counts as their linear combination (an angle below 1e-10 rad)."""

def _dot(left: Sequence[float], right: Sequence[float]) -> float:
    """The inner product of two short sequences of floats."""
    return sum(map(operator.mul, left, right))


def _solve_small(matrix: list[list[float]], rhs: list[float]) -> list[float] | None:
    """x with matrix x = rhs on a few Python floats (cheaper than a numpy call for the
    filter's systems of 1 to 3 unknowns): directly for one unknown, else Gaussian elimination
    with partial pivoting; None when a pivot is zero or not finite (singular)."""
    n = len(rhs)
    if n == 1:
        pivot = matrix[0][0]
        return [rhs[0] / pivot] if 0.0 < abs(pivot) < math.inf else None
    if n == 2:  # Cramer's rule
        (a, b), (c, d) = matrix
        determinant = a * d - b * c
        if not 0.0 < abs(determinant) < math.inf:
            return None
        return [(d * rhs[0] - b * rhs[1]) / determinant, (a * rhs[1] - c * rhs[0]) / determinant]
    work = [row[:] + [value] for row, value in zip(matrix, rhs)]
    for col in range(n):
        pivot = max(range(col, n), key=lambda i: abs(work[i][col]))
        head = work[pivot]
        if not 0.0 < abs(head[col]) < math.inf:
            return None
        work[col], work[pivot] = head, work[col]
        for i in range(col + 1, n):
            row = work[i]
            factor = row[col] / head[col]
            if factor:
                for k in range(col, n + 1):
                    row[k] -= factor * head[k]
    solution = [0.0] * n
    for i in range(n - 1, -1, -1):
        row = work[i]
        solution[i] = (row[n] - _dot(row[i + 1:n], solution[i + 1:])) / row[i]
    return solution


def _gram(basis: list[list[float]]) -> list[list[float]]:
    """The Gram matrix of a few rows (each inner product computed once)."""
    if len(basis) == 1:
        (a,) = basis
        return [[_dot(a, a)]]
    if len(basis) == 2:
        a, b = basis
        ab = _dot(a, b)
        return [[_dot(a, a), ab], [ab, _dot(b, b)]]
    gram = [[0.0] * len(basis) for _ in basis]
    for i, a in enumerate(basis):
        for j in range(i, len(basis)):
            gram[i][j] = gram[j][i] = _dot(a, basis[j])
    return gram


def _on_rows(basis: list[list[float]], rhs: list[float], tolerance: float
             ) -> tuple[list[float], list[float]] | None:
    """The least |y| with basis y = rhs and its multipliers lambda (y = -sum_i lambda_i
    basis_i), if the rows hold to ``tolerance``, every lambda_i >= 0 and stationarity holds
    to round-off; else None.

    lambda comes from the Gram system of the rows, y = -sum_i lambda_i basis_i from lambda
    (stationarity by construction). y sums terms far larger than itself when a costly slack
    makes the multipliers large; where it then misses the rows by more than ``tolerance``,
    one step of iterative refinement (on lambda, and y with it) puts it back, and
    stationarity, |y + sum_i lambda_i basis_i| evaluated, must then be at most
    :data:`STATIONARITY_TOLERANCE` of the terms summed. Two rows (the filter's common case)
    are written out, the same sums, as far as no refinement is needed."""
    if len(basis) == 2:
        a, b = basis
        ra, rb = rhs
        aa, ab, bb = _dot(a, a), _dot(a, b), _dot(b, b)
        determinant = aa * bb - ab * ab  # Cramer's rule, as _solve_small
        if not 0.0 < abs(determinant) < math.inf:
            return None
        l0 = (bb * -ra - ab * -rb) / determinant
        l1 = (aa * -rb - ab * -ra) / determinant
        y = [-(l0 * p + l1 * q) for p, q in zip(a, b)]
        if abs(_dot(a, y) - ra) <= tolerance and abs(_dot(b, y) - rb) <= tolerance:
            return (y, [l0, l1]) if l0 >= 0.0 and l1 >= 0.0 else None
    gram = _gram(basis)
    multipliers = _solve_small(gram, [-value for value in rhs])
    if multipliers is None:
        return None
    columns = list(zip(*basis))
    y = [-_dot(multipliers, column) for column in columns]
    residual = [_dot(a, y) - value for a, value in zip(basis, rhs)]
    if not max(map(abs, residual)) <= tolerance:
        correction = _solve_small(gram, residual)
        if correction is None:
            return None
        multipliers = [value + delta for value, delta in zip(multipliers, correction)]
        y = [value - _dot(correction, column) for value, column in zip(y, columns)]
        residual = [_dot(a, y) - value for a, value in zip(basis, rhs)]
        if not max(map(abs, residual)) <= tolerance:
            return None
        stationarity = [value + _dot(multipliers, column) for value, column in zip(y, columns)]
        terms = 1.0 + sum(value * max(map(abs, a)) for value, a in zip(multipliers, basis))
        if not max(map(abs, stationarity)) <= STATIONARITY_TOLERANCE * terms:
            return None
    if not min(multipliers) >= 0.0:
        return None
    return y, multipliers


def _as_floats(value: Sequence) -> list:
    """``value`` as a list (of floats, or of sequences of floats): an array's ``tolist()``, a
    list as it is (the method does not change it)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value if isinstance(value, list) else list(value)


Kernels = tuple[Callable[[Sequence[float]], float],
                Callable[[list[list[float]], list[float], Sequence[float]], list[float]],
                Callable[[list[list[float]], list[float]], tuple[int, float] | None]]
"""(row -> row^T P^-1 row, (rows, upper, z) -> [row^T z - upper for each row],
(rows, upper) -> (the violated row farthest from z = 0 in distance, -1 for none, and its
row^T P^-1 row), None for a violated row of zeros)."""


def _kernels(p_inverse: list[float]) -> Kernels:
    """The inner loops of :func:`active_set_solution` for P^-1 = diag(p_inverse)
    (:data:`Kernels`), written out for the filter's two and three unknowns (the same sums as
    :func:`_dot`)."""
    if len(p_inverse) == 3:
        w0, w1, w2 = p_inverse

        def norm(row: Sequence[float]) -> float:
            a, b, c = row
            return a * a * w0 + b * b * w1 + c * c * w2

        def excess(rows: list[list[float]], upper: list[float], z: Sequence[float]
                   ) -> list[float]:
            z0, z1, z2 = z
            return [a * z0 + b * z1 + c * z2 - value for (a, b, c), value in zip(rows, upper)]
    elif len(p_inverse) == 2:
        w0, w1 = p_inverse

        def norm(row: Sequence[float]) -> float:
            a, b = row
            return a * a * w0 + b * b * w1

        def excess(rows: list[list[float]], upper: list[float], z: Sequence[float]
                   ) -> list[float]:
            z0, z1 = z
            return [a * z0 + b * z1 - value for (a, b), value in zip(rows, upper)]
    else:
        def norm(row: Sequence[float]) -> float:
            return sum([r * r * w for r, w in zip(row, p_inverse)])

        def excess(rows: list[list[float]], upper: list[float], z: Sequence[float]
                   ) -> list[float]:
            return [_dot(row, z) - value for row, value in zip(rows, upper)]

    def farthest(rows: list[list[float]], upper: list[float]) -> tuple[int, float] | None:
        # only a violated row (upper < 0) can be farthest; the first of equals is taken
        p, distance, norm_p = -1, 0.0, 0.0
        for i, value in enumerate(upper):
            if value < 0.0:
                squared = norm(rows[i])
                if not squared > 0.0:
                    return None  # a violated row of zeros (or NaN): no step meets it
                ratio = value / math.sqrt(squared)
                if ratio < distance:
                    p, distance, norm_p = i, ratio, squared
        return p, norm_p

    return norm, excess, farthest


def active_set_solution(*, rows: Sequence[Sequence[float]], upper: Sequence[float],
                        p_inverse: Sequence[float], tolerance: float,
                        max_steps: int = ACTIVE_SET_STEPS) -> list[float] | None:
    """The exact solution of min 1/2 z^T P z s.t. rows z <= upper, P = diag(1 / p_inverse),
    with its KKT certificate, on Python floats.

    In y = P^1/2 z the QP is min 1/2 |y|^2 s.t. (rows P^-1/2) y <= upper: the projection of 0
    onto the rows' polyhedron. A dual active-set method (Goldfarb and Idnani's, with the
    identity as the Hessian) solves it: from the unconstrained minimum y = 0, the row
    violated most (in distance) joins the working set W; where the step that meets it would
    turn a multiplier of W negative, that row leaves first. Every step raises the dual
    objective, so no working set repeats: the method ends after finitely many steps, with
    W's rows linearly independent (at most len(y) of them). After each row joins, y and the
    multipliers are recomputed from W alone (:func:`_on_rows`), so no round-off accumulates
    over the steps.

    The first two steps are written out, for the filter's QPs (one or two rows active in
    most calls). The first: the row p farthest from z = 0 (in distance) alone, z on it, with
    multiplier -upper_p / (row_p^T P^-1 row_p) > 0. Where another row is still violated, the
    row q violated most there joins, and W = {p, q} is tried on its certificate (q alone is
    no answer but in a tie: every point that meets p is at least p's distance from 0, q's own
    point no farther; p can leave W only once more rows join). Only where it does not answer do
    the steps go on as above, from W = {p}. Each scan for the row violated most evaluates
    row^T z - upper for every row and the distance only for the rows it exceeds.

    The answer comes with the certificate that makes it the QP's one solution (whichever
    steps found it): every multiplier >= 0 and stationarity to round-off (:func:`_on_rows`),
    every row met to ``tolerance`` (the last scan) and W's rows held to it. Otherwise None
    (the caller solves the QP another way): where y = 0 already meets every row to
    ``tolerance`` (not this method's case), past ``max_steps``, for a singular Gram system,
    for rows that admit no step (inconsistent, or a violated row of zeros), for a NaN, or for
    a failed certificate (round-off in nearly dependent rows).

    Args:
        rows: m rows of n floats, the constraint matrix (lists or an (m, n) array).
        upper: (m,) the right-hand sides.
        p_inverse: (n,) the diagonal of P^-1, every entry > 0.
        tolerance: how far a row may be exceeded (or an active one missed), absolute.
        max_steps: most rows added or dropped.

    Returns:
        z (n floats), or None.
    """
    rows, upper, p_inverse = _as_floats(rows), _as_floats(upper), _as_floats(p_inverse)
    return _active_set_steps(rows, upper, p_inverse, tolerance, max_steps, _kernels(p_inverse))


def _each_row_own(rows: list[list[float]], upper: list[float], k: int,
                  largest: float | None = None
                  ) -> tuple[list[list[float]], list[float], float]:
    """(rows, upper, tolerance) for :func:`_active_set_steps` that meet each of the first
    ``k`` rows (the RCBF rows) to :data:`ACTIVE_SET_TOLERANCE` (1 + |upper_i|) and the rest
    (the limit rows, which the kernels read as +/- e_j, never scaled) to that of the largest
    of theirs.

    Within :data:`ROW_SPREAD` the rows as they are and the tolerance of the largest scale (the
    common case: nothing is scaled). Beyond, RCBF row i and its right-hand side are multiplied
    by c_i = base / (1 + |upper_i|) (base: the limit rows' largest scale, 1 without limits):
    the same constraint, so the same polyhedron and solution, whose excess c_i (row_i^T z -
    upper_i) <= tolerance * base says row_i^T z - upper_i <= tolerance (1 + |upper_i|). The
    multipliers scale by 1 / c_i and stay >= 0; the distances the method compares do not
    change. ``largest``: 1 + max |upper_i|, where the caller has it."""
    if largest is None:
        largest = 1.0 + max(map(abs, upper), default=0.0)
    if not (largest > ROW_SPREAD  # (the least scale is 1: no spread below; NaN: as it is)
            and largest > ROW_SPREAD * (1.0 + min(map(abs, upper), default=0.0))):
        return rows, upper, ACTIVE_SET_TOLERANCE * largest
    scales = [1.0 + abs(value) for value in upper]
    base = max(scales[k:], default=1.0)
    factors = [base / scale for scale in scales[:k]]
    scaled = [[c * value for value in row] for c, row in zip(factors, rows)]
    return (scaled + rows[k:], [c * value for c, value in zip(factors, upper)] + upper[k:],
            ACTIVE_SET_TOLERANCE * base)


def _each_row_own_steps(rows: list[list[float]], upper: list[float], k: int,
                        p_inverse: list[float],
                        kernels_of: Callable[[list[list[float]], list[float]], Kernels],
                        largest: float | None = None) -> list[float] | None:
    """:func:`_active_set_steps` on the rows met each to its own scale
    (:func:`_each_row_own`); where they were scaled and that certificate fails (the round-off
    of a row of large gradient can exceed 1e-12 of its right-hand side), on the rows as they
    are to the largest scale's tolerance: the row check, each row to its own scale, then
    judges that answer (OSQP, the next resort, is least sure of such rows). ``kernels_of``:
    the kernels for the rows and right-hand sides a try solves."""
    if largest is None:
        largest = 1.0 + max(map(abs, upper), default=0.0)
    scaled, bounds, tolerance = _each_row_own(rows, upper, k, largest)
    z = _active_set_steps(scaled, bounds, p_inverse, tolerance, ACTIVE_SET_STEPS,
                          kernels_of(scaled, bounds))
    if z is None and scaled is not rows:
        z = _active_set_steps(rows, upper, p_inverse, ACTIVE_SET_TOLERANCE * largest,
                              ACTIVE_SET_STEPS, kernels_of(rows, upper))
    return z


def _active_set_steps(rows: list[list[float]], upper: list[float], p_inverse: list[float],
                      tolerance: float, max_steps: int, kernels: Kernels
                      ) -> list[float] | None:
    """:func:`active_set_solution` on lists, with the :func:`_kernels` of ``p_inverse``."""
    norm, excess_of, farthest = kernels
    # The first step: the row farthest from z = 0 (in distance) alone.
    found = farthest(rows, upper)
    if found is None:
        return None  # a violated row of zeros (or NaN): no step meets it
    p, norm_p = found
    if p < 0 or not upper[p] < -tolerance:
        return None  # z = 0 meets every row to the tolerance: not this method's case
    multiplier = -upper[p] / norm_p
    first = [w * r * -multiplier for w, r in zip(p_inverse, rows[p])]
    excess = excess_of(rows, upper, first)
    if not abs(excess[p]) <= tolerance:
        return None
    excess[p] = -math.inf
    if max(excess) <= tolerance and sum(excess) == -math.inf:  # (a NaN makes the sum NaN)
        return first
    # The further steps in y = P^1/2 z.
    scale = [math.sqrt(w) for w in p_inverse]
    scaled: dict[int, list[float]] = {}
    lengths: dict[int, float] = {p: math.sqrt(norm_p)}

    def scaled_row(i: int) -> list[float]:
        row = scaled.get(i)
        if row is None:
            row = scaled[i] = [r * s for r, s in zip(rows[i], scale)]
        return row

    def violated_most(excess: list[float]) -> int | None:
        """The row violated most (in distance), -1 where every row is met, None for a NaN."""
        p, best = -1, 0.0
        for i, value in enumerate(excess):
            if not value <= tolerance:
                if value != value:
                    return None
                length = lengths.get(i)
                if length is None:
                    length = lengths[i] = math.sqrt(norm(rows[i]))
                score = (value - tolerance) / length
                if score > best:
                    p, best = i, score
        return p

    def certified(working: list[int]) -> tuple[list[float], list[float], list[float]] | None:
        """(y, multipliers, the rows' excess) on W = ``working``, if _on_rows certifies it."""
        solved = _on_rows([scaled_row(j) for j in working], [upper[j] for j in working],
                          tolerance)
        if solved is None:
            return None
        y, multipliers = solved
        excess = excess_of(rows, upper, [s * value for s, value in zip(scale, y)])
        for j in working:
            excess[j] = -math.inf
        return y, multipliers, excess

    q = violated_most(excess)
    if q is None:
        return None
    if max_steps >= 2:  # the second step, written out: q joins
        found = certified([p, q])
        if found is not None and max(found[2]) <= tolerance and sum(found[2]) == -math.inf:
            return [s * value for s, value in zip(scale, found[0])]
    y = [value / s for value, s in zip(first, scale)]
    active, multipliers = [p], [multiplier]
    steps = 1
    while True:
        p = violated_most(excess)
        if p is None:
            return None
        if p < 0:  # every row met
            break
        row_p = scaled_row(p)
        while True:  # add row p, dropping rows of W whose multiplier would turn negative
            steps += 1
            if steps > max_steps:
                return None
            basis = [scaled_row(j) for j in active]
            # ratios: row p's coordinates on W's rows; direction: its part orthogonal to them
            ratios = _solve_small(_gram(basis), [_dot(a, row_p) for a in basis]
                                  ) if basis else []
            if ratios is None:
                return None
            direction = row_p
            for ratio, row in zip(ratios, basis):
                direction = [d - ratio * r for d, r in zip(direction, row)]
            dual_step, drop = math.inf, -1
            for k, (multiplier, ratio) in enumerate(zip(multipliers, ratios)):
                if ratio > 0.0 and multiplier < dual_step * ratio:
                    dual_step, drop = multiplier / ratio, k
            squared = _dot(direction, direction)
            primal_step = math.inf
            if squared > DEPENDENT_ROW * lengths[p] ** 2:
                primal_step = (_dot(row_p, y) - upper[p]) / squared
                if not primal_step >= 0.0:
                    return None
            step = min(primal_step, dual_step)
            if step == math.inf:
                return None  # row p contradicts W's rows: the QP has no solution
            if primal_step < math.inf:
                y = [value - step * d for value, d in zip(y, direction)]
            multipliers = [value - step * ratio for value, ratio in zip(multipliers, ratios)]
            if primal_step <= dual_step:
                active.append(p)
                break
            del active[drop], multipliers[drop]
        found = certified(active)
        if found is None:
            return None
        y, multipliers, excess = found
    # W's rows held to the tolerance (_on_rows), every other row met (the last scan)
    return [s * value for s, value in zip(scale, y)]


def _vector(name: str, value: object, size: int) -> np.ndarray:
    """A 1-D float64 array of ``value`` with ``size`` entries; raise ValueError naming the field
    for a wrong length or non-numeric data.

    A float64 array of that shape is used as it is (the filter neither changes nor keeps its
    inputs); anything else is converted into a new array."""
    if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == (size,):
        return value
    try:
        array = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f'{name}: not a numeric vector ({exc})') from exc
    if array.shape != (size,):
        raise ValueError(f'{name}: expected {size} values, got {array.size}')
    return array


def _floats(name: str, value: object, size: int) -> list[float]:
    """The ``size`` values of ``value`` as a new list of Python floats (as :func:`_vector`
    converts them; the same ValueError for a wrong length or non-numeric data)."""
    if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == (size,):
        return value.tolist()
    if type(value) is list and len(value) == size and all(type(v) is float for v in value):
        return value[:]  # Python floats already: what the conversion would give
    return _vector(name, value, size).tolist()


def _out_of_bounds(name: str, values: list[float], bound: float) -> str | None:
    """Why ``values`` is refused (not finite, or beyond +/- ``bound``), or None."""
    if not all(map(math.isfinite, values)):
        return f'{name}: contains NaN or inf'
    worst = max(map(abs, values), default=0.0)
    if worst > bound:
        return f'{name}: |value| {worst:.3g} beyond the bound {bound:.3g}'
    return None


def _interior_point(problem: RCBFProblem, inputs: tuple[list[float], ...],
                    rows: tuple[np.ndarray, np.ndarray, list[float]] | None = None
                    ) -> np.ndarray | None:
    """The fallback's solution of the QP at ``inputs`` (x, u, mean, std), by the batched
    interior point of :mod:`rcbf_ros.core.diffqp`; ``rows`` (lg (M, n_u), upper (M,), the
    limit rows' right-hand sides) replace its RCBF rows (the rows tightened by sampled-data
    margins, :func:`~rcbf_ros.core.sampled_data.split_rows`). None when it did not converge,
    or where PyTorch, which it runs on, is not installed (the filter then gives the
    fail-safe)."""
    try:
        from rcbf_ros.core.diffqp import solve_qp_batch_full
    except ImportError:
        return None
    qp = problem.qp(*(torch.tensor([a], dtype=torch.float64) for a in inputs))
    if rows is not None:
        lg, upper, limit_upper = rows
        n_u = lg.shape[1]
        unit = np.eye(n_u, n_u + 1)
        rcbf_rows = np.concatenate([-lg, np.full((upper.size, 1), -1.0)], axis=1)
        g_matrix = np.concatenate([rcbf_rows] + ([unit, -unit] if limit_upper else []))
        qp = qp._replace(G=torch.tensor(g_matrix[None], dtype=qp.G.dtype),
                         h=torch.tensor(np.concatenate([upper, limit_upper])[None],
                                        dtype=qp.h.dtype))
    solution = solve_qp_batch_full(*qp)
    if not bool(solution.converged[0]):
        return None
    return solution.z[0].detach().numpy().astype(np.float64)


def _input_refusal(x: list[float], u: list[float], mean: list[float], std: list[float],
                   bounds: InputBounds) -> str | None:
    """The filter's input checks one by one, in order: the reason naming the first field that
    fails, or None."""
    for name, values, bound in (('state', x, bounds.state), ('u_rl', u, bounds.command),
                                ('disturbance_mean', mean, bounds.disturbance),
                                ('disturbance_std', std, bounds.disturbance)):
        reason = _out_of_bounds(name, values, bound)
        if reason is not None:
            return reason
    if min(std, default=0.0) < 0.0:
        return 'disturbance_std: must be >= 0'
    return None


def _data_refusal(h: list[float], rows: list[list[float]], upper: list[float]) -> str | None:
    """Why the QP data is refused (a value not finite or beyond :data:`QP_DATA_LIMIT`, in
    order: the barrier values, the rows, their right-hand sides), or None."""
    for name, values in (('barrier values', h), ('constraint rows', chain.from_iterable(rows)),
                         ('constraint bounds', upper)):
        if not all(abs(value) <= QP_DATA_LIMIT for value in values):
            return f'{name}: not finite or beyond {QP_DATA_LIMIT:.0e} at this input'
    return None


RowValues = Callable[[list[float], list[list[float]], Sequence[float]], list[float]]
"""(upper (K), rows (K), step (n_u)) -> [upper_i - row_i[:n_u]^T step for each RCBF row]: the
row values L_f h + L_g h u + alpha h + rho at u = u_rows + step (the rows hold -L_g h in their
first n_u entries)."""


class _ShapeKernels(NamedTuple):
    """The filter's per-call loops over a few values, generated for its shape (n_x, n_u, K,
    the limits) at construction by :func:`_shape_kernels`."""

    solve: Kernels
    """For :func:`_active_set_steps`: the norm, row^T z - upper over every row, the violated
    row farthest from z = 0."""
    row_values: RowValues
    """The RCBF rows' values at a step of the action."""
    within_bounds: Callable[..., bool]
    """(x, u, mean, std, state, command, disturbance bound) -> whether every value is finite
    and within its bound and every std >= 0: exactly what the field-by-field checks accept."""
    clip: Callable[[list[float]], list[float]]
    """u -> u clipped to the actuator limits (a new list)."""
    act: Callable[[list[float], list[float]], tuple[list[float], list[float]] | None]
    """(u, z) -> (the action u + z[:n_u] projected onto the limits, its step from u), or None
    where u + z[:n_u] lies beyond a limit by more than :data:`LIMIT_TOLERANCE`."""


def _shape_kernels(p_inverse: list[float], n_x: int, n_barriers: int,
                   limits: list[tuple[float, float]] | None) -> _ShapeKernels:
    """The filter's per-call loops as straight-line Python (a fraction of the time of loops
    and builtin calls on a few dozen values): the active-set method's scans over the rows (K
    RCBF rows, then, with limits, [e_j, 0] z <= . and [-e_j, 0] z <= ., their zeros and ones
    folded in; the same sums as :func:`_kernels`, whose norm is taken), the RCBF rows' values
    at a step of the
    action (:data:`RowValues`), the input bounds as one chained comparison per value (NaN
    fails every comparison), the clip and the action of a solution (the row check's
    projection onto the limits), the limits folded in. ``limits``: (low, high) per input, or
    None (no limits: no clip, no projection). ``n_barriers`` 0: no row functions (the
    many-row path takes :func:`_kernels` and evaluates its rows over arrays)."""
    n_u = len(p_inverse) - 1
    nz, k = n_u + 1, n_barriers
    z = [f'z{j}' for j in range(nz)]
    rows = ['(' + ', '.join(f'r{i}_{j}' for j in range(nz)) + ')' for i in range(k)]
    limit_rows = [f'_{j}' for j in range(2 * n_u)] if limits else []
    upper = [f'v{i}' for i in range(k + len(limit_rows))]
    excess = [' + '.join(f'r{i}_{j}*{z[j]}' for j in range(nz)) + f' - v{i}' for i in range(k)]
    if limits:
        excess += [f'z{j} - v{k + j}' for j in range(n_u)]
        excess += [f'-z{j} - v{k + n_u + j}' for j in range(n_u)]
    values = [f'v{i} - (' + ' + '.join(f'r{i}_{j}*d{j}' for j in range(n_u)) + ')'
              for i in range(k)]
    norms = [' + '.join(f'r{i}_{j}*r{i}_{j}*{w!r}' for j, w in enumerate(p_inverse))
             for i in range(k)]
    if limits:  # a limit row's norm: its one entry's weight
        norms += [repr(float(p_inverse[j])) for j in range(n_u)] * 2
    farthest = []
    for i, norm in enumerate(norms):
        farthest += [f'    if v{i} < 0.0:',
                     f'        squared = {norm}',
                     '        if not squared > 0.0:',
                     '            return None',
                     f'        ratio = v{i} / sqrt(squared)',
                     '        if ratio < distance:',
                     f'            p, distance, norm_p = {i}, ratio, squared']
    x, u = [f'x{i}' for i in range(n_x)], [f'u{j}' for j in range(n_u)]
    m, sd = [f'm{i}' for i in range(n_x)], [f's{i}' for i in range(n_x)]
    bounded = ([f'-state <= {v} <= state' for v in x] + [f'-command <= {v} <= command' for v in u]
               + [f'-box <= {v} <= box' for v in m] + [f'0.0 <= {v} <= box' for v in sd])
    clipped = ([f'{low!r} if {v} < {low!r} else {high!r} if {v} > {high!r} else {v}'
                for v, (low, high) in zip(u, limits)] if limits else u)
    act = []
    for j, (low, high) in enumerate(limits or []):
        act += [f'    a{j} = u{j} + z{j}',
                f'    if a{j} < {low - LIMIT_TOLERANCE!r} or a{j} > {high + LIMIT_TOLERANCE!r}:',
                '        return None',
                f'    a{j} = {low!r} if a{j} < {low!r} else {high!r} if a{j} > {high!r} else a{j}']
    if not limits:
        act += [f'    a{j} = u{j} + z{j}' for j in range(n_u)]
    row_source = [
        'def excess(rows, upper, z):',
        f'    {", ".join(z)}, = z',
        f'    {", ".join(rows + limit_rows)}, = rows',
        f'    {", ".join(upper)}, = upper',
        f'    return [{", ".join(excess)}]',
        'def farthest(rows, upper):',
        f'    {", ".join(rows + limit_rows)}, = rows',
        f'    {", ".join(upper)}, = upper',
        '    p, distance, norm_p = -1, 0.0, 0.0',
        *farthest,
        '    return p, norm_p',
        'def row_values(upper, rows, step):',
        f'    {", ".join(f"d{j}" for j in range(n_u))}, = step',
        f'    {", ".join(rows)}, = rows',
        f'    {", ".join(upper[:k])}, = upper',
        f'    return [{", ".join(values)}]'] if k else []
    source = '\n'.join([
        *row_source,
        'def within_bounds(x, u, mean, std, state, command, box):',
        *(f'    {", ".join(names)}, = {arg}'
          for names, arg in ((x, 'x'), (u, 'u'), (m, 'mean'), (sd, 'std'))),
        f'    return {" and ".join(bounded)}',
        'def clip(u):',
        f'    {", ".join(u)}, = u',
        f'    return [{", ".join(clipped)}]',
        'def act(applied, z):',
        f'    {", ".join(u)}, = applied',
        f'    {", ".join(z)}, = z',
        *act,
        f'    return [{", ".join(f"a{j}" for j in range(n_u))}], '
        f'[{", ".join(f"a{j} - u{j}" for j in range(n_u))}]', ''])
    namespace: dict = {'inf': math.inf, 'sqrt': math.sqrt}
    exec(compile(source, '<filter rows>', 'exec'), namespace)  # noqa: S102 - own source
    solve = (_kernels(p_inverse) if not k else
             (_kernels(p_inverse)[0], namespace['excess'], namespace['farthest']))
    return _ShapeKernels(solve, namespace.get('row_values', _no_rows), namespace['within_bounds'],
                         namespace['clip'], namespace['act'])


def _no_rows(upper: list[float], rows: list[list[float]], step: Sequence[float]) -> list[float]:
    """The row values of a filter whose rows are not generated (:data:`RowValues`; the
    many-row path evaluates them over arrays)."""
    raise AssertionError('row values of the many-row path are evaluated over arrays')


Assembly = Callable[['torch.Tensor', 'torch.Tensor', 'torch.Tensor', 'torch.Tensor'],
                   'tuple[torch.Tensor, torch.Tensor, torch.Tensor]']
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


def _on_lists(assembly: Assembly) -> RowAssembly:
    """A torch assembly of one state with the filter's lists in and out
    (:data:`RowAssembly`)."""

    def assemble(x: list[float], u: list[float], mean: list[float], std: list[float]
                 ) -> tuple[list[float], list[list[float]], list[float], float]:
        h, g_matrix, upper = (a[0] for a in assembly(*(torch.tensor([a], dtype=torch.float64)
                                                       for a in (x, u, mean, std))))
        size = sum(float(v.square().sum()) for v in (h, g_matrix, upper))
        return h.tolist(), g_matrix.tolist(), upper.tolist(), size

    return assemble


PRUNE_MARGIN = 1e-9
"""How far (relative to 1 + the largest |right-hand side|) a row's least value over the input
box must lie above 0 for the many-row path to leave it out of its QP: round-off of that least
value is below 1e-15 of it, so a row left out holds at every action within the limits."""


def binding_rows(*, lg: np.ndarray, upper: np.ndarray, applied: Sequence[float],
                 u_min: Sequence[float] | None, u_max: Sequence[float] | None,
                 margin: float) -> np.ndarray:
    """The indices of the RCBF rows that can bind: those some action within the input box
    could violate.

    Row i at an action a is v_i(a) = upper_i + lg_i^T (a - applied) >= 0 (``upper`` written at
    the proposal ``applied``, which lies in the box). Its least value over the box
    [u_min, u_max] is attained at a vertex, coordinate-wise, in closed form:

        min_a v_i(a) = upper_i + lg_i^T (mid - applied) - |lg_i|^T half,

    mid and half the box's centre and half-widths. A row whose least value is at least
    ``margin`` holds at every action the QP can return (its limit rows are hard, so u_S keeps
    the action in the box, and its slack eps >= 0 at the optimum: a negative eps only costs and
    tightens), so the QP without it has the same solution: the full QP's feasible set lies in
    the smaller one's, and the smaller one's solution meets the full set. Without limits no row
    is left out. A violated row (upper_i < 0) is always kept: its least value is at most
    upper_i. ``upper`` is the rows' as the QP takes them, sampled-data margins included
    (:mod:`rcbf_ros.core.sampled_data`): a row left out holds with its margin. A row tightened
    by the margin of its command, nu0 + c^T |u|, is concave in the action and comes here as its
    split rows (:func:`~rcbf_ros.core.sampled_data.split_rows`), each linear, the row the least
    of them: each split row is kept or left out by the argument above, so the tightened row's
    least value over the box (a concave function's least over a box lies at a vertex) is the
    least of its split rows', and a split row left out holds at every action the QP can
    return, as the row it belongs to does where all of its split rows are left out.

    Args:
        lg: (K, n_u) L_g h of each row.
        upper: (K,) the right-hand sides at ``applied``.
        applied: (n_u,) the proposal the rows are written at, within the limits.
        u_min: (n_u,) lower limits, or None (no limits).
        u_max: (n_u,) upper limits, or None.
        margin: how far above 0 a row's least value must be to be left out.

    Returns:
        (k,) int indices into the rows, ascending.
    """
    if u_min is None or u_max is None:
        return np.arange(upper.size)
    # the box less the proposal on floats (the same differences as over arrays, fewer calls)
    applied = [float(value) for value in applied]
    least = _least_over_box(lg, [float(low) - a for low, a in zip(u_min, applied)],
                            [float(high) - a for high, a in zip(u_max, applied)])
    least += upper
    return (~(least >= margin)).nonzero()[0]  # flatnonzero's, without its ravel


EXACT_ROWS = 256
"""The most rows that can bind the exact solve of the many-row path takes as they are; more
(a cloud's points along a corridor) are merged by :func:`merged_rows` into at most this many
rows that imply every one of them, unless :meth:`SafetyFilter._generated` finds the exact
answer within this many. The exact solve runs in Python over its rows, a few steps of about
a microsecond a row each: 83k rows took 0.1-0.5 s a decision, 256 keep it near a millisecond
(benchmarks/bench_sources.py, the corridor)."""
GENERATED_BATCH = 32
"""The rows the exact solve of many rows starts with, and adds per round
(:meth:`SafetyFilter._generated`)."""
ARRAY_EXCESS_ROWS = 64
"""From this many rows on, the exact solve of the many-row path takes row^T z - upper over its
rows as arrays (:func:`_excess_over`): a few numpy calls instead of a Python step a row."""


def _excess_over(columns: np.ndarray, upper: np.ndarray) -> Callable[..., list[float]]:
    """The ``excess`` kernel of :func:`_kernels` for two or three unknowns over one QP's rows
    held as arrays: ``columns`` (n, m) the rows' entries by column, ``upper`` (m,) their
    right-hand sides. It takes THESE rows whatever it is handed (the same rows as lists, which
    the other kernels read). The same list bit for bit: each row's a z0 + b z1 (+ c z2) -
    upper in that order, as elementwise IEEE operations."""
    first, *rest = columns

    def excess(rows: object, upper_list: object, z: Sequence[float]) -> list[float]:
        total = first * z[0]
        for column, value in zip(rest, z[1:]):
            total += column * value
        total -= upper
        return total.tolist()

    return excess


def _least_over_box(lg: np.ndarray, low: Sequence[float], high: Sequence[float]
                    ) -> np.ndarray:
    """(K,) the least lg_i^T d over the box low <= d <= high (one column at a time: faster
    than a reduction over a short last axis; summed from the first column's, the values of
    a sum from 0)."""
    if not lg.shape[1]:
        return np.zeros(lg.shape[0])
    column = lg[:, 0]
    out = np.minimum(column * low[0], column * high[0])
    for j in range(1, lg.shape[1]):
        column = lg[:, j]
        out += np.minimum(column * low[j], column * high[j])
    return out


def merged_rows(*, lg: np.ndarray, upper: np.ndarray, applied: Sequence[float],
                u_min: Sequence[float], u_max: Sequence[float], count: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``count`` rows, each below the rows it stands for at every action of the box:
    an action within the box that meets them (with a slack eps) meets every row (with eps).

    Row i at an action a is v_i(a) = upper_i + lg_i^T d, d = a - applied in [dl, dh] = [u_min -
    applied, u_max - applied] (:func:`binding_rows`). Half of ``count`` goes to the rows of
    least value over the box, taken as they are; the others are binned on a grid over lg (k
    cells a coordinate, k^n_u <= the rest of ``count``), and a cell with centre c gives the row

        upper_c + c^T d,  upper_c = min over its rows of upper_i + sum_j min(e_ij dl_j,
        e_ij dh_j),  e_i = lg_i - c,

    so that v_i(a) >= upper_c + c^T d for every a in the box (the sum is the least e_i^T d
    over the box). The cost: a cell's row is lower than its rows by up to sum_j |e_ij|
    max(-dl_j, dh_j), at most half a cell's width per coordinate times the box: more
    conservative commands where many rows bind at once, never a row left unmet.

    Args:
        lg: (K, n_u) L_g h of each row.
        upper: (K,) the right-hand sides at ``applied``.
        applied: (n_u,) the proposal the rows are written at, within the limits.
        u_min, u_max: (n_u,) finite limits.
        count: the most rows returned, 2 to 32,767.

    Returns:
        (lg (k, n_u), upper (k,)) of the k <= ``count`` rows.
    """
    if upper.size <= count:
        return lg, upper
    applied = np.asarray(applied, dtype=np.float64)
    low = np.asarray(u_min, dtype=np.float64) - applied
    high = np.asarray(u_max, dtype=np.float64) - applied
    least = upper + _least_over_box(lg, low, high)
    exact = count // 2
    order = np.argpartition(least, exact)
    first, rest = order[:exact], order[exact:]
    rest_lg, rest_upper = lg[rest], upper[rest]
    n_u = lg.shape[1]
    bins = 1
    while (bins + 1) ** n_u <= count - exact:
        bins += 1
    bottom, top = rest_lg.min(axis=0), rest_lg.max(axis=0)
    width = (top - bottom) / bins
    width[~(width > 0.0)] = 1.0  # one value along that coordinate: one cell
    cells = np.clip(np.floor((rest_lg - bottom) / width), 0, bins - 1).astype(np.int64)
    centre = bottom + (cells + 0.5) * width
    error = rest_lg - centre
    worst = rest_upper + _least_over_box(error, low, high)
    keys = np.ravel_multi_index(tuple(cells.T), (bins,) * n_u).astype(np.int16)
    by_cell = np.argsort(keys, kind='stable')  # a radix sort of at most `count` keys
    keys = keys[by_cell]
    starts = np.flatnonzero(np.concatenate(([True], keys[1:] != keys[:-1])))
    cell_upper = np.minimum.reduceat(worst[by_cell], starts)
    cell_lg = centre[by_cell[starts]]
    return (np.concatenate([lg[first], cell_lg]),
            np.concatenate([upper[first], cell_upper]))


POINTS_BARRIER = 'sensor_points'
"""The barrier name of the sensor points' rows in a result (one entry for all of them)."""


def _solve_once(g_rows: list[list[float]], upper: list[float], p_inverse: np.ndarray
                ) -> tuple[np.ndarray | None, str]:
    """OSQP on G z <= upper with the cost diag(1 / p_inverse), set up for one call:
    (z or None, the solver's status)."""
    import osqp
    import scipy.sparse as sp
    a_matrix = sp.csc_matrix(np.array(g_rows, dtype=np.float64).reshape(len(g_rows), -1))
    solver = osqp.OSQP()
    solver.setup(P=sp.csc_matrix(np.diag(1.0 / p_inverse)), q=np.zeros(p_inverse.size),
                 A=a_matrix, l=np.full(len(upper), -np.inf), u=np.array(upper, dtype=np.float64),
                 verbose=False, polishing=True, eps_abs=OSQP_EPS, eps_rel=OSQP_EPS,
                 max_iter=OSQP_MAX_ITER)
    result = solver.solve(raise_error=False)
    status_val = int(result.info.status_val)
    z = None if result.x is None else np.asarray(result.x, dtype=np.float64)
    return (z if status_val in _OK_STATUS else None), _OK_STATUS.get(
        status_val, str(result.info.status))


GENERATED_ROWS = 1024
"""The most RCBF rows for which the filter generates its per-call loops as code per row
(``_shape_kernels``, several lines a row); a problem with more takes the many-row path
whatever its assembly (e.g. many circles on a system without a closed form)."""


def _all_finite(values: np.ndarray) -> bool:
    """Whether every entry of ``values`` (float64) is finite: their sum of squares is (one
    BLAS call; NaN and inf carry into it), else each entry is checked (the sum also overflows
    for finite entries beyond about 1e154)."""
    flat = values.ravel(order='K')  # a view in either memory order
    return math.isfinite(flat.dot(flat)) or bool(np.isfinite(flat).all())


def _meets_every_row(upper: np.ndarray, least_point: float, limit_upper: list[float]
                     ) -> bool:
    """Whether every right-hand side is >= 0 (z = 0 meets every row): the problem's, the
    points' (``least_point`` their least, inf for none) and the limits' (an empty part meets
    it; a NaN fails it)."""
    return ((not upper.size or _least(upper) >= 0.0) and least_point >= 0.0
            and (not limit_upper or min(limit_upper) >= 0.0))


def _as_they_are(values: np.ndarray) -> np.ndarray:
    """``values`` per row where no row is split (:func:`least_per_row` where they are)."""
    return values


class _RowsAsArrays:
    """A :data:`RowAssembly` (lists) with the many-row path's :class:`ManyRows` out, for a
    problem of more than :data:`GENERATED_ROWS` rows without rows over arrays (a system or
    family without a closed form)."""

    def __init__(self, assemble: RowAssembly, n_barriers: int, n_u: int) -> None:
        self._assemble, self._k, self.n_u = assemble, n_barriers, n_u

    def evaluate(self, x: list[float], u: list[float], mean: list[float], std: list[float]
                 ) -> ManyRows:
        h, rows, upper, size = self._assemble(x, u, mean, std)
        k = self._k
        g_rows = np.array(rows[:k], dtype=np.float64).reshape(k, self.n_u + 1)  # k may be 0
        return ManyRows(np.array(h, dtype=np.float64), -g_rows[:, :self.n_u],
                        np.array(upper[:k], dtype=np.float64), list(upper[k:]), size)


def _many_as_lists(many: VectorAssembly) -> RowAssembly:
    """The many-row assembly with the lists of :data:`RowAssembly` (for the checks that take
    every row: :meth:`SafetyFilter.evaluation_refusal`)."""
    n_u = many.n_u
    unit = np.eye(n_u, n_u + 1)
    limit_rows = (np.concatenate((unit, -unit)) + 0.0).tolist()

    def assemble(x: list[float], u: list[float], mean: list[float], std: list[float]
                 ) -> tuple[list[float], list[list[float]], list[float], float]:
        rows = many.evaluate(x, u, mean, std)
        g_rows = np.concatenate([-rows.lg, np.full((rows.h.size, 1), -1.0)], axis=1).tolist()
        if rows.limit_upper:
            g_rows += limit_rows
        return rows.h.tolist(), g_rows, rows.upper.tolist() + rows.limit_upper, rows.size

    return assemble


def _tightened(assemble: RowAssembly, margin: SampledDataMargin | IntervalMargin,
               n_barriers: int) -> RowAssembly:
    """``assemble`` with the right-hand side of each of its ``n_barriers`` RCBF rows lowered by
    its constant sampled-data margin nu_i = nu0_i + c_i^T U (:mod:`rcbf_ros.core.sampled_data`,
    the largest over the commands within the limits): the lists
    :meth:`SafetyFilter.evaluation_refusal` checks (finite exactly where the command-linear
    margin is). The limit rows are unchanged; the sum of squares follows."""

    def assemble_tightened(x: list[float], u: list[float], mean: list[float],
                           std: list[float]
                           ) -> tuple[list[float], list[list[float]], list[float], float]:
        h, rows, upper, size = assemble(x, u, mean, std)
        nu = margin.rows(x, mean, std).tolist()
        before = upper[:n_barriers]
        after = [value - pad for value, pad in zip(before, nu)]
        size += sum(v * v for v in after) - sum(v * v for v in before)
        return h, rows, after + upper[n_barriers:], size

    return assemble_tightened


def select_assembly(problem: RCBFProblem, *, compile_assembly: bool = False,
                    closed_form: bool = True) -> tuple[str, RowAssembly]:
    """The filter's constraint assembly and its name.

    ``closed_form`` where the problem has one (:meth:`ClosedFormAssembly.from_problem` decides)
    and ``closed_form`` is on: the fastest, with nothing to compile. Otherwise the autograd
    assembly, ``compiled`` with ``compile_assembly``, else ``autograd``.

    Raises:
        ImportError: the autograd assembly without torch installed (one line saying how to
            install it, :data:`rcbf_ros.core.torch_import.INSTALL_HINT`).
    """
    fast = ClosedFormAssembly.from_problem(problem) if closed_form else None
    if fast is not None:
        return 'closed_form', fast.evaluate
    bind_torch()  # now, so that a filter that needs torch and has none is refused when built
    if compile_assembly:
        return 'compiled', _on_lists(compiled_assembly(problem))
    return 'autograd', _on_lists(eager_assembly(problem))


class _DirectOSQP:
    """An OSQP problem's per-call data path on the extension object ``osqp.OSQP`` wraps.

    The same C calls with the same arguments as ``OSQP.update(Ax=, u=)``, ``solve()`` and
    ``warm_start()``, without the wrapper's per-call bookkeeping (a derivative cache and an info
    namespace built by reflection), which took longer than the update itself. Skipped with it:
    the clamp of ``u`` to +/- OSQP_INFTY (1e30), a no-op for data within
    :data:`QP_DATA_LIMIT`, which the filter checks before every update."""

    def __init__(self, solver: osqp.OSQP) -> None:
        self._ext = solver._solver

    @staticmethod
    def wrap(solver: osqp.OSQP) -> osqp.OSQP | _DirectOSQP:
        """The direct path where the installed osqp has it, else ``solver`` itself."""
        ext = getattr(solver, '_solver', None)
        needed = ('update_data_vec', 'update_data_mat', 'solve', 'warm_start', 'info',
                  'solution')
        return _DirectOSQP(solver) if all(hasattr(ext, n) for n in needed) else solver

    def update(self, *, Ax: np.ndarray, u: np.ndarray) -> None:
        """New values of A's fixed pattern and of the upper bounds."""
        self._ext.update_data_vec(q=None, l=None, u=u)
        self._ext.update_data_mat(P_x=None, P_i=None, A_x=Ax, A_i=None)

    def solve(self, raise_error: bool = False) -> SimpleNamespace:
        """Solve; ``x`` is a copy of the iterate, ``info`` OSQP's (status_val, status, ...)."""
        del raise_error  # never raises: the status is checked by the caller
        self._ext.solve()
        return SimpleNamespace(x=np.array(self._ext.solution.x, dtype=np.float64),
                               info=self._ext.info)

    def warm_start(self, x: np.ndarray | None = None, y: np.ndarray | None = None) -> None:
        """Start the next solve from (x, y)."""
        self._ext.warm_start(x, y)


OSQP_EPS = 1e-9
"""Default OSQP absolute and relative tolerance, of this class and of the safety_filter node
(one value, so the node and the in-process trainer take the same actions)."""
OSQP_MAX_ITER = 4000
"""Default OSQP iteration cap (the node's ``osqp.max_iter``)."""
OSQP_INT_MAX = 2 ** 31 - 1
"""The largest integer setting OSQP takes (its ``OSQPInt`` is 32 bits in the osqp wheels)."""


class SafetyFilter:
    """RCBF-QP safety filter for one :class:`RCBFProblem` (see module docstring)."""

    def __init__(self, problem: RCBFProblem, *, fail_safe_action: Sequence[float] | None = None,
                 eps_abs: float = OSQP_EPS, eps_rel: float = OSQP_EPS,
                 max_iter: int = OSQP_MAX_ITER,
                 polish: bool = False, fallback: bool = True,
                 compile_assembly: bool = False, slack_tolerance: float | None = None,
                 input_bounds: InputBounds | None = None, closed_form: bool = True,
                 vector_rows: int = VECTOR_ROWS, footprint: object | None = None,
                 control_period_s: float = 0.0, latency_s: float = 0.0) -> None:
        """Set OSQP up once with the fixed sparsity pattern.

        Args:
            problem: system, barriers and gains.
            fail_safe_action: n_u values applied when the filter cannot filter (default
                zeros); must lie within the actuator limits.
            eps_abs: OSQP absolute tolerance.
            eps_rel: OSQP relative tolerance.
            max_iter: OSQP iteration cap.
            polish: OSQP solution polishing (off by default: at these tolerances the answer
                already matches an interior-point reference to < 1e-6, see
                benchmarks/bench_filter_step.py, and OSQP prints a notice on every call whose
                active set is empty).
            fallback: when OSQP does not converge or its answer fails the row check, solve the
                same QP with the batched interior point of :mod:`rcbf_ros.core.diffqp` (status
                ``solved_interior_point``) before resorting to the fail-safe action.
            compile_assembly: where the autograd assembly is used (a system or barrier family
                without a closed form, or ``closed_form=False``), trace it (autograd through
                the cascades included) into one flat graph and compile it (see
                :func:`compiled_assembly`): several times faster per call for cascaded
                barriers, at a one-off compile of seconds to tens of seconds at construction.
                No effect where the closed form is used (faster still).
            slack_tolerance: the most slack the returned action may need in any RCBF row;
                beyond it the fail-safe is returned (None: return the QP's best effort and
                report the slack; the solver's answer is checked either way).
            input_bounds: magnitude bounds of the inputs (default :class:`InputBounds`).
            closed_form: assemble in closed form where the problem has one (see
                :func:`select_assembly`; False: the autograd path, as for any other problem).
                :attr:`assembly` names the path taken.
            vector_rows: the fewest obstacles of a circle family that the closed form
                evaluates over arrays (:mod:`rcbf_ros.core.lie_closed_form_rows`); the filter
                then takes its many-row path (:meth:`_filter_many`), whose QP carries only
                the rows that can bind.
            footprint: a one-obstacle circle family (radius the robot's, the obstacles'
                margin, look-ahead and cascade gains) for sensor points: :meth:`set_points`
                then replaces the points without a rebuild, their rows join the many-row path,
                and the result reports them as one more barrier, :data:`POINTS_BARRIER` (the
                least h and the least row value over the points; h = inf without points).
            control_period_s: T, how long the plant holds each command (s, 0 to 1; 0: the
                continuous-time rows).
            latency_s: L, the age of the state when its command starts to act (s, 0 to 1).
                With T + L > 0 every RCBF row (the sensor points' too) is tightened by its
                sampled-data margin (:mod:`rcbf_ros.core.sampled_data`), so that h >= 0 holds
                over [t_k, t_k + L + T], not only at the sample; the rows and the reported
                constraint values are the tightened ones.

        Raises:
            ValueError: naming ``fail_safe_action`` (wrong length, not finite, outside the
                limits), ``slack_tolerance`` (negative or not finite), or ``control_period_s``
                / ``latency_s`` (out of range, or no margin derived for the problem).
        """
        self.fallback = fallback
        self._margin = sampled_data_margin(problem, control_period_s=control_period_s,
                                           latency_s=latency_s, footprint=footprint)
        self.control_period_s, self.latency_s = float(control_period_s), float(latency_s)
        """T and L the rows are tightened for (both 0: not tightened)."""
        self._points = None if footprint is None else PointRows(problem, footprint)
        self._many: VectorAssembly | _RowsAsArrays | None = (
            VectorAssembly.from_problem(problem, threshold=vector_rows) if closed_form else None)
        if self._many is not None:
            assembly, self._assemble = 'vectorised', _many_as_lists(self._many)
        else:
            assembly, self._assemble = select_assembly(
                problem, compile_assembly=compile_assembly, closed_form=closed_form)
            if (problem.n_barriers > GENERATED_ROWS or self._points is not None
                    or self._margin is not None):
                # the many-row path, on this assembly (with a margin: its split rows, whose
                # count is not the problem's)
                self._many = _RowsAsArrays(self._assemble, problem.n_barriers,
                                           problem.system.n_u)
        if self._margin is not None:  # the data check of evaluation_refusal
            self._assemble = _tightened(self._assemble, self._margin, problem.n_barriers)
        self.assembly = assembly
        """The constraint assembly's path: 'closed_form', 'vectorised' (the closed form with
        circle rows over arrays), 'autograd' or 'compiled'."""
        self.problem = problem
        system = problem.system
        self.n_x, self.n_u = system.n_x, system.n_u
        self.n_barriers = problem.n_barriers
        self.barrier_names = problem.barrier_names + (
            [POINTS_BARRIER] if self._points is not None else [])
        nz, nc = self.n_u + 1, problem.n_constraints
        if problem.has_limits:
            self._u_min = np.asarray(system.u_min, dtype=np.float64)
            self._u_max = np.asarray(system.u_max, dtype=np.float64)
        else:
            self._u_min = np.full(self.n_u, -np.inf)
            self._u_max = np.full(self.n_u, np.inf)
        if slack_tolerance is not None and not (math.isfinite(slack_tolerance)
                                                and slack_tolerance >= 0):
            raise ValueError(f'slack_tolerance: must be a finite number >= 0, '
                             f'got {slack_tolerance!r}')
        self.slack_tolerance = slack_tolerance
        self.input_bounds = InputBounds() if input_bounds is None else input_bounds
        self._limits = list(zip(self._u_min.tolist(), self._u_max.tolist()))
        self._finite_limits = bool(np.isfinite(self._u_min).all()
                                   and np.isfinite(self._u_max).all())
        self._zeros_x_list = [0.0] * self.n_x
        action = np.zeros(self.n_u) if fail_safe_action is None else _vector(
            'fail_safe_action', fail_safe_action, self.n_u)
        if not np.all(np.isfinite(action)):
            raise ValueError('fail_safe_action: contains NaN or inf')
        outside = (action < self._u_min) | (action > self._u_max)
        if fail_safe_action is None:
            action = np.clip(action, self._u_min, self._u_max)  # zeros unless 0 is excluded
        elif np.any(outside):
            raise ValueError(f'fail_safe_action: {action.tolist()} lies outside the input '
                             f'limits [{self._u_min.tolist()}, {self._u_max.tolist()}]')
        self.fail_safe_action = action

        # Fixed pattern: RCBF rows are dense in (u_S, eps); limit rows hold one entry each.
        pattern = np.zeros((nc, nz), dtype=bool)
        pattern[:self.n_barriers, :] = True
        for j in range(self.n_u if problem.has_limits else 0):
            pattern[self.n_barriers + j, j] = True
            pattern[self.n_barriers + self.n_u + j, j] = True
        cols, rows = np.nonzero(pattern.T)  # column-major = CSC order
        self._rows, self._cols = rows, cols
        self._pattern_index = rows * nz + cols  # A's entries in G.ravel(), CSC order
        # Imported here: what only reads the filter's settings (a node's --help) skips them.
        import osqp
        import scipy.sparse as sp
        a_matrix = sp.csc_matrix((np.ones(rows.size), (rows, cols)), shape=(nc, nz))
        a_matrix.sort_indices()
        diag = 2.0 * np.asarray(cost_weights(self.n_u, problem.slack_weight,
                                             problem.input_weight))
        self._solver = osqp.OSQP()
        self._solver.setup(P=sp.csc_matrix(np.diag(diag)), q=np.zeros(nz), A=a_matrix,
                           l=np.full(nc, -np.inf), u=np.ones(nc), verbose=False, polishing=polish,
                           eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter,
                           warm_starting=True)
        self._solver = _DirectOSQP.wrap(self._solver)
        self._nc = nc
        self._p_inverse = 1.0 / diag  # P = diag(diag), for the active-set solve
        self._p_inverse_list = self._p_inverse.tolist()
        kernels = _shape_kernels(self._p_inverse_list, self.n_x,
                                 0 if self._many is not None else self.n_barriers,
                                 self._limits if problem.has_limits else None)
        self._pruned = 0
        """How many RCBF rows the last call of the many-row path left out of its QP."""
        unit = np.eye(self.n_u, nz)
        self._limit_rows = ((np.concatenate((unit, -unit)) + 0.0).tolist()
                            if problem.has_limits else [])
        self._limit_columns = np.array(self._limit_rows).T.copy()
        """The limit rows by column (for the many-row path's table of rows)."""
        self._kernels, self._row_values = kernels.solve, kernels.row_values
        self._within_bounds, self._clip = kernels.within_bounds, kernels.clip
        self._act = kernels.act

    def filter(self, state: Sequence[float], u_rl: Sequence[float],
               mean: Sequence[float] | None = None,
               std: Sequence[float] | None = None) -> FilterResult:
        """Make u_rl safe at state under the disturbance box mean +/- k_c std.

        Never raises on values: NaN, inf, out-of-bound inputs and every failed or unverified
        solve return the fail-safe action with the reason (see the module docstring).

        Args:
            state: n_x values.
            u_rl: n_u proposed values.
            mean: n_x disturbance mean (None: zero).
            std: n_x disturbance std >= 0 (None: zero).

        Raises:
            ValueError: naming the field, for a wrong length or non-numeric data.
        """
        start = time.perf_counter()
        n_x = self.n_x
        x = _floats('state', state, n_x)
        u = _floats('u_rl', u_rl, self.n_u)
        mu = self._zeros_x_list if mean is None else _floats('disturbance_mean', mean, n_x)
        sd = self._zeros_x_list if std is None else _floats('disturbance_std', std, n_x)
        bounds = self.input_bounds
        # Finite, within the bounds and std >= 0: one chained comparison per value (NaN fails
        # each); an input that fails goes through the checks one by one, for the reason
        # naming the field.
        if not self._within_bounds(x, u, mu, sd, bounds.state, bounds.command,
                                   bounds.disturbance):
            reason = _input_refusal(x, u, mu, sd, bounds)
            if reason is not None:
                return self._fail_safe(u, start, status='input_refused', reason=reason)

        # Clip before the QP: its rows are then written at a command the plant can take.
        applied = self._clip(u)
        clipped = applied != u
        if self._many is not None:
            return self._filter_many(x, u, applied, clipped, mu, sd, start)
        h_values, g_rows, upper, size = self._assemble(x, applied, mu, sd)
        # One sum of squares when the data passes (NaN and inf fail the <=); else the exact
        # check, for the refusal naming the data.
        if not size <= _QP_DATA_SQUARES:
            reason = _data_refusal(h_values, g_rows, upper)
            if reason is not None:
                return self._fail_safe(u, start, status='input_refused', h=h_values,
                                       clipped=clipped, reason=reason)
        solve_start = time.perf_counter()
        k = self.n_barriers
        if min(upper) >= 0.0:
            # z = 0 is feasible, hence optimal (the objective's minimum): the proposal passes
            # through exactly, without a solve. The row check holds at z = 0 by construction:
            # the action is the clipped proposal (within the limits), each row's value at it is
            # its right-hand side (all >= 0 here: no slack needed, none claimed).
            values = np.array(upper[:k])
            u_safe = [value + 0.0 for value in applied]  # as u + z[:n_u], z = 0
            solve_time = time.perf_counter() - solve_start
            return FilterResult._filled(
                u_safe=np.array(u_safe), u_s=np.array([a - b for a, b in zip(u_safe, u)]),
                slack=0.0, h=np.array(h_values), constraint_values=values, status='solved',
                solve_time_s=solve_time, total_time_s=time.perf_counter() - start,
                fail_safe=False, barrier_names=list(self.barrier_names), needed_slack=0.0,
                reason='', proposal_clipped=clipped, points=None)
        # The RCBF rows (their right-hand sides, the rows of G) at the clipped proposal.
        rows = (upper[:k], g_rows[:k], applied)
        status = 'solved'
        z = self._active_set(g_rows, upper)
        checked = None if z is None else self._check(z, rows)
        if checked is None:
            self._solver.update(Ax=np.array(g_rows).take(self._pattern_index),
                                u=np.array(upper))
            result = self._solver.solve(raise_error=False)
            status_val = int(result.info.status_val)
            # used within this call only (the action and values are new arrays): no copy
            z = None if result.x is None else np.asarray(result.x, dtype=np.float64)
            checked = self._check(z, rows) if status_val in _OK_STATUS else None
            status = _OK_STATUS.get(status_val, str(result.info.status))
        if checked is None:
            # Never start a later solve from this iterate.
            self._solver.warm_start(x=np.zeros(self.n_u + 1), y=np.zeros(self._nc))
            if self.fallback:
                # ADMM can stall when the slack is far from 0 (the 1 : l diagonal); the
                # interior point of the differentiable layer solves the same QP robustly.
                solved = _interior_point(self.problem, (x, applied, mu, sd))
                if solved is not None:
                    z = solved
                    checked = self._check(z, rows)
                    status = 'solved_interior_point'
        solve_time = time.perf_counter() - solve_start
        if checked is None:
            return self._fail_safe(u, start, status='unverified', h=h_values, clipped=clipped,
                                   solve_time=solve_time, rows=rows,
                                   reason=f'no solution passed the row check (solver: {status})')
        action, values, needed = checked
        if self.slack_tolerance is not None and needed > self.slack_tolerance:
            return self._fail_safe(
                u, start, status='slack_exceeded', h=h_values, clipped=clipped,
                solve_time=solve_time, rows=rows,
                reason=f'barrier rows need slack {needed:.3g} > slack_tolerance '
                       f'{self.slack_tolerance:.3g} within the input limits')
        return FilterResult._filled(
            u_safe=np.array(action), u_s=np.array([a - b for a, b in zip(action, u)]),
            slack=float(z[-1]), h=np.array(h_values), constraint_values=np.array(values),
            status=status, solve_time_s=solve_time, total_time_s=time.perf_counter() - start,
            fail_safe=False, barrier_names=list(self.barrier_names), needed_slack=needed,
            reason='', proposal_clipped=clipped, points=None)

    def evaluation_refusal(self, state: Sequence[float], mean: Sequence[float] | None = None,
                           std: Sequence[float] | None = None) -> str | None:
        """Why :meth:`filter` would refuse every proposal at ``state`` with this box, or None.

        The input checks and the QP data check of :meth:`filter`, at the fail-safe action:
        parameters whose rows overflow float64 or pass :data:`QP_DATA_LIMIT` at an ordinary
        state make every answer the fail-safe, which a caller can refuse before it uses the
        filter. Nothing is solved and nothing changes (no warm start).

        Raises:
            ValueError: naming the field, for a wrong length or non-numeric data.
        """
        x = _floats('state', state, self.n_x)
        u = [float(a) for a in self.fail_safe_action]
        mu = self._zeros_x_list if mean is None else _floats('disturbance_mean', mean, self.n_x)
        sd = self._zeros_x_list if std is None else _floats('disturbance_std', std, self.n_x)
        reason = _input_refusal(x, u, mu, sd, self.input_bounds)
        if reason is not None:
            return reason
        h_values, g_rows, upper, size = self._assemble(x, self._clip(u), mu, sd)
        return None if size <= _QP_DATA_SQUARES else _data_refusal(h_values, g_rows, upper)

    def _active_set(self, g_rows: list[list[float]], upper: list[float]) -> list[float] | None:
        """The QP's exact solution by :func:`active_set_solution`, else None (then OSQP).

        With P diagonal the QP is the projection of 0 onto the rows' polyhedron in the
        P-metric, which :func:`active_set_solution` solves exactly, certified (multipliers >=
        0, stationarity, every row and limit met and the active ones held, each to
        :data:`ACTIVE_SET_TOLERANCE` relative to the largest right-hand side, or, where they
        spread, each RCBF row to its own: :func:`_each_row_own`). A strictly
        convex QP has one solution, so a certified answer is it (OSQP's is within its
        tolerance of it). The answer then goes through the row check like any other (where
        scaled rows are not certified, the rows as they are: :func:`_each_row_own_steps`)."""
        kernels = self._kernels
        return _each_row_own_steps(g_rows, upper, self.n_barriers, self._p_inverse_list,
                                   lambda rows, bounds: kernels)

    def _finite_solution(self, z: Sequence[float] | np.ndarray | None) -> list[float] | None:
        """Solution z as a list of n_u + 1 finite floats, or None if it is not one."""
        if type(z) is not list:
            if z is None or z.shape != (self.n_u + 1,):
                return None
            z = z.tolist()
        elif len(z) != self.n_u + 1:
            return None
        return z if all(map(math.isfinite, z)) else None

    def _check(self, z: Sequence[float] | np.ndarray | None,
               rows: tuple[list[float], list[list[float]], list[float]]
               ) -> tuple[list[float], list[float], float] | None:
        """The action of solution z and its row values, if z passes the row check.

        ``rows``: the RCBF rows' right-hand sides (K floats), the rows themselves (K lists
        [-L_g h_i, -1]) and the proposal they are written at (n_u floats). The action
        u + z[:n_u] must lie within the limits (to :data:`LIMIT_TOLERANCE`; then projected
        onto them), and the slack its rows need, from the rows themselves, must be accounted
        for by the solver's own eps z[-1], each row to 1e-6 of its own scale, 1 + |upper_i| +
        sum_j |L_g h_ij step_j| (step: the answer's move from the proposal): the size of the
        terms its value is summed from, which the solver's own tolerance is relative to
        (OSQP's: to the largest |G z|), and no other row's. A far row's right-hand side must
        not loosen the rows that bind, nor a row of large gradient be held to a round-off its
        solver cannot reach (|L_g h| 1e3 at a right-hand side near 0)."""
        z = self._finite_solution(z)
        if z is None:
            return None
        rows_upper, g_rows, applied = rows
        moved = self._act(applied, z)
        if moved is None:
            return None
        action, step = moved
        values = self._row_values(rows_upper, g_rows, step)
        needed = max(0.0, -min(values))
        # The solver's own eps must account for what the rows need: else the answer is not the
        # solution of this QP (a stale or garbage iterate).
        claimed = max(0.0, z[-1])
        if needed > claimed + 1e-6:  # each row to 1e-6 of its own scale (_check)
            n_u = self.n_u
            if any(value + claimed < -1e-6 * (1.0 + abs(bound) + sum(
                    abs(g * d) for g, d in zip(row[:n_u], step)))
                   for value, bound, row in zip(values, rows_upper, g_rows)):
                return None
        return action, values, needed

    def _filter_many(self, x: list[float], u: list[float], applied: list[float],
                     clipped: bool, mu: list[float], sd: list[float], start: float
                     ) -> FilterResult:
        """:meth:`filter` from the assembly on, for a problem whose circle rows are evaluated
        over arrays (:class:`VectorAssembly`): the same steps and checks, the rows' data and
        the row check over arrays, and the exact solve on the rows that can bind only
        (:func:`binding_rows`; beyond :data:`EXACT_ROWS` of them, the fewer rows of
        :func:`merged_rows` that imply them all); OSQP and the interior point, where reached,
        take every row. The answer is checked against every row either way."""
        rows = self._many.evaluate(x, applied, mu, sd)  # type: ignore[union-attr]
        h, lg, upper, limit_upper = rows.h, rows.lg, rows.upper, rows.limit_upper
        size = rows.size
        point_h = None
        margin = self._margin
        if margin is not None:
            rest, linear = margin.split_rows(x, mu, sd)
        if self._points is not None:  # the sensor points' rows follow the problem's
            point_h, point_lg, point_upper = self._points.evaluate(x, applied, mu, sd)
            if margin is not None:
                point_rest, point_linear = margin.split_points(  # type: ignore[union-attr]
                    x, mu, sd, *self._points.centres)
                rest = np.concatenate([rest, point_rest])
                linear = np.concatenate([linear, point_linear])
            flat = point_lg.ravel()
            # (``dot``: the BLAS call of ``@``, without its ufunc overhead)
            size += (float(point_h.dot(point_h)) + float(flat.dot(flat))
                     + float(point_upper.dot(point_upper)) + point_h.size)
            least_point = _least(point_upper) if point_upper.size else math.inf
            if (margin is None and size <= _QP_DATA_SQUARES
                    and _meets_every_row(upper, least_point, limit_upper)):
                # the pass-through below, from the problem's rows and the points' apart: the
                # common answer skips joining them (three arrays of every point's row)
                self._pruned = upper.size + point_upper.size
                return self._passed_through(
                    u, applied, clipped, start, time.perf_counter(),
                    self._reported(h, point_h), self._with_least(upper, least_point),
                    self._point_values(point_h, point_upper, every=False))
            h = np.concatenate([h, point_h])
            lg = np.concatenate([lg, point_lg])
            upper = np.concatenate([upper, point_upper])
        report, per_row = self._reported, _as_they_are
        if margin is not None:
            # each row tightened by nu0 + c^T |u|: its split rows (one per sign vector)
            before = float(upper @ upper) + float(lg.ravel() @ lg.ravel())
            lg, upper, starts = split_rows(lg, upper, applied, rest, linear)
            size += float(upper @ upper) + float(lg.ravel() @ lg.ravel()) - before
            per_row = functools.partial(least_per_row, starts=starts)
        if not size <= _QP_DATA_SQUARES:
            reason = _data_refusal(h.tolist(), (-lg).tolist(), upper.tolist() + limit_upper)
            if reason is not None:
                return self._fail_safe(u, start, status='input_refused', h=report(h).tolist(),
                                       clipped=clipped, reason=reason)
        solve_start = time.perf_counter()
        lowest, highest = ((float(_least(upper)), float(_largest(upper))) if upper.size
                           else (0.0, 0.0))  # no rows: sensor points only, none in sight
        if limit_upper:
            lowest, highest = min(lowest, min(limit_upper)), max(highest, max(limit_upper))
        if lowest >= 0.0:  # the pass-through of filter(): z = 0 meets every row
            self._pruned = upper.size
            at_rows = per_row(upper)
            return self._passed_through(u, applied, clipped, start, solve_start, report(h),
                                        report(at_rows), self._point_values(point_h, at_rows))
        has_limits = self.problem.has_limits
        scale = 1.0 + max(highest, -lowest)
        keep = binding_rows(lg=lg, upper=upper, applied=applied,
                            u_min=self._u_min if has_limits else None,
                            u_max=self._u_max if has_limits else None,
                            margin=PRUNE_MARGIN * scale)
        self._pruned = upper.size - keep.size
        solve_lg, solve_upper = lg[keep], upper[keep]
        generated = None
        if keep.size > EXACT_ROWS and self._finite_limits:
            # too many rows to solve at once in time: the exact QP by adding the rows its
            # answer violates (_generated), else fewer rows that imply them all (merged_rows)
            generated = self._generated(solve_lg, solve_upper, limit_upper)
            solve_lg, solve_upper = generated[1:] if generated is not None else merged_rows(
                lg=solve_lg, upper=solve_upper, applied=applied, u_min=self._u_min,
                u_max=self._u_max, count=EXACT_ROWS)
        # the QP's rows [-lg, -1] z <= upper, then the limit rows: by column, and as lists
        count, n_u = solve_upper.size, self.n_u
        columns = np.empty((n_u + 1, count + len(self._limit_rows)))
        np.negative(solve_lg.T, out=columns[:n_u, :count])
        columns[n_u, :count] = -1.0
        if self._limit_rows:
            columns[:, count:] = self._limit_columns
        g_rows = columns.T.tolist()
        qp_upper = np.concatenate((solve_upper, limit_upper)) if limit_upper else solve_upper
        qp_upper_list = qp_upper.tolist()
        if generated is not None:
            z = generated[0]
        else:
            kernels = self._kernels
            if len(g_rows) >= ARRAY_EXCESS_ROWS and n_u + 1 in (2, 3):
                def kernels_of(rows: list[list[float]], bounds: list[float]) -> Kernels:
                    # the arrays' excess kernel reads the rows a try solves (scaled too)
                    excess = (_excess_over(columns, qp_upper) if rows is g_rows
                              else _excess_over(np.array(rows).T, np.array(bounds)))
                    return kernels[0], excess, kernels[2]
            else:
                def kernels_of(rows: list[list[float]], bounds: list[float]) -> Kernels:
                    return kernels
            z = _each_row_own_steps(
                g_rows, qp_upper_list, count, self._p_inverse_list, kernels_of,
                1.0 + max(float(_largest(qp_upper)), -float(_least(qp_upper))))
        status = 'solved'
        checked = None if z is None else self._check_many(z, upper, lg, applied)
        if checked is None and (self._points is not None or margin is not None):
            # the row count changes with the points and the margins' split: a QP of the rows
            # that can bind, set up for this call (the exact solve failed: rare)
            z, status = _solve_once(g_rows, qp_upper_list, self._p_inverse)
            checked = None if z is None else self._check_many(z, upper, lg, applied)
        elif checked is None:
            g_matrix = np.empty((self._nc, self.n_u + 1))
            g_matrix[:h.size, :self.n_u] = -lg
            g_matrix[:h.size, self.n_u] = -1.0
            if self._limit_rows:
                g_matrix[h.size:] = self._limit_rows
            self._solver.update(Ax=g_matrix.take(self._pattern_index),
                                u=np.concatenate([upper, limit_upper]))
            result = self._solver.solve(raise_error=False)
            status_val = int(result.info.status_val)
            z = None if result.x is None else np.asarray(result.x, dtype=np.float64)
            checked = self._check_many(z, upper, lg, applied) if status_val in _OK_STATUS else None
            status = _OK_STATUS.get(status_val, str(result.info.status))
        if checked is None:
            self._solver.warm_start(x=np.zeros(self.n_u + 1), y=np.zeros(self._nc))
            if self.fallback and self._points is None:  # its problem has no points
                solved = _interior_point(self.problem, (x, applied, mu, sd), None if (
                    margin is None) else (lg, upper, limit_upper))
                if solved is not None:
                    z = solved
                    checked = self._check_many(z, upper, lg, applied)
                    status = 'solved_interior_point'
        solve_time = time.perf_counter() - solve_start
        fail_values = None
        if checked is None or (self.slack_tolerance is not None
                               and checked[2] > self.slack_tolerance):
            fail_values = per_row(upper + lg @ (self.fail_safe_action - np.array(applied)))
        fail_points = None
        if fail_values is not None:
            fail_points = self._point_values(point_h, fail_values)
            fail_values = report(fail_values)
        if checked is None:
            return self._fail_safe(u, start, status='unverified', h=report(h).tolist(),
                                   clipped=clipped, solve_time=solve_time, values=fail_values,
                                   reason=f'no solution passed the row check (solver: {status})',
                                   points=fail_points)
        action, values, needed = checked
        values = per_row(values)
        if self.slack_tolerance is not None and needed > self.slack_tolerance:
            return self._fail_safe(
                u, start, status='slack_exceeded', h=report(h).tolist(), clipped=clipped,
                solve_time=solve_time, values=fail_values, points=fail_points,
                reason=f'barrier rows need slack {needed:.3g} > slack_tolerance '
                       f'{self.slack_tolerance:.3g} within the input limits')
        assert z is not None
        return FilterResult._filled(
            u_safe=np.array(action), u_s=np.array([a - b for a, b in zip(action, u)]),
            slack=float(z[-1]), h=report(h), constraint_values=report(values),
            status=status, solve_time_s=solve_time, total_time_s=time.perf_counter() - start,
            fail_safe=False, barrier_names=list(self.barrier_names), needed_slack=needed,
            reason='', proposal_clipped=clipped, points=self._point_values(point_h, values))

    def _passed_through(self, u: list[float], applied: list[float], clipped: bool,
                        start: float, solve_start: float, h: np.ndarray, values: np.ndarray,
                        points: PointValues | None) -> FilterResult:
        """The many-row path's answer where the clipped proposal meets every row (z = 0, the
        pass-through of :meth:`filter`): ``h`` and ``values`` as reported."""
        u_safe = [value + 0.0 for value in applied]  # as u + z[:n_u], z = 0
        return FilterResult._filled(
            u_safe=np.array(u_safe), u_s=np.array([a - b for a, b in zip(u_safe, u)]),
            slack=0.0, h=h, constraint_values=values, status='solved',
            solve_time_s=time.perf_counter() - solve_start,
            total_time_s=time.perf_counter() - start, fail_safe=False,
            barrier_names=list(self.barrier_names), needed_slack=0.0, reason='',
            proposal_clipped=clipped, points=points)

    def _generated(self, lg: np.ndarray, upper: np.ndarray, limit_upper: list[float]
                   ) -> tuple[list[float], np.ndarray, np.ndarray] | None:
        """The QP on many rows (``lg`` (K, n_u), ``upper`` (K,)) solved exactly on few of them:
        the :data:`GENERATED_BATCH` lowest at the proposal first, then, while the answer
        violates a row, the :data:`GENERATED_BATCH` it violates most added, up to
        :data:`EXACT_ROWS` rows. An answer that meets every row is the QP's own (the QP on
        fewer rows has the larger feasible set). (z, the rows it was solved on) or None. A row
        counts as met to :data:`PRUNE_MARGIN` of its own scale, 1 + |upper_i|."""
        working = np.argpartition(upper, GENERATED_BATCH)[:GENERATED_BATCH]
        while True:
            working_lg, working_upper = lg[working], upper[working]
            g_rows = np.concatenate([-working_lg, np.full((working.size, 1), -1.0)],
                                    axis=1).tolist()
            rows, bounds, each = _each_row_own(g_rows + self._limit_rows,
                                               working_upper.tolist() + limit_upper,
                                               working.size)
            z = _active_set_steps(rows, bounds, self._p_inverse_list, each, ACTIVE_SET_STEPS,
                                  self._kernels)
            if z is None:
                return None
            values = upper + lg @ np.array(z[:self.n_u]) + z[self.n_u]
            violated = np.flatnonzero(values < -PRUNE_MARGIN)  # (each scale is 1 or more)
            if violated.size:
                violated = violated[values[violated]
                                    < -PRUNE_MARGIN * (1.0 + np.abs(upper[violated]))]
            if not violated.size:
                return z, working_lg, working_upper
            if working.size + GENERATED_BATCH > EXACT_ROWS:
                return None
            if violated.size > GENERATED_BATCH:
                violated = violated[np.argpartition(values[violated],
                                                    GENERATED_BATCH)[:GENERATED_BATCH]]
            working = np.concatenate([working, violated])

    def set_points(self, points: np.ndarray, spread: np.ndarray | float = 0.0) -> None:
        """Replace the sensor points (a filter built with ``footprint``): (N, 2) finite
        float64 in the state's frame; ``spread`` (N,) or one value >= 0 widens each point's
        circle. Costs microseconds: nothing is rebuilt.

        Raises:
            ValueError: the filter has no footprint, or ``points`` is not (N, 2) finite.
        """
        if self._points is None:
            raise ValueError('set_points: this filter was built without a footprint')
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or not _all_finite(points):
            raise ValueError(f'set_points: expected finite (N, 2) points, got shape '
                             f'{points.shape}')
        if type(spread) is float or np.ndim(spread) == 0:
            if not 0.0 <= spread < math.inf:
                raise ValueError('set_points: spread must be finite and >= 0')
        else:
            spread = np.asarray(spread, dtype=np.float64)
            if spread.shape != (len(points),) or not ((spread >= 0.0) & (spread < math.inf)).all():
                raise ValueError('set_points: spread must be (N,) finite and >= 0')
        self._points.set(points, spread)

    @property
    def point_count(self) -> int:
        """How many sensor points the rows hold (0 without a footprint)."""
        return 0 if self._points is None else self._points.count

    def _reported(self, values: np.ndarray, point_values: np.ndarray | None = None
                  ) -> np.ndarray:
        """Per-row values as the result reports them: the problem's rows, then (with a
        footprint) the least over the sensor points' rows (inf without points); the points'
        rows follow the problem's in ``values``, or are ``point_values`` apart."""
        if self._points is None:
            return values
        k = self.n_barriers
        if point_values is None:
            values, point_values = values[:k], values[k:]
        return self._with_least(values, _least(point_values) if point_values.size else math.inf)

    def _with_least(self, values: np.ndarray, least_point: float) -> np.ndarray:
        """:meth:`_reported` with the least over the points' rows given: the problem's rows
        of ``values``, then ``least_point``."""
        k = self.n_barriers
        out = np.empty(k + 1)
        out[:k] = values[:k]
        out[k] = least_point
        return out

    def _point_values(self, point_h: np.ndarray | None, values: np.ndarray, *,
                      every: bool = True) -> PointValues | None:
        """The sensor points' rows of an answer (None without points): their h and their part
        of ``values`` (every row's, the problem's first; ``every`` False: the points' rows
        only), views, no copy."""
        if point_h is None:
            return None
        cx, cy = self._points.centres  # type: ignore[union-attr]
        return PointValues(cx, cy, point_h, values[self.n_barriers:] if every else values)

    def _check_many(self, z: Sequence[float] | np.ndarray | None, upper: np.ndarray,
                    lg: np.ndarray, applied: list[float]
                    ) -> tuple[list[float], np.ndarray, float] | None:
        """:meth:`_check` over arrays: the action of solution z and the values of EVERY row
        at it (those left out of the QP too), if z passes the row check."""
        z = self._finite_solution(z)
        if z is None:
            return None
        moved = self._act(applied, z)
        if moved is None:
            return None
        action, step = moved
        values = upper + product(lg, step)
        needed = max(0.0, -float(_least(values)))
        claimed = max(0.0, z[-1])
        if needed > claimed + 1e-6:  # each row to 1e-6 of its own scale (_check)
            scale = 1.0 + np.abs(upper) + product(np.abs(lg), np.abs(np.asarray(step)))
            if _least(values + claimed + 1e-6 * scale) < 0.0:
                return None
        return action, values, needed

    def _fail_safe(self, u: list[float], start: float, *, status: str, reason: str,
                   h: list[float] | None = None, clipped: bool = False,
                   solve_time: float = 0.0,
                   rows: tuple[list[float], list[list[float]], list[float]] | None = None,
                   values: np.ndarray | None = None,
                   points: PointValues | None = None) -> FilterResult:
        """The fail-safe result; ``rows`` (right-hand sides, rows, u at the rows) give its row
        values; ``points`` the sensor points' rows at the fail-safe action."""
        action = self.fail_safe_action.copy()
        nan = np.full(len(self.barrier_names), np.nan)
        needed = float('nan')
        if rows is not None:
            rows_upper, g_rows, u_rows = rows
            row_values = self._row_values(rows_upper, g_rows,
                                     [a - b for a, b in zip(action.tolist(), u_rows)])
            values, needed = np.array(row_values), max(0.0, -min(row_values))
        elif values is not None:  # the many-row path's, evaluated over arrays
            needed = max(0.0, -float(values.min()))
        else:
            values = nan
        return FilterResult(
            u_safe=action, u_s=action - np.array(u), slack=float('nan'),
            h=nan if h is None else np.array(h), constraint_values=values, status=status,
            solve_time_s=solve_time, total_time_s=time.perf_counter() - start, fail_safe=True,
            barrier_names=list(self.barrier_names), needed_slack=needed, reason=reason,
            proposal_clipped=clipped, points=points)

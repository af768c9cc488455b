"""The safety filter's active-set solve against an independent solver.

The reference enumerates active sets: for every set of at most nz linearly independent rows it
takes the least-cost point with those rows held as equalities (z = P^-1 G_W^T (G_W P^-1
G_W^T)^-1 upper_W, in numpy, in the filter's own units), keeps the points that meet every row
and returns the cheapest. The QP's solution is such a point (its active rows, or a linearly
independent subset of them, determine it), and no feasible point costs less, so this is the
solution without any multiplier or step logic of the method under test.

QPs: the filter's shape (K dense RCBF rows with -1 in the slack column, then two limit rows
per input), random and adversarial (two and three rows active, limits active, nearly parallel
and duplicated rows, slack far from zero, data spanning many orders of magnitude), the
shipped systems' own QPs, and a Hypothesis search over hostile QP data fed to the whole
filter.
"""
from __future__ import annotations

import itertools
import math

from filter_paths import qp_arrays, random_call, shipped_filter
from hypothesis import example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.core import filter as filter_module
from rcbf_ros.core.filter import active_set_solution, ACTIVE_SET_TOLERANCE, SafetyFilter

SYSTEMS = ('unicycle', 'car_following', 'pvtol')


def enumerated_solution(g_matrix: np.ndarray, upper: np.ndarray, weights: np.ndarray
                        ) -> np.ndarray | None:
    """min 1/2 z^T diag(weights) z s.t. g_matrix z <= upper by enumerating active sets.

    In y = sqrt(weights) z (cost 1/2 |y|^2, rows A = G diag(weights)^-1/2), each row and its
    right-hand side divided by the row's length (the same constraint; unit rows keep the rank
    test and the round-off independent of the rows' scales, which may differ by 1e8 and
    more): for every set W of up to nz rows of full rank, the least |y| with A_W y = upper_W
    (by SVD, all sets of one size at once); the cheapest of those that meet every row."""
    m, nz = g_matrix.shape
    scale = 1.0 / np.sqrt(weights)
    rows = g_matrix * scale
    lengths = np.linalg.norm(rows, axis=1)  # > 0: every row of the filter's QP has an entry
    rows, bounds = rows / lengths[:, None], upper / lengths
    best = np.zeros(nz) if upper.min() >= 0.0 else None
    best_cost = 0.0 if best is not None else np.inf
    for size in range(1, min(nz, m) + 1):
        subsets = np.array(list(itertools.combinations(range(m), size)))
        u_matrix, singular, v_rows = np.linalg.svd(rows[subsets], full_matrices=False)
        full_rank = singular.min(axis=1) > 1e-10 * singular.max(axis=1)
        with np.errstate(all='ignore'):  # the rank-deficient sets, left out below
            coordinates = np.einsum('csk,cs->ck', u_matrix, bounds[subsets]) / singular
            candidates = np.einsum('ckn,ck->cn', v_rows, coordinates)
            # each (unit) row met to the round-off of its own terms (the sum of |row_k y_k|),
            # and of the candidate's (the SVD's, relative to |y|): |y| itself at 1e-9 would
            # let a large coordinate the row hardly weighs (a costly slack) cover a real miss
            tolerance = (1e-9 * (1.0 + np.abs(bounds) + np.abs(candidates) @ np.abs(rows).T)
                         + 1e-12 * np.linalg.norm(candidates, axis=1)[:, None])
            feasible = full_rank & np.all(candidates @ rows.T - bounds <= tolerance, axis=1)
        if feasible.any():
            with np.errstate(all='ignore'):
                costs = np.where(feasible, 0.5 * (candidates ** 2).sum(axis=1), np.inf)
            c = int(costs.argmin())
            if costs[c] < best_cost:
                best, best_cost = candidates[c], float(costs[c])
    return None if best is None else scale * best


def filter_shaped_qp(rng: np.random.Generator, *, n_u: int, k: int, limits: bool = True
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(G, upper, P's diagonal) of the filter's shape with random rows, limits and weights."""
    rows = np.concatenate([rng.normal(0.0, 3.0, (k, n_u)), -np.ones((k, 1))], axis=1)
    upper = rng.normal(-1.0, 3.0, k)
    if limits:
        identity = np.concatenate([np.eye(n_u), np.zeros((n_u, 1))], axis=1)
        high, low = rng.uniform(0.0, 3.0, n_u), rng.uniform(0.0, 3.0, n_u)
        rows = np.concatenate([rows, identity, -identity])
        upper = np.concatenate([upper, high, low])
    weights = 2.0 * np.concatenate([10.0 ** rng.uniform(-2.0, 2.0, n_u),
                                    [10.0 ** rng.uniform(0.0, 8.0)]])
    return rows, upper, weights


def solve(g_matrix: np.ndarray, upper: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """The method under test, as SafetyFilter._active_set calls it."""
    return active_set_solution(
        rows=g_matrix, upper=upper, p_inverse=1.0 / weights,
        tolerance=ACTIVE_SET_TOLERANCE * (1.0 + float(np.abs(upper).max())))


def active_rows(g_matrix: np.ndarray, upper: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.abs(g_matrix @ z - upper) <= 1e-9 * (1.0 + np.abs(upper).max())


def assert_same_solution(z: np.ndarray, reference: np.ndarray, weights: np.ndarray,
                         g_matrix: np.ndarray, upper: np.ndarray, *,
                         spread_data: bool = False) -> None:
    """Equal to the reference in the cost's own metric, to 1e-7 of its size. With
    ``spread_data`` (right-hand sides over many orders of magnitude) also to what a row met
    to 1e-9 of the largest right-hand side can move the answer (the method meets rows to
    1e-12 of it, the reference to their own round-off): that over the shortest row's length
    in the metric."""
    gap = np.linalg.norm(np.sqrt(weights) * (z - reference))
    allowed = 1e-7 * (1.0 + float(np.linalg.norm(np.sqrt(weights) * reference)))
    if spread_data:
        shortest = float(np.linalg.norm(g_matrix / np.sqrt(weights), axis=1).min())
        allowed += 1e-9 * (1.0 + float(np.abs(upper).max())) / shortest
    assert gap <= allowed, (z, reference, gap, allowed)


def test_random_qps_of_the_filters_shape_match_enumeration():
    rng = np.random.default_rng(3)
    seen = {1: 0, 2: 0, 3: 0}
    limit_active = declined = 0
    for trial in range(300):
        n_u = (1, 2, 2, 3)[trial % 4]
        k = int(rng.integers(1, 7))
        g_matrix, upper, weights = filter_shaped_qp(rng, n_u=n_u, k=k, limits=trial % 5 != 0)
        if upper.min() >= 0.0:
            continue  # a pass-through: the filter never calls the method
        reference = enumerated_solution(g_matrix, upper, weights)
        z = solve(g_matrix, upper, weights)
        if z is None:
            declined += 1
            continue
        assert_same_solution(z, reference, weights, g_matrix, upper)
        active = active_rows(g_matrix, upper, reference)
        seen[min(int(active.sum()), 3)] += 1
        limit_active += bool(active[k:].any())
    assert min(seen.values()) >= 10, seen
    assert limit_active >= 20 and declined <= 3, (limit_active, declined)


def test_adversarial_qps_are_solved_exactly_or_left_to_osqp():
    """Nearly parallel and duplicated rows, slack far from 0, rows of very different size,
    rows with no input term, right-hand sides that are exactly 0: an answer, when there is
    one, is the solution; the method may decline (None: OSQP solves it) but never errs."""
    rng = np.random.default_rng(4)
    answered = 0
    for trial in range(240):
        g_matrix, upper, weights = filter_shaped_qp(rng, n_u=2, k=4)
        case = trial % 6
        if case == 0:  # nearly parallel rows, both violated
            g_matrix[1] = g_matrix[0] + np.append(rng.normal(0.0, 1e-9, 2), 0.0)
            upper[:2] = -abs(upper[:2]) - 0.5
        elif case == 1:  # a duplicated row
            g_matrix[1], upper[1] = g_matrix[0], upper[0]
        elif case == 2:  # the limits make the rows infeasible: slack far from 0
            g_matrix[:4, :2] = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
            upper[:4] = -1e3 * rng.uniform(1.0, 2.0, 4)
        elif case == 3:  # rows of very different magnitude
            g_matrix[:4] *= 10.0 ** rng.uniform(-6.0, 6.0, (4, 1))
            g_matrix[:4, 2] = -1.0
        elif case == 4:  # rows with no input term: only the slack can meet them
            g_matrix[:2, :2] = 0.0
        else:  # a row exactly met at z = 0, another violated
            upper[0] = 0.0
            upper[1] = -abs(upper[1]) - 0.1
        if upper.min() >= 0.0:
            continue
        z = solve(g_matrix, upper, weights)
        if z is None:
            continue
        answered += 1
        reference = enumerated_solution(g_matrix, upper, weights)
        assert reference is not None
        assert_same_solution(z, reference, weights, g_matrix, upper)
    assert answered >= 200, answered


def test_the_certificate_refuses_what_it_cannot_prove():
    """No step possible (contradicting rows, no slack), a singular working set and too few
    steps give None, never a wrong answer."""
    unit = np.ones(2)
    contradicting = np.array([[1.0, 0.0], [-1.0, 0.0]])
    assert active_set_solution(rows=contradicting, upper=np.array([-1.0, -1.0]),
                               p_inverse=unit, tolerance=1e-12) is None
    # two rows violated whose solution needs both: one step is not enough
    rows = np.array([[1.0, 0.2], [0.2, 1.0]])
    upper = np.array([-1.0, -1.0])
    assert active_set_solution(rows=rows, upper=upper, p_inverse=unit, tolerance=1e-12,
                               max_steps=1) is None
    z = active_set_solution(rows=rows, upper=upper, p_inverse=unit, tolerance=1e-12)
    np.testing.assert_allclose(rows @ z, upper, rtol=0, atol=1e-12)
    # z = 0 already meets every row: not the method's case
    assert active_set_solution(rows=rows, upper=np.array([1.0, 0.0]), p_inverse=unit,
                               tolerance=1e-12) is None


class _CountedSolve:
    """Wraps the filter's OSQP solve and counts its calls."""

    def __init__(self, solve) -> None:
        self.solve, self.calls = solve, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.solve(*args, **kwargs)


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_filter_answers_active_qps_without_osqp(system):
    """On the shipped systems every active QP met here (two and three rows active, limits
    among them) is answered by the active-set solve: status 'solved', OSQP not called, the
    action the enumerated solution's."""
    rng = np.random.default_rng(5)
    safety_filter = shipped_filter(system)
    counted = _CountedSolve(safety_filter._solver.solve)
    safety_filter._solver.solve = counted
    n_u, k = safety_filter.n_u, safety_filter.n_barriers
    weights = 1.0 / safety_filter._p_inverse
    rows_active = {1: 0, 2: 0, 3: 0}
    for _ in range(250):
        x, u, mean, std = random_call(system, rng)
        applied = np.clip(u, safety_filter._u_min, safety_filter._u_max)
        _, g_matrix, upper = qp_arrays(safety_filter, x, applied, mean, std)
        if upper.min() >= 0.0:
            continue
        result = safety_filter.filter(x, u, mean, std)
        assert counted.calls == 0
        assert result.status == 'solved' and not result.fail_safe
        reference = enumerated_solution(g_matrix, upper, weights)
        np.testing.assert_allclose(result.u_safe, applied + reference[:n_u], rtol=0, atol=1e-9)
        assert result.slack == pytest.approx(reference[-1], rel=1e-7, abs=1e-12)
        values = upper[:k] - g_matrix[:k, :n_u] @ (result.u_safe - applied)
        np.testing.assert_allclose(result.constraint_values, values, rtol=0, atol=1e-12)
        rows_active[min(int(active_rows(g_matrix, upper, reference).sum()), 3)] += 1
    wanted = {'car_following': (1,), 'unicycle': (1, 2, 3), 'pvtol': (1, 2, 3)}[system]
    assert all(rows_active[n] >= 2 for n in wanted), rows_active


PROPERTY = settings(max_examples=120, derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow])
ENTRY = st.one_of(st.floats(-10.0, 10.0), st.floats(-1e6, 1e6),
                  st.sampled_from([0.0, -0.0, 1e-300, -1e-12, 1e-12, 1e8, -1e8, 1e12]))


@st.composite
def hostile_qp(draw: st.DrawFn) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """A shipped system, a proposal within its limits and RCBF rows of any finite size."""
    system = draw(st.sampled_from(['unicycle', 'car_following']))
    k = {'unicycle': 5, 'car_following': 2}[system]
    n_u = 1 if system == 'car_following' else 2
    lg_h = np.array(draw(st.lists(ENTRY, min_size=k * n_u, max_size=k * n_u))).reshape(k, n_u)
    if draw(st.booleans()):  # two rows nearly parallel
        lg_h[1] = lg_h[0] * (1.0 + draw(st.floats(-1e-9, 1e-9)))
    rhs = np.array(draw(st.lists(ENTRY, min_size=k, max_size=k)))
    proposal = np.array(draw(st.lists(st.floats(-2.5, 2.5), min_size=n_u, max_size=n_u)))
    return system, lg_h, rhs, proposal


FILTERS = {system: shipped_filter(system) for system in ('unicycle', 'car_following')}


def _on_rows(system: str, lg_h: np.ndarray, rhs: np.ndarray, proposal: np.ndarray
             ) -> tuple[SafetyFilter, np.ndarray, np.ndarray, list]:
    """A shipped system's filter whose QP has these RCBF rows (and its limit rows at
    ``proposal``), its G and right-hand sides, and the list its active-set solve records each
    answer in (None where it declined)."""
    safety_filter = SafetyFilter(FILTERS[system].problem, fallback=False)
    n_u, k = safety_filter.n_u, safety_filter.n_barriers
    g_matrix = np.zeros((safety_filter._nc, n_u + 1))
    g_matrix[:k, :n_u], g_matrix[:k, n_u] = -lg_h, -1.0
    upper = np.zeros(safety_filter._nc)
    upper[:k] = rhs
    if safety_filter.problem.has_limits:
        for j in range(n_u):
            g_matrix[k + j, j], g_matrix[k + n_u + j, j] = 1.0, -1.0
        upper[k:k + n_u] = safety_filter._u_max - proposal
        upper[k + n_u:] = proposal - safety_filter._u_min
    safety_filter._assemble = lambda x, u, mean, std: (
        [0.0] * k, g_matrix.tolist(), upper.tolist(),
        float(np.square(g_matrix).sum() + np.square(upper).sum()))
    calls: list = []
    method = safety_filter._active_set

    def recorded(g, b):
        calls.append(method(g, b))
        return calls[-1]

    safety_filter._active_set = recorded
    return safety_filter, g_matrix, upper, calls


@PROPERTY
@given(hostile_qp())
# A costly slack far larger than the rows: the oracle once took a point 2.5e8 outside row 3
@example(('unicycle', np.array([[0.0, 0.5], [0.0, 0.5], [0.0, 0.0], [0.0, -1e8], [0.0, 0.0]]),
          np.array([0.0, -580171.875, 1e8, 0.0, 0.0]), np.array([0.0, 0.0])))
# and, with only the rows' own terms, found no point meeting a row that its SVD met to |y| eps
@example(('car_following', np.array([[1.72934e5], [-1.192092896e-07]]),
          np.array([0.0, -16387.0]), np.array([0.0])))
def test_hostile_qp_data_never_break_the_row_check_and_match_enumeration(drawn):
    """Whatever QP data reach the solve, the filter's answer meets every row to the slack it
    reports and lies within the limits (or is the fail-safe), and an answer of the active-set
    solve is the enumerated solution."""
    system, lg_h, rhs, proposal = drawn
    safety_filter, g_matrix, upper, calls = _on_rows(system, lg_h, rhs, proposal)
    result = safety_filter.filter(np.zeros(safety_filter.n_x), proposal)
    answered = [z for z in calls if z is not None]
    if result.fail_safe:
        assert result.reason
        return
    assert np.all(result.u_safe >= safety_filter._u_min)
    assert np.all(result.u_safe <= safety_filter._u_max)
    values = rhs + lg_h @ (result.u_safe - proposal)
    scale = 1.0 + float(np.abs(rhs).max())
    assert float(values.min()) >= -max(result.slack, 0.0) - 1e-6 * scale
    if answered:
        weights = 1.0 / safety_filter._p_inverse
        reference = enumerated_solution(g_matrix, upper, weights)
        assert reference is not None
        assert_same_solution(answered[0], reference, weights, g_matrix, upper,
                             spread_data=True)



def _answer(system: str, lg_h: np.ndarray, rhs: np.ndarray, proposal: np.ndarray
            ) -> tuple[object, list]:
    """The filter's result on these RCBF rows, and what each active-set solve answered."""
    safety_filter, _, _, calls = _on_rows(system, lg_h, rhs, proposal)
    return safety_filter.filter(np.zeros(safety_filter.n_x), proposal), calls


MODERATE = st.floats(-10.0, 10.0)


@PROPERTY
@given(lg_h=st.lists(MODERATE, min_size=8, max_size=8), rhs=st.lists(MODERATE, min_size=4,
                                                                      max_size=4),
       far_row=st.lists(MODERATE, min_size=2, max_size=2), far=st.floats(1e4, 1e15),
       proposal=st.lists(st.floats(-2.5, 2.5), min_size=2, max_size=2))
# the rows of the first counterexample: met to 1 (1e-12 of 1e12), a limit crossed by 0.5
@example(lg_h=[3.0, 0.0] + [0.0, 1.0] * 3, rhs=[-6.0, 0.0, 0.0, 0.0], far_row=[0.0, 1.0],
         far=1e12, proposal=[1.0, 0.0])
def test_a_far_row_that_never_binds_changes_nothing(lg_h, rhs, far_row, far, proposal):
    """A row far from binding (right-hand side 1e4 to 1e15, |row| <= 10: it holds for every
    command within the limits) leaves the answer as a copy of another row does, exactly, and
    the active-set solve still answers: each row is met to its own scale, not the far one's."""
    lg_h, proposal = np.array(lg_h).reshape(4, 2), np.array(proposal)
    near, answered = _answer('unicycle', np.vstack([lg_h, lg_h[:1]]),
                             np.array(rhs + rhs[:1]), proposal)
    with_far, answered_far = _answer('unicycle', np.vstack([lg_h, [far_row]]),
                                     np.array(rhs + [far]), proposal)
    assert near.fail_safe == with_far.fail_safe
    if near.fail_safe:
        return
    np.testing.assert_allclose(with_far.u_safe, near.u_safe, rtol=0, atol=1e-9)
    assert with_far.slack == pytest.approx(near.slack, rel=1e-9, abs=1e-12)
    if answered and answered[0] is not None:  # solved without OSQP, so is the far one
        assert answered_far and answered_far[0] is not None
        np.testing.assert_allclose(answered_far[0], answered[0], rtol=0, atol=1e-9)


# Feasible QPs (every row holds at a command within the limits) whose rows have L_g h of 1e2
# to 5e4 at right-hand sides spread by more than ROW_SPREAD (a far row of 1.7e8 in the first):
# the certificate each row to 1e-12 of its own scale misses their round-off, and OSQP does not
# converge on them; the filter once gave the fail-safe (unverified) where it had answered.
_LARGE_GRADIENTS = [
    ([[11004.58121764222, -11004.500617683863], [-30200.815171269667, 30201.1669078712],
      [-1102.2636840169625, 9049.511171005759], [-93.69925366644979, -369.5686342031274],
      [4255.799752521216, 2246.8838519260494]],
     [-68849.94162777139, 188953.0326300837, 37946.26246035826, -1223.6699346219868,
      169138901.81319776], [-2.089450021991395, 1.9303678297274542]),
    ([[23609.48472314298, -23611.987615668942], [-48963.95660726672, 48964.74750207882],
      [-120.04471836976452, 33.34953580160927], [75.16102434194127, 2.9486873109494356],
      [8368.142639337992, -5423.387938095272]],
     [138985.30483245378, -288228.56896901794, -420.73804167419894, 185.43760189135048,
      39551.60313168301], [1.983176297476489, -1.8171551842349631]),
]


@pytest.mark.parametrize('lg_h,rhs,proposal', _LARGE_GRADIENTS)
def test_rows_of_large_gradient_at_spread_scales_are_solved_exactly(lg_h, rhs, proposal):
    """The active-set solve answers these (the rows as they are, where the scaled rows'
    certificate fails), the row check takes it (each row to its own scale), and it is the
    enumerated solution."""
    lg_h, rhs, proposal = np.array(lg_h), np.array(rhs), np.array(proposal)
    safety_filter, g_matrix, upper, calls = _on_rows('unicycle', lg_h, rhs, proposal)
    result = safety_filter.filter(np.zeros(safety_filter.n_x), proposal)
    assert not result.fail_safe, result.reason
    assert result.status == 'solved' and calls and calls[0] is not None
    weights = 1.0 / safety_filter._p_inverse
    reference = enumerated_solution(g_matrix, upper, weights)
    assert reference is not None
    assert_same_solution(np.array(calls[0]), reference, weights, g_matrix, upper,
                         spread_data=True)


def _row_check(lg_h: np.ndarray, rhs: np.ndarray, proposal: np.ndarray, step: np.ndarray,
               claimed: float) -> tuple[bool, bool]:
    """The unicycle filter's row check, on RCBF rows (4, 2) at ``proposal``, of the answer
    that moves it by ``step`` claiming slack ``claimed``: (on those rows, with a fifth row far
    from binding added). One verdict per row set, each row judged on its own."""
    safety_filter = SafetyFilter(FILTERS['unicycle'].problem, fallback=False)
    z = [*step.tolist(), claimed]
    verdicts = []
    for far in (False, True):
        lg = np.vstack([lg_h, [[1.0, -1.0]] if far else lg_h[:1]])
        upper = np.append(rhs, 1e12 if far else rhs[0])
        g_rows = np.hstack([-lg, -np.ones((5, 1))]).tolist()
        verdicts.append(safety_filter._check(z, (upper.tolist(), g_rows,
                                                 proposal.tolist())) is not None)
        many = safety_filter._check_many(z, upper, lg, proposal.tolist())
        assert (many is not None) == verdicts[-1]  # the arrays' check: the same verdict
    return verdicts[0], verdicts[1]


@PROPERTY
@given(gradient=st.floats(1e2, 1e6), direction=st.floats(-math.pi, math.pi),
       relative=st.floats(-1e-9, 1e-9), claimed=st.floats(0.0, 1e-3))
@example(gradient=1e4, direction=0.3, relative=-1e-9, claimed=0.0)
def test_the_row_check_takes_a_row_of_large_gradient_to_its_solvers_round_off(
        gradient, direction, relative, claimed):
    """A row of large L_g h (1e2 to 1e6) binding at a right-hand side of 0, met to 1e-9 of
    its terms |L_g h_j step_j| either way (what OSQP's eps_rel 1e-9 leaves of a row so
    large), passes the row check, with or without a far row; such a row once failed it (its
    scale taken as 1 + |upper_i| alone), and the filter then gave the fail-safe."""
    proposal = np.array([0.5, -0.5])
    lg_row = gradient * np.array([math.cos(direction), math.sin(direction)])
    step = np.array([-math.sin(direction), math.cos(direction)])  # along the row's boundary
    terms = float(np.abs(lg_row) @ np.abs(step))
    rhs = -float(lg_row @ step) + relative * terms  # the row's value: relative * terms
    lg_h = np.vstack([lg_row, [[0.0, 1.0]] * 3])
    assert _row_check(lg_h, np.array([rhs, 5.0, 5.0, 5.0]), proposal, step, claimed) == (
        True, True)


@PROPERTY
@given(short=st.floats(1e-5, 1.0), claimed=st.floats(0.0, 1e-3),
       lg_row=st.lists(st.floats(-10.0, 10.0), min_size=2, max_size=2))
def test_a_far_row_does_not_loosen_the_row_check(short, claimed, lg_row):
    """A row of moderate L_g h missed by 1e-5 to 1 more than the slack claimed fails the row
    check, and a far row (right-hand side 1e12) beside it changes nothing: each row is held
    to its own scale."""
    proposal, step = np.array([0.5, -0.5]), np.array([0.75, 1.25])
    lg_row = np.array(lg_row)
    terms = float(np.abs(lg_row) @ np.abs(step))
    # the row's value: claimed + short past 1e-6 of its scale, 1 + |rhs| + terms (|rhs| is at
    # most terms + 1.01 + 1e-6 (4 + 2 terms))
    rhs = -float(lg_row @ step) - claimed - short - 1e-6 * (4.0 + 2.0 * terms)
    lg_h = np.vstack([lg_row, [[0.0, 1.0]] * 3])
    assert _row_check(lg_h, np.array([rhs, 5.0, 5.0, 5.0]), proposal, step, claimed) == (
        False, False)


_SPECIAL = st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-310, -1e300, 1e300, math.inf, -math.inf,
                            math.nan])


@settings(max_examples=150, deadline=None)
@given(nz=st.sampled_from([2, 3]), m=st.integers(0, 70), seed=st.integers(0, 2**32 - 1),
       scale=st.sampled_from([1e-8, 1.0, 1e8, 1e200]),
       specials=st.lists(st.tuples(st.integers(0, 300), _SPECIAL), max_size=8))
def test_the_excess_over_arrays_is_the_loops_bit_for_bit(nz, m, seed, scale, specials):
    # the many-row path scans row^T z - upper over arrays from ARRAY_EXCESS_ROWS rows on: the
    # same list as the Python loop's, each sum in the loop's order (round-off, NaN, inf,
    # signed zeros and overflow included)
    rng = np.random.default_rng(seed)
    values = rng.normal(size=m * nz + m + nz) * scale
    for where, special in specials:
        values[where % values.size] = special
    rows = values[:m * nz].reshape(m, nz).tolist()
    upper, z = values[m * nz:m * nz + m].tolist(), values[m * nz + m:].tolist()
    loop = filter_module._kernels([1.0] * nz)[1](rows, upper, z)
    with np.errstate(all='ignore'):
        arrays = filter_module._excess_over(np.array(rows).reshape(m, nz).T.copy(),
                                            np.array(upper))(rows, upper, z)
    arrays, loop = np.array(arrays, dtype=np.float64), np.array(loop, dtype=np.float64)
    nan = np.isnan(loop)
    assert np.array_equal(np.isnan(arrays), nan)
    assert arrays[~nan].tobytes() == loop[~nan].tobytes()  # the sign of a zero too

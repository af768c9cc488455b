"""The per-step OSQP safety filter (rcbf_ros.core.filter) against independent references.

References, none of them the code under test:
- cvxpy + Clarabel (an interior-point solver) on the RCBF-QP written out here from the paper
  (min ||u_S||^2 + l eps^2, or sum_j w_j u_S,j^2 with the config's input weights,
  s.t. L_f h + L_g h (u_RL + u_S) + alpha h + rho + eps >= 0, limits),
  with rho = grad h^T mean - k_c |grad h|^T std computed here, and, on the unicycle, h and its
  Lie derivatives written out by hand (on PVTOL and cars: checked by finite differences);
- the closed form of the soft QP with a single active row and no limits:
  u_S = -r W^-1 a / (a^T W^-1 a + 1/l), eps = -r / (l a^T W^-1 a + 1) with a = L_g h,
  r = row value at u_RL, W = diag(input weights);
- a minimal-slack LP (cvxpy): eps_min = min eps s.t. the rows and the limits; every feasible
  point of the filter's QP has eps >= eps_min, and eps_min <= 0 means the rows are satisfiable.
"""
from __future__ import annotations

import cvxpy as cp
from filter_paths import osqp_only
import numpy as np
import pytest
from scipy.optimize import linprog
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.dynamics import step_euler
from rcbf_ros.core.filter import InputBounds, SafetyFilter
from rcbf_ros.envs.nominal import unicycle_go_to_goal
from rcbf_ros.learning.safety_layer import DifferentiableSafetyLayer
from rcbf_ros.parameters.rules import find_config, load_params

SYSTEMS = ('unicycle', 'pvtol', 'car_following')
# OSQP's default cap (4000) is too small for some PVTOL states and for infeasible rows (slack
# weight 1e6 makes the QP ill-conditioned): see test_default_iteration_cap_*. Accuracy tests
# therefore give OSQP room; the cap itself is tested separately.
ROOMY_MAX_ITER = 40000


def config_for(system: str, **overrides):
    params = load_params(find_config(system), 'safety_filter')
    params.update(overrides)
    return filter_config_from_params(params)


def random_state(system: str, rng: np.random.Generator) -> np.ndarray:
    if system == 'unicycle':
        return np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
    if system == 'pvtol':  # inside the filter's envelope (arena less 0.3 m, thrust band)
        x1 = rng.uniform(-5.5, 5.5)
        return np.array([x1, rng.uniform(-2.5, 2.5), *rng.uniform(-1.0, 1.0, 2),
                         rng.uniform(-0.5, 0.5), rng.uniform(0.6, 1.4),
                         x1 + rng.uniform(-0.7, 0.7)])
    positions = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + rng.normal(0.0, 1.0, 5)
    velocities = 30.0 + rng.normal(0.0, 2.0, 5)
    return np.stack([positions, velocities], axis=1).reshape(-1)


def lie_terms(problem, x: np.ndarray, u: np.ndarray | None = None):
    """h, grad h, L_f h, L_g h at one state (numpy), via the problem's barrier families; the
    proposal u picks the unicycle's look-ahead point (None: the point ahead)."""
    terms = problem.terms(torch.from_numpy(x).unsqueeze(0),
                          None if u is None else torch.from_numpy(u).unsqueeze(0))
    return (terms.h[0].numpy(), terms.grad_h[0].numpy(), terms.lf_h[0].numpy(),
            terms.lg_h[0].numpy())


def reference_solution(problem, x, u_rl, mean, std, limits=True):
    """u_safe and eps of the RCBF-QP solved by Clarabel, from the paper's formulation."""
    h, grad, _, _ = lie_terms(problem, x, u_rl)
    system = problem.system
    xt = torch.from_numpy(x).unsqueeze(0)
    f = system.f(xt)[0].numpy()
    g = system.g(xt)[0].numpy()
    lf_h, lg_h = grad @ f, grad @ g
    rho = grad @ mean - problem.k_c * np.abs(grad) @ std
    u_s = cp.Variable(system.n_u)
    eps = cp.Variable()
    rows = lf_h + lg_h @ (u_rl + u_s) + problem.alpha * h + rho + eps >= 0
    constraints = [rows]
    if limits and problem.has_limits:
        constraints += [u_rl + u_s <= np.array(system.u_max),
                        u_rl + u_s >= np.array(system.u_min)]
    weights = np.ones(system.n_u) if problem.input_weight is None else np.array(
        problem.input_weight)
    objective = cp.Minimize(weights @ cp.square(u_s) + problem.slack_weight * cp.square(eps))
    cp.Problem(objective, constraints).solve(solver=cp.CLARABEL, tol_gap_abs=1e-12,
                                             tol_gap_rel=1e-12, tol_feas=1e-12)
    return u_rl + u_s.value, float(eps.value)


def minimal_slack(problem, x, u_rl, mean, std) -> float:
    """min eps such that every RCBF row (as chosen for the proposal u_rl) holds within the
    input limits (an LP, HiGHS)."""
    h, grad, lf_h, lg_h = lie_terms(problem, x, u_rl)
    rho = grad @ mean - problem.k_c * np.abs(grad) @ std
    system = problem.system
    # Variables [u, eps]: -(L_g h u) - eps <= L_f h + alpha h + rho.
    a_ub = np.hstack([-lg_h, -np.ones((h.size, 1))])
    b_ub = lf_h + problem.alpha * h + rho
    limits = (list(zip(system.u_min, system.u_max)) if problem.has_limits
              else [(None, None)] * system.n_u)
    lp = linprog(np.r_[np.zeros(system.n_u), 1.0], A_ub=a_ub, b_ub=b_ub,
                 bounds=[*limits, (None, None)])
    if lp.status == 3:  # unbounded below: the rows hold with any margin
        return -np.inf
    assert lp.status == 0, lp.message
    return float(lp.x[-1])


@pytest.mark.parametrize('system, overrides', [
    *((system, {}) for system in SYSTEMS),
    ('pvtol', {'input_weight': [0.3, 1.5]}),
    ('unicycle', {'input_weight': [1.0, 1.0]}),
])
def test_matches_clarabel_on_random_states(system, overrides):
    rng = np.random.default_rng(7)
    config = config_for(system, **overrides)
    problem = config.problem
    safety_filter = SafetyFilter(problem, max_iter=ROOMY_MAX_ITER)
    n_x, n_u = problem.system.n_x, problem.system.n_u
    active = 0
    for _ in range(40):
        x = random_state(system, rng)
        u_rl = rng.uniform(-3.0, 3.0, n_u)
        mean = rng.normal(0.0, 0.05, n_x)
        std = np.abs(rng.normal(0.0, 0.05, n_x))
        result = safety_filter.filter(x, u_rl, mean, std)
        assert not result.fail_safe, result.status
        # The filter clips the proposal to the limits before the QP: the smallest correction
        # is measured from the command the plant can take.
        applied = (np.clip(u_rl, problem.system.u_min, problem.system.u_max)
                   if problem.has_limits else u_rl)
        expected, expected_eps = reference_solution(problem, x, applied, mean, std)
        # An infeasible state (slack > 0: PVTOL's envelope rows can conflict) makes the QP
        # badly scaled (slack weight 1e6): the two solvers then agree to 1e-5, not 1e-6.
        atol = 1e-6 if expected_eps < 1e-6 else 1e-5
        if problem.has_limits and np.any(
                np.minimum(expected - problem.system.u_min, problem.system.u_max - expected)
                < 1e-5):
            atol = 1e-5  # the interior point stops short of an active limit by a few 1e-6
        np.testing.assert_allclose(result.u_safe, expected, rtol=0, atol=atol)
        assert result.slack == pytest.approx(expected_eps, abs=1e-6)
        active += bool(np.any(np.abs(result.u_s) > 1e-6))
    assert active >= 5  # the comparison exercised active rows, not only pass-through


def test_unicycle_lie_derivatives_match_hand_written_barrier():
    config = config_for('unicycle')
    obstacles = load_params(find_config('unicycle'), 'safety_filter')
    centers = np.stack([obstacles['obstacles.x'], obstacles['obstacles.y']], axis=1)
    delta = np.array(obstacles['obstacles.radius']) + obstacles['obstacles.margin']
    lp = obstacles['obstacles.lookahead']
    rng = np.random.default_rng(3)
    for _ in range(10):
        x, y, th = rng.uniform(-3.0, 3.0), rng.uniform(-3.0, 3.0), rng.uniform(-np.pi, np.pi)
        p = np.array([x + lp * np.cos(th), y + lp * np.sin(th)])
        d = p - centers
        h_hand = (d ** 2).sum(1) - delta ** 2
        # x_dot = [v cos th, v sin th, omega]: dp/dt = v (cos, sin) + omega l_p (-sin, cos)
        lg_hand = np.stack([2 * d @ [np.cos(th), np.sin(th)],
                            2 * lp * d @ [-np.sin(th), np.cos(th)]], axis=1)
        h, _, lf_h, lg_h = lie_terms(config.problem, np.array([x, y, th]))
        np.testing.assert_allclose(h, h_hand, atol=1e-12)
        np.testing.assert_allclose(lf_h, 0.0, atol=1e-12)
        np.testing.assert_allclose(lg_h, lg_hand, atol=1e-12)


def test_a_reversing_proposal_guards_the_point_behind_once_it_is_clear():
    # Hand-written rows for both points; the point behind is used exactly when the proposal
    # reverses AND that point is outside every obstacle's delta.
    config = config_for('unicycle')
    obstacles = load_params(find_config('unicycle'), 'safety_filter')
    assert obstacles['obstacles.speed_input'] == 0
    centers = np.stack([obstacles['obstacles.x'], obstacles['obstacles.y']], axis=1)
    delta = np.array(obstacles['obstacles.radius']) + obstacles['obstacles.margin']
    lp = obstacles['obstacles.lookahead']

    def hand(x, y, th, offset):
        d = np.array([x + offset * np.cos(th), y + offset * np.sin(th)]) - centers
        lg = np.stack([2 * d @ [np.cos(th), np.sin(th)],
                       2 * offset * d @ [-np.sin(th), np.cos(th)]], axis=1)
        return (d ** 2).sum(1) - delta ** 2, lg

    rng = np.random.default_rng(4)
    seen = {'ahead': 0, 'behind': 0, 'behind_blocked': 0}
    for k in range(400):
        if k % 2:  # on the rim of an obstacle, where the two points disagree
            c, angle = centers[rng.integers(len(centers))], rng.uniform(-np.pi, np.pi)
            x, y = c + (delta[0] + rng.uniform(-0.04, 0.04)) * np.array(
                [np.cos(angle), np.sin(angle)])
        else:
            x, y = rng.uniform(-3.0, 3.0, 2)
        th = rng.uniform(-np.pi, np.pi)
        u = np.array([rng.uniform(-2.5, 2.5), rng.uniform(-2.5, 2.5)])
        h, _, lf_h, lg_h = lie_terms(config.problem, np.array([x, y, th]), u)
        h_ahead, lg_ahead = hand(x, y, th, lp)
        h_behind, lg_behind = hand(x, y, th, -lp)
        if u[0] < 0 and np.all(h_behind >= 0):
            want_h, want_lg, case = h_behind, lg_behind, 'behind'
        else:
            want_h, want_lg = h_ahead, lg_ahead
            case = 'behind_blocked' if u[0] < 0 else 'ahead'
        seen[case] += 1
        np.testing.assert_allclose(h, want_h, atol=1e-12)
        np.testing.assert_allclose(lf_h, 0.0, atol=1e-12)
        np.testing.assert_allclose(lg_h, want_lg, atol=1e-12)
    assert min(seen.values()) >= 10, seen
    # Without a proposal: the point ahead for the QP's rows; for judging a recorded state
    # (state_h), the point behind where it is clear, since a reversing robot may be there.
    x = np.array([0.5, -0.3, 2.0])
    np.testing.assert_allclose(lie_terms(config.problem, x)[0], hand(*x, lp)[0], atol=1e-12)
    # facing the centre obstacle from just outside: the point ahead is in, the point behind out
    x = np.array([-0.6 - 0.1 - 0.02, 0.0, 0.0])
    ahead, behind = hand(*x, lp)[0], hand(*x, -lp)[0]
    assert ahead[0] < 0 < behind[0] and np.all(behind >= 0)
    state_h = config.problem.state_h(torch.from_numpy(x)[None])[0].numpy()
    np.testing.assert_allclose(state_h, np.maximum(ahead, behind), atol=1e-12)
    x = np.array([-0.6 - 0.1 + 0.04, 0.0, 0.0])  # both points in: the state is outside the set
    assert hand(*x, -lp)[0][0] < 0
    assert config.problem.state_h(torch.from_numpy(x)[None])[0, 0] < 0


@pytest.mark.parametrize('system', ('pvtol', 'car_following'))
def test_barrier_gradients_match_finite_differences(system):
    problem = config_for(system).problem
    rng = np.random.default_rng(11)
    for _ in range(5):
        x = random_state(system, rng)
        _, grad, _, _ = lie_terms(problem, x)
        step = 1e-6
        for i in range(x.size):
            dx = np.zeros_like(x)
            dx[i] = step
            fd = (lie_terms(problem, x + dx)[0] - lie_terms(problem, x - dx)[0]) / (2 * step)
            np.testing.assert_allclose(grad[:, i], fd, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize('input_weight', [[], [1.0, 0.01], [3.0, 0.5]])
def test_single_active_row_is_the_soft_projection(input_weight):
    # One obstacle, no input limits: the QP has one row, solved in closed form.
    config = config_for('unicycle', **{'obstacles.x': [0.0], 'obstacles.y': [0.0],
                                       'obstacles.radius': [0.6], 'input_limits.min': [],
                                       'input_limits.max': [], 'input_weight': input_weight})
    problem = config.problem
    assert problem.n_barriers == 1 and not problem.has_limits
    w_inv = 1.0 / np.array(input_weight or [1.0, 1.0])
    safety_filter = SafetyFilter(problem)
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(30):
        x = np.array([*rng.uniform(-2.0, 2.0, 2), rng.uniform(-np.pi, np.pi)])
        u_rl = rng.uniform(-3.0, 3.0, 2)
        h, _, lf_h, lg_h = lie_terms(problem, x, u_rl)
        a = lg_h[0]
        r = lf_h[0] + a @ u_rl + problem.alpha * h[0]
        result = safety_filter.filter(x, u_rl)
        if r >= 0:
            continue
        l = problem.slack_weight  # noqa: E741 - the paper's name
        a_w_a = a @ (w_inv * a)
        u_s = -r * w_inv * a / (a_w_a + 1.0 / l)
        eps = -r / (l * a_w_a + 1.0)
        np.testing.assert_allclose(result.u_s, u_s, rtol=0, atol=1e-6)
        assert result.slack == pytest.approx(eps, abs=1e-9)
        checked += 1
    assert checked >= 5


def test_pass_through_is_exact_on_a_fresh_filter():
    config = config_for('unicycle')
    safety_filter = SafetyFilter(config.problem)
    x = np.array([-2.5, -2.5, -0.75 * np.pi])  # corner, heading away from every obstacle
    u_rl = np.array([1.0, 0.3])
    result = safety_filter.filter(x, u_rl)
    assert np.all(result.constraint_values > 0)
    assert np.array_equal(result.u_safe, u_rl) and not result.active


def test_pass_through_is_exact_after_an_active_solve():
    config = config_for('unicycle')
    safety_filter = SafetyFilter(config.problem)
    safety_filter.filter([-0.85, 0.0, 0.0], [2.5, 0.0])  # active: leaves a warm start behind
    x = np.array([-2.5, -2.5, -0.75 * np.pi])
    u_rl = np.array([1.0, 0.3])
    result = safety_filter.filter(x, u_rl)
    assert np.array_equal(result.u_safe, u_rl)


def test_pass_through_within_round_off_whenever_no_row_is_active():
    rng = np.random.default_rng(13)
    config = config_for('unicycle')
    safety_filter = SafetyFilter(config.problem)
    inactive = 0
    for _ in range(60):
        x = random_state('unicycle', rng)
        u_rl = rng.uniform(-2.4, 2.4, 2)
        h, _, lf_h, lg_h = lie_terms(config.problem, x, u_rl)
        rows = lf_h + lg_h @ u_rl + config.problem.alpha * h
        result = safety_filter.filter(x, u_rl)
        if np.all(rows > 1e-9):
            # Exact: rows that hold at z = 0 pass the proposal through without a solve.
            np.testing.assert_allclose(result.u_safe, u_rl, rtol=0, atol=1e-9)
            inactive += 1
        else:
            assert np.any(np.abs(result.u_s) > 0)
    assert inactive >= 10


@pytest.mark.parametrize('system', SYSTEMS)
def test_slack_is_positive_only_when_rows_are_infeasible_within_limits(system):
    rng = np.random.default_rng(17)
    problem = config_for(system).problem
    safety_filter = SafetyFilter(problem, max_iter=ROOMY_MAX_ITER)
    n_x, n_u = problem.system.n_x, problem.system.n_u
    feasible = infeasible = 0
    for _ in range(60):
        x = random_state(system, rng)
        if system == 'unicycle' and rng.uniform() < 0.5:
            x[:2] = rng.uniform(-0.5, 0.5, 2)  # inside the centre obstacle: often infeasible
        u_rl = rng.uniform(-3.0, 3.0, n_u)
        mean, std = np.zeros(n_x), np.abs(rng.normal(0.0, 0.05, n_x))
        eps_min = minimal_slack(problem, x, u_rl, mean, std)
        result = safety_filter.filter(x, u_rl, mean, std)
        assert not result.fail_safe, result.status
        if eps_min <= -1e-6:
            # Satisfiable rows: only the soft penalty's eps ~ |u_S| / (l |L_g h|) remains
            # (grows with the correction: car states can need |u_S| ~ 200).
            assert result.slack < 1e-4 * max(1.0, float(np.abs(result.u_s).max()))
            feasible += 1
        elif eps_min > 1e-3:
            assert result.slack >= eps_min - 1e-6
            infeasible += 1
    assert feasible >= 5
    assert infeasible >= (3 if system == 'unicycle' else 0)


def test_default_iteration_cap_solves_random_pvtol_states():
    rng = np.random.default_rng(7)
    problem = config_for('pvtol').problem
    safety_filter = SafetyFilter(problem)
    statuses = set()
    for _ in range(200):
        x = random_state('pvtol', rng)
        result = safety_filter.filter(x, rng.uniform(-3.0, 3.0, problem.system.n_u))
        statuses.add(result.status)
        assert not result.fail_safe, result.status
    # OSQP stalls on some of these; the interior-point fallback must then have solved them.
    assert statuses <= {'solved', 'solved_inaccurate', 'solved_interior_point'}


def test_starved_solver_returns_fail_safe_with_status():
    config = config_for('unicycle')
    safety_filter = osqp_only(SafetyFilter(config.problem, fail_safe_action=[0.5, -2.5],
                                           max_iter=1, fallback=False))
    result = safety_filter.filter([-0.85, 0.0, 0.0], [2.5, 0.0])
    assert result.fail_safe and result.active
    assert result.status == 'unverified' and 'iterations' in result.reason
    np.testing.assert_array_equal(result.u_safe, [0.5, -2.5])
    assert np.isnan(result.slack)


class _LyingSolver:
    """Wraps OSQP and reports 'solved' with an answer of another problem (zero correction)."""

    def __init__(self, solver):
        self.solver = solver

    def __getattr__(self, name):
        return getattr(self.solver, name)

    def solve(self, raise_error=False):
        result = self.solver.solve(raise_error=raise_error)
        result.x[:] = 0.0
        return result


@pytest.mark.parametrize('fallback', [False, True])
def test_a_solver_answer_that_breaks_the_rows_is_never_published(fallback):
    problem = config_for('unicycle').problem
    state, u_rl = [-0.85, 0.0, 0.0], [2.5, 0.0]
    honest = SafetyFilter(problem).filter(state, u_rl)
    safety_filter = SafetyFilter(problem, fallback=fallback)
    osqp_only(safety_filter)._solver = _LyingSolver(safety_filter._solver)
    result = safety_filter.filter(state, u_rl)
    if fallback:  # the interior point solves the same QP, and its answer passes the check
        assert result.status == 'solved_interior_point' and not result.fail_safe
        np.testing.assert_allclose(result.u_safe, honest.u_safe, atol=1e-6)
    else:
        assert result.fail_safe and result.status == 'unverified'
        np.testing.assert_array_equal(result.u_safe, [0.0, 0.0])


def test_interior_point_fallback_solves_what_a_starved_osqp_cannot():
    config = config_for('unicycle')
    state, u_rl = [-0.85, 0.0, 0.0], [2.5, 0.0]
    reference = SafetyFilter(config.problem).filter(state, u_rl)
    fallback = osqp_only(SafetyFilter(config.problem, max_iter=1)).filter(state, u_rl)
    assert reference.status == 'solved' and fallback.status == 'solved_interior_point'
    assert not fallback.fail_safe
    np.testing.assert_allclose(fallback.u_safe, reference.u_safe, atol=1e-6)


@pytest.mark.parametrize('kwargs, field', [
    ({'state': [0.0, 0.0]}, 'state'),
    ({'u_rl': [1.0, 2.0, 3.0]}, 'u_rl'),
    ({'std': [0.0, 0.1]}, 'disturbance_std'),
    ({'mean': ['a', 0.0, 0.0]}, 'disturbance_mean'),
])
def test_wrong_shape_raises_naming_the_field(kwargs, field):
    safety_filter = SafetyFilter(config_for('unicycle').problem)
    args = {'state': [0.0, 2.0, 0.0], 'u_rl': [0.0, 0.0], 'mean': None, 'std': None}
    args.update(kwargs)
    with pytest.raises(ValueError, match=f'^{field}:'):
        safety_filter.filter(args['state'], args['u_rl'], args['mean'], args['std'])


@pytest.mark.parametrize('kwargs, field', [
    ({'state': [0.0, np.nan, 0.0]}, 'state'),
    ({'state': [1e300, 0.0, 0.0]}, 'state'),
    ({'u_rl': [np.inf, 0.0]}, 'u_rl'),
    ({'u_rl': [1e7, 0.0]}, 'u_rl'),
    ({'std': [0.0, -0.1, 0.0]}, 'disturbance_std'),
    ({'std': [0.0, 1e300, 0.0]}, 'disturbance_std'),
    ({'mean': [np.nan, 0.0, 0.0]}, 'disturbance_mean'),
])
def test_bad_values_give_the_fail_safe_naming_the_field(kwargs, field):
    safety_filter = SafetyFilter(config_for('unicycle').problem, fail_safe_action=[0.0, 0.5])
    args = {'state': [0.0, 2.0, 0.0], 'u_rl': [0.0, 0.0], 'mean': None, 'std': None}
    args.update(kwargs)
    result = safety_filter.filter(args['state'], args['u_rl'], args['mean'], args['std'])
    assert result.fail_safe and result.status == 'input_refused'
    assert result.reason.startswith(f'{field}:'), result.reason
    np.testing.assert_array_equal(result.u_safe, [0.0, 0.5])


@pytest.mark.parametrize('u_v', [1e6, 1e3, 2.6])
def test_proposals_beyond_the_limits_are_clipped_before_the_qp(u_v):
    # The obstacle at the origin lies 0.25 m ahead of the look-ahead point: at full speed the
    # rows bind. Clipping after the QP let huge proposals through at full speed.
    problem = config_for('unicycle').problem
    safety_filter = SafetyFilter(problem, slack_tolerance=1e-4)
    x = np.array([-0.85 - 0.03 - 0.25 + 0.7, 0.0, 0.0])
    at_limit = safety_filter.filter(x, [2.5, 0.0])
    result = safety_filter.filter(x, [u_v, 0.0])
    assert not result.fail_safe and result.proposal_clipped
    np.testing.assert_allclose(result.u_safe, at_limit.u_safe, rtol=0, atol=1e-9)
    assert at_limit.u_safe[0] < 2.0  # the filter brakes
    h, _, lf_h, lg_h = lie_terms(problem, x, np.array([2.5, 0.0]))
    rows = lf_h + lg_h @ result.u_safe + problem.alpha * h
    assert np.all(rows >= -1e-4)


def test_osqp_refusing_huge_data_never_returns_the_previous_answer():
    # Beyond ~1e30 OSQP keeps the previous problem; such data must be refused, and the next
    # call must not depend on what came before.
    problem = config_for('unicycle').problem
    x, u = [-0.4, 0.0, 0.0], [2.5, 0.0]
    fresh = SafetyFilter(problem).filter(x, u)
    used = SafetyFilter(problem, input_bounds=InputBounds(state=1e300, disturbance=1e300))
    used.filter([-2.5, -2.5, 0.0], [1.0, 0.0])
    refused = used.filter(x, u, std=[1e200, 1e200, 0.0])
    assert refused.fail_safe and refused.status == 'input_refused'
    np.testing.assert_allclose(used.filter(x, u).u_safe, fresh.u_safe, rtol=0, atol=1e-9)


def test_fail_safe_action_outside_the_limits_is_refused():
    with pytest.raises(ValueError, match='^fail_safe_action: .* outside the input limits'):
        SafetyFilter(config_for('unicycle').problem, fail_safe_action=[99.0, 0.0])


def _drive_past_one_obstacle(input_weight, y0: float, steps: int = 600, *,
                             reverse: bool = False, speed_input: int = 0):
    """Go-to-goal from (-2, y0) to (2, 0) through the filter, one obstacle of radius 0.6 at the
    origin on the straight line between them; ``reverse``: the same controller on the robot
    turned around, so it drives there backwards; ``speed_input`` -1: the look-ahead point
    always ahead. Returns (steps to the goal or None, final state, min clearance of the robot's
    centre from the obstacle's true circle)."""
    config = config_for('unicycle', **{'obstacles.x': [0.0], 'obstacles.y': [0.0],
                                       'obstacles.radius': [0.6],
                                       'obstacles.speed_input': speed_input,
                                       'input_weight': input_weight})
    safety_filter = SafetyFilter(config.problem)
    x, goal, clearance = np.array([-2.0, y0, np.pi if reverse else 0.0]), (2.0, 0.0), np.inf
    for k in range(steps):
        if reverse:
            v, omega = unicycle_go_to_goal(x + np.array([0.0, 0.0, np.pi]), goal)
            nominal = np.array([-v, omega])
        else:
            nominal = unicycle_go_to_goal(x, goal)
        u = safety_filter.filter(x, nominal).u_safe
        x = step_euler(config.problem.system, torch.from_numpy(x)[None],
                       torch.from_numpy(u)[None], 0.02)[0].numpy()
        clearance = min(clearance, float(np.hypot(x[0], x[1])) - 0.6)
        if np.hypot(x[0] - goal[0], x[1] - goal[1]) < 0.3:
            return k, x, clearance
    return None, x, clearance


@pytest.mark.parametrize('y0', [0.02, 0.2])
def test_cheap_steering_weight_turns_a_deadlock_into_a_detour(y0):
    # With the paper's ||u_S||^2, omega reaches L_g h only through the look-ahead l_p = 0.03, so
    # the smallest correction brakes: the robot stops at the boundary, facing the obstacle,
    # while the nominal controller keeps pointing at the goal behind it. A small omega weight
    # makes turning the cheaper correction, and the robot goes around. Both stay safe.
    steps, x, clearance = _drive_past_one_obstacle([1.0, 1.0], y0)
    assert steps is None and x[0] < -0.6 and clearance > 0.0
    steps, x, clearance = _drive_past_one_obstacle([1.0, 0.01], y0)
    assert steps is not None and clearance > 0.0


@pytest.mark.parametrize('y0', [0.02, 0.2, 0.8])
def test_a_reversing_robot_passes_with_the_point_behind(y0):
    # With the look-ahead point always ahead (speed_input -1, the reference's filter), a robot
    # driving backwards trails it: the cheap turn that moves it off the obstacle turns the
    # direction of travel onto the obstacle, and braking is all that is left, even well off
    # the obstacle's centre line, where the same controller driving forwards passes. With the
    # point following the direction of travel (config/unicycle.yaml), reversing is the mirror
    # image of driving forwards and the robot passes too. Every run keeps the centre outside
    # the true circle by more than margin - 3 l_p.
    steps, x, clearance = _drive_past_one_obstacle([1.0, 0.01], y0, reverse=True,
                                                   speed_input=-1)
    assert steps is None and x[0] < -0.4 and clearance > 0.1 - 3 * 0.03
    steps, _, clearance = _drive_past_one_obstacle([1.0, 0.01], y0, reverse=True)
    assert steps is not None and clearance > 0.1 - 3 * 0.03
    steps, _, clearance = _drive_past_one_obstacle([1.0, 0.01], y0)
    assert steps is not None and clearance > 0.1 - 3 * 0.03


def test_chattering_direction_of_travel_keeps_the_centre_clear():
    # The worst case for a point that switches with the sign of v: starts on the filter's
    # boundary (the centre 0.07-0.13 outside a true circle), proposals at full speed toward
    # the obstacle that flip direction at random every other step. The bound of barrier_terms
    # (the centre at least margin - 3 l_p = 0.01 outside every true circle) must hold at every
    # step, and the point behind must really have been in use.
    problem = config_for('unicycle').problem
    safety_filter = SafetyFilter(problem)
    params = load_params(find_config('unicycle'), 'safety_filter')
    centers = np.stack([params['obstacles.x'], params['obstacles.y']], axis=1)
    radius = np.array(params['obstacles.radius'])
    rng = np.random.default_rng(21)
    worst, switches, behind = np.inf, 0, 0
    for _ in range(24):
        while True:
            i, angle = rng.integers(len(centers)), rng.uniform(-np.pi, np.pi)
            offset = (radius[i] + rng.uniform(0.07, 0.13)) * np.array([np.cos(angle),
                                                                       np.sin(angle)])
            x = np.array([*(centers[i] + offset), rng.uniform(-np.pi, np.pi)])
            if lie_terms(problem, x)[0].min() >= 0:  # inside the filter's safe set
                break
        sign = 1.0
        for _ in range(100):
            if rng.uniform() < 0.5:
                sign, switches = -sign, switches + 1
            to_obstacle = np.arctan2(*(centers[i] - x[:2])[::-1])
            error = (to_obstacle + (0.0 if sign > 0 else np.pi) - x[2] + np.pi) % (
                2 * np.pi) - np.pi
            u_rl = np.array([sign * 2.5, np.clip(3.0 * error + rng.normal(0.0, 1.0), -2.5, 2.5)])
            result = safety_filter.filter(x, u_rl)
            assert not result.fail_safe
            behind += not np.allclose(result.h, lie_terms(problem, x)[0], rtol=0, atol=1e-12)
            x = step_euler(problem.system, torch.from_numpy(x)[None],
                           torch.from_numpy(result.u_safe)[None], 0.02)[0].numpy()
            worst = min(worst, float((np.hypot(*(x[:2] - centers).T) - radius).min()))
    assert switches > 800 and behind > 500, (switches, behind)
    assert worst > 0.1 - 3 * 0.03, worst


@pytest.mark.parametrize('system, overrides', [
    *((system, {}) for system in SYSTEMS),
    ('pvtol', {'input_weight': [0.3, 1.5]}),
])
def test_differentiable_layer_gives_the_filters_action(system, overrides):
    # The learner's layer (diffqp) and the per-step filter (OSQP) solve the QP that ONE
    # RCBFProblem builds, input weights included.
    rng = np.random.default_rng(11)
    problem = config_for(system, **overrides).problem
    safety_filter = SafetyFilter(problem, max_iter=ROOMY_MAX_ITER)
    n_x, n_u = problem.system.n_x, problem.system.n_u
    states = np.stack([random_state(system, rng) for _ in range(32)])
    u_rl = rng.uniform(-3.0, 3.0, (32, n_u))
    mean = rng.normal(0.0, 0.05, (32, n_x))
    std = np.abs(rng.normal(0.0, 0.05, (32, n_x)))
    layer = DifferentiableSafetyLayer(problem, lambda x: (torch.from_numpy(mean),
                                                          torch.from_numpy(std)))
    batch = layer(torch.from_numpy(states), torch.from_numpy(u_rl)).numpy()
    active = 0
    for b in range(32):
        result = safety_filter.filter(states[b], u_rl[b], mean[b], std[b])
        np.testing.assert_allclose(batch[b], result.u_safe, rtol=0, atol=1e-5)
        active += bool(result.active)
    assert active >= 3


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_active_set_solve_is_exact_and_osqp_answers_what_it_leaves(system):
    """Where the active-set method certifies its answer (one, two or three rows active, limits
    among them), the filter returns it (Clarabel agrees to 1e-8, closer than OSQP's
    tolerance); where it gives way, OSQP's answer is the one returned."""
    rng = np.random.default_rng(11)
    problem = config_for(system).problem
    safety_filter = SafetyFilter(problem, max_iter=ROOMY_MAX_ITER)
    taken: list[bool] = []
    active_set = safety_filter._active_set

    def counting(g_matrix, upper):
        z = active_set(g_matrix, upper)
        taken.append(z is not None)
        return z

    safety_filter._active_set = counting
    n_x, n_u = problem.system.n_x, problem.system.n_u
    exact = by_osqp = 0
    for _ in range(80):
        x = random_state(system, rng)
        u_rl = rng.uniform(-3.0, 3.0, n_u)
        mean = rng.normal(0.0, 0.05, n_x)
        std = np.abs(rng.normal(0.0, 0.05, n_x))
        taken.clear()
        result = safety_filter.filter(x, u_rl, mean, std)
        if not taken:
            continue  # passed through: no row active
        applied = (np.clip(u_rl, problem.system.u_min, problem.system.u_max)
                   if problem.has_limits else u_rl)
        expected, expected_eps = reference_solution(problem, x, applied, mean, std)
        if taken[0]:
            exact += 1
            assert result.status == 'solved'
            np.testing.assert_allclose(result.u_safe, expected, rtol=0, atol=1e-8)
            assert result.slack == pytest.approx(expected_eps, abs=1e-9)
        else:
            by_osqp += 1
            assert not result.fail_safe
            np.testing.assert_allclose(result.u_safe, expected, rtol=0, atol=1e-5)
    assert exact >= 5, (exact, by_osqp)

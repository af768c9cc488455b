"""Many circle obstacles: the rows over arrays (rcbf_ros.core.lie_closed_form_rows) and the QP
that carries only the rows that can bind (SafetyFilter's many-row path, binding_rows).

References, none of them the code under test: the generated per-row closed form
(ClosedFormAssembly, itself held to autograd by test_lie_closed_form), the batched autograd
path (RCBFProblem.qp), the exact active-set solve over EVERY row (no row left out), and the
rows' values at the vertices of the input box.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

from hypothesis import assume, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_lean_filter import _BLOCK_TORCH, _env_with_tests
from test_lie_closed_form import assert_close, problems, random_state, shipped
import torch

from rcbf_ros.core.config import filter_config_from_params, OBSTACLE_LIMIT
import rcbf_ros.core.filter as filter_module
from rcbf_ros.core.filter import (
    _many_as_lists,
    active_set_solution,
    ACTIVE_SET_TOLERANCE,
    binding_rows,
    PRUNE_MARGIN,
    SafetyFilter,
)
from rcbf_ros.core.lie_closed_form import ClosedFormAssembly
from rcbf_ros.core.lie_closed_form_rows import product, SMALL_PRODUCT, VectorAssembly
from rcbf_ros.node_logic import safety_filter as logic

PROPERTY = settings(max_examples=60, derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


def world(system: str, rng: np.random.Generator, count: int, *, spread: float = 4.0,
          cascaded: bool | None = None) -> dict:
    """The shipped config of ``system`` with ``count`` random circles (the unicycle's with its
    look-ahead point and the direction-of-travel switch, or without them, cascaded)."""
    params = shipped(system)
    params.update({'obstacles.x': rng.uniform(-spread, spread, count).tolist(),
                   'obstacles.y': rng.uniform(-spread / 2, spread / 2, count).tolist(),
                   'obstacles.radius': rng.uniform(0.05, 0.4, count).tolist()})
    if system == 'unicycle':
        params['obstacles.speed_input'] = 0
        if cascaded:
            params.update({'obstacles.lookahead': 0.0, 'obstacles.speed_input': -1,
                           'obstacles.gammas': [float(rng.uniform(0.5, 3.0))]})
    return params


def inputs(system: str, rng: np.random.Generator, n_x: int, n_u: int) -> list[list[float]]:
    x = random_state(system, rng, n_x)
    u = rng.uniform(-3.0, 3.0, n_u)
    return [a.tolist() for a in (x, u, rng.normal(0.0, 0.1, n_x), rng.uniform(0.0, 0.2, n_x))]


# --- the rows over arrays --------------------------------------------------------------------

@pytest.mark.parametrize('system', ['unicycle', 'pvtol'])
def test_rows_over_arrays_equal_the_generated_rows(system):
    """Every circle family over arrays (threshold 1), the other families generated, against
    the generated code of the whole problem: shipped and varied configs (look-ahead point and
    its switch, cascades 0 to 2, bands, walls)."""
    rng = np.random.default_rng(3)
    for problem in problems(system, 8, seed=23):
        vector = VectorAssembly.from_problem(problem, threshold=1)
        assert vector is not None
        many, generated = _many_as_lists(vector), ClosedFormAssembly.from_problem(problem)
        n_x, n_u = problem.system.n_x, problem.system.n_u
        for _ in range(10):
            call = inputs(system, rng, n_x, n_u)
            for sign in (1.0, -1.0):  # forwards and reversing: both look-ahead points
                call[1] = [sign * abs(v) for v in call[1]]
                got, want = many(*call), generated.evaluate(*call)
                for part, name in zip(range(3), ('h', 'G', 'h_qp')):
                    assert_close(np.array(got[part]), np.array(want[part]), name)
                assert got[3] == pytest.approx(want[3], rel=1e-10)


@pytest.mark.parametrize('system, cascaded', [('unicycle', False), ('unicycle', True),
                                              ('pvtol', None)])
def test_rows_over_arrays_equal_autograd_at_hundreds_of_obstacles(system, cascaded):
    rng = np.random.default_rng(11)
    problem = filter_config_from_params(world(system, rng, 300, cascaded=cascaded)).problem
    many = _many_as_lists(VectorAssembly.from_problem(problem))
    n_x, n_u = problem.system.n_x, problem.system.n_u
    for _ in range(6):
        call = inputs(system, rng, n_x, n_u)
        h, rows, upper, _ = many(*call)
        x, u, mean, std = (torch.tensor([a], dtype=torch.float64) for a in call)
        want = problem.qp(x, u, mean, std)
        assert_close(np.array(h), problem.terms(x, u).h[0].numpy(), 'h')
        assert_close(np.array(rows), want.G[0].numpy(), 'G')
        assert_close(np.array(upper), want.h[0].numpy(), 'h_qp')


@pytest.mark.parametrize('rows', [0, 1, 2, 3, 64, 360, SMALL_PRODUCT // 3 - 2,
                                  SMALL_PRODUCT // 3 + 2, SMALL_PRODUCT, 3 * SMALL_PRODUCT])
def test_the_rows_products_equal_matmul_bit_for_bit(rows):
    # product takes ndarray.dot below SMALL_PRODUCT entries and @ above: either way the values
    # of @, at every row count (one point, none, a scan, a cloud) and the shapes the rows use
    rng = np.random.default_rng(rows)

    def wide(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape) * 10.0 ** rng.uniform(-8.0, 8.0, shape)

    grads, coefficients, g_rows = wide(3, rows), wide(3), wide(3, 2)
    lg, step = wide(rows, 2), wide(2)
    pairs = [(coefficients, grads), (np.abs(coefficients), np.abs(grads)), (grads.T, g_rows),
             (lg, step), (lg[::2], step), (g_rows, step)]
    for left, right in pairs:
        assert product(left, right).tobytes() == (left @ right).tobytes()
    for left, right in ((lg, step), (g_rows, step)):  # a list of floats on the right
        assert product(left, right.tolist()).tobytes() == (left @ right).tobytes()


def test_the_shipped_configs_keep_the_generated_rows():
    for system in ('unicycle', 'pvtol', 'car_following'):
        problem = filter_config_from_params(shipped(system)).problem
        assert VectorAssembly.from_problem(problem) is None
        assert SafetyFilter(problem).assembly == 'closed_form'


def test_a_large_family_takes_the_rows_over_arrays_and_answers_as_the_generated_code():
    rng = np.random.default_rng(5)
    problem = filter_config_from_params(world('unicycle', rng, 100)).problem
    vector, generated = SafetyFilter(problem), SafetyFilter(problem, vector_rows=10 ** 6)
    assert (vector.assembly, generated.assembly) == ('vectorised', 'closed_form')
    for _ in range(200):
        call = inputs('unicycle', rng, 3, 2)
        got, want = vector.filter(*call), generated.filter(*call)
        assert (got.status, got.fail_safe) == (want.status, want.fail_safe)
        np.testing.assert_allclose(got.u_safe, want.u_safe, rtol=0, atol=1e-8)
        assert_close(got.constraint_values, want.constraint_values, 'row values')


# --- only the rows that can bind -------------------------------------------------------------

@given(seed=st.integers(0, 2 ** 32 - 1), n_u=st.integers(1, 3), rows=st.integers(1, 40))
@PROPERTY
def test_a_row_left_out_holds_at_every_action_in_the_box(seed, n_u, rows):
    rng = np.random.default_rng(seed)
    low = rng.uniform(-3.0, 0.0, n_u)
    high = low + rng.uniform(0.0, 3.0, n_u)
    applied = rng.uniform(low, high)
    lg = rng.normal(0.0, 2.0, (rows, n_u)) * (rng.random((rows, n_u)) < 0.8)
    upper = rng.normal(0.0, 5.0, rows)
    kept = binding_rows(lg=lg, upper=upper, applied=applied, u_min=low, u_max=high, margin=0.0)
    left_out = np.setdiff1d(np.arange(rows), kept)
    assert set(np.flatnonzero(upper < 0.0)) <= set(kept)  # a violated row is always kept
    corners = np.array(np.meshgrid(*zip(low, high))).reshape(n_u, -1).T
    actions = np.concatenate([corners, rng.uniform(low, high, (50, n_u))])
    values = upper[left_out, None] + lg[left_out] @ (actions - applied).T
    assert np.all(values >= -1e-12 * (1.0 + np.abs(upper).max()))
    # and the bound is tight: each row kept is violated at some corner (or lies within margin)
    least = (upper[kept, None] + lg[kept] @ (corners - applied).T).min(axis=1)
    assert np.all(least < 1e-9 * (1.0 + np.abs(upper).max()))
    # without limits no row is left out
    assert binding_rows(lg=lg, upper=upper, applied=applied, u_min=None, u_max=None,
                        margin=0.0).size == rows


def _qp_action(safety_filter: SafetyFilter, call: list[list[float]], *, pruned: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The action of the QP by the exact active-set solve, with EVERY row (``pruned`` False)
    or only those binding_rows keeps, and every row's (upper, L_g h) at the clipped
    proposal."""
    applied = safety_filter._clip(call[1])
    h, rows, upper, _ = safety_filter._assemble(call[0], applied, call[2], call[3])
    k = len(h)
    upper_a, lg = np.array(upper[:k]), -np.array(rows)[:k, :-1]
    if min(upper) >= 0.0:
        return np.array(applied), upper_a, lg
    scale = 1.0 + max(map(abs, upper))
    if pruned:
        kept = binding_rows(lg=lg, upper=upper_a, applied=applied, u_min=safety_filter._u_min,
                            u_max=safety_filter._u_max, margin=PRUNE_MARGIN * scale).tolist()
        kept += list(range(k, len(rows)))  # the limit rows
        rows, upper = [rows[i] for i in kept], [upper[i] for i in kept]
    z = active_set_solution(rows=rows, upper=upper, p_inverse=safety_filter._p_inverse_list,
                            tolerance=ACTIVE_SET_TOLERANCE * scale)
    if z is None:
        return None
    action = np.clip(np.array(applied) + z[:-1], safety_filter._u_min, safety_filter._u_max)
    return action, upper_a, lg


FILTERS: dict[tuple[str, int], SafetyFilter] = {}


@given(seed=st.integers(0, 2 ** 32 - 1), system=st.sampled_from(['unicycle', 'pvtol']),
       count=st.sampled_from([64, 150, 400]), near=st.booleans())
@PROPERTY
def test_the_answer_with_rows_left_out_equals_the_full_qp_and_meets_every_row(
        seed, system, count, near):
    rng = np.random.default_rng(seed)
    key = (system, count, seed % 4)  # a few worlds per size, built once
    if key not in FILTERS:
        params = world(system, np.random.default_rng(key[2]), count)
        FILTERS[key] = SafetyFilter(filter_config_from_params(params).problem,
                                    slack_tolerance=None)
    safety_filter = FILTERS[key]
    n_x, n_u = safety_filter.n_x, safety_filter.n_u
    call = inputs(system, rng, n_x, n_u)
    if near:  # next to an obstacle, so that rows bind
        family = safety_filter.problem.families[0]
        while hasattr(family, 'base'):
            family = family.base
        o = int(rng.integers(family.count))
        centre, reach = family.centers[o], family.radii[o] + family.margin
        angle = rng.uniform(0.0, 2.0 * np.pi)
        distance = reach * rng.uniform(1.0, 1.5)
        call[0][0] = centre[0] + distance * np.cos(angle)
        call[0][1] = centre[1] + distance * np.sin(angle)
    result = safety_filter.filter(*call)
    assert safety_filter.assembly == 'vectorised'
    reference = _qp_action(safety_filter, call, pruned=False)
    pruned = _qp_action(safety_filter, call, pruned=True)
    assume(reference is not None and pruned is not None)
    action, upper, lg = reference
    tolerance = 1e-7 * (1.0 + np.abs(upper).max())
    # the QP of the rows that can bind has the full QP's solution (the argument itself) ...
    np.testing.assert_allclose(pruned[0], action, rtol=0, atol=tolerance)
    # ... and so has the filter's answer
    assert not result.fail_safe, result.reason
    np.testing.assert_allclose(result.u_safe, action, rtol=0, atol=tolerance)
    # every row checked: the values reported are those of every row at the answer
    applied = np.array(safety_filter._clip(call[1]))
    values = upper + lg @ (result.u_safe - applied)
    assert_close(result.constraint_values, values, 'row values')
    assert values.min() >= -max(result.slack, 0.0) - 1e-6 * (1.0 + np.abs(upper).max())


def test_rows_that_cannot_bind_are_left_out_of_the_qp(monkeypatch):
    rng = np.random.default_rng(2)
    params = world('unicycle', rng, 2000, spread=60.0)
    safety_filter = SafetyFilter(filter_config_from_params(params).problem)
    seen = []
    solve = filter_module._active_set_steps

    def counted(rows, upper, *args):
        seen.append(len(rows))
        return solve(rows, upper, *args)

    monkeypatch.setattr(filter_module, '_active_set_steps', counted)
    active = 0
    for _ in range(300):
        result = safety_filter.filter(*inputs('unicycle', rng, 3, 2))
        active += result.active
    assert active and seen
    assert max(seen) < 50  # 2,000 rows, a handful of them (plus 4 limit rows) in each QP


# --- the obstacles message and the limit -----------------------------------------------------

def test_an_obstacles_message_of_10000_rows_is_installed_and_answered():
    rng = np.random.default_rng(9)
    rows = np.column_stack([rng.uniform(-100, 100, 10_000), rng.uniform(-100, 100, 10_000),
                            rng.uniform(0.05, 0.5, 10_000)])
    changes = logic.obstacle_parameters(data=rows.ravel().tolist(), dims=[('rows', 10_000, 30_000),
                                                                          ('xyr', 3, 3)])
    params = dict(shipped('unicycle'), **changes)
    active = logic.build_active_filter(params=logic.collect_parameters(params),
                                       probe_states=([0.0, 0.0, 0.0],))
    safety_filter = active.safety_filter
    assert safety_filter.n_barriers == 10_000 and safety_filter.assembly == 'vectorised'
    # straight at the nearest obstacle: the answer brakes or turns, and meets every row
    distance = np.hypot(rows[:, 0], rows[:, 1]) - rows[:, 2]
    o = int(np.argmin(distance))
    heading = float(np.arctan2(rows[o, 1], rows[o, 0]))
    start = rows[o, :2] - (rows[o, 2] + 0.2) * np.array([np.cos(heading), np.sin(heading)])
    result = safety_filter.filter([*start, heading], [2.5, 0.0])
    assert not result.fail_safe and result.active
    assert result.constraint_values.shape == (10_000,)
    # every row met, up to the QP's own slack (within the node's slack tolerance)
    assert result.constraint_values.min() >= -result.slack - 1e-9
    assert result.needed_slack <= active.settings.slack_tolerance


def test_an_obstacles_message_past_the_limit_is_refused_in_one_line_naming_it():
    data = [0.0, 1.5, 0.4] * (OBSTACLE_LIMIT + 1)
    with pytest.raises(ValueError) as error:
        logic.obstacle_parameters(data=data)
    assert str(error.value) == (f'obstacles: data: at most {OBSTACLE_LIMIT} rows of '
                                f'[x, y, radius], got {OBSTACLE_LIMIT + 1}')


_CHILD = _BLOCK_TORCH + textwrap.dedent("""
    import json
    import numpy as np
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.core.filter import SafetyFilter
    params, calls = json.loads(sys.stdin.read())
    safety_filter = SafetyFilter(filter_config_from_params(params).problem)
    out = [safety_filter.filter(*call).u_safe.tolist() for call in calls]
    print(json.dumps({'answers': out, 'assembly': safety_filter.assembly,
                      'torch': 'torch' in sys.modules}))
""")


def test_the_rows_over_arrays_run_without_torch():
    rng = np.random.default_rng(4)
    params = world('unicycle', rng, 300)
    calls = [inputs('unicycle', rng, 3, 2) for _ in range(30)]
    run = subprocess.run([sys.executable, '-c', _CHILD], input=json.dumps([params, calls]),
                         capture_output=True, text=True, timeout=120, check=False,
                         env=_env_with_tests())
    assert run.returncode == 0, run.stderr[-2000:]
    child = json.loads(run.stdout.strip().splitlines()[-1])
    assert child['assembly'] == 'vectorised' and not child['torch']
    safety_filter = SafetyFilter(filter_config_from_params(params).problem)
    assert child['answers'] == [safety_filter.filter(*call).u_safe.tolist() for call in calls]


@pytest.mark.parametrize('limits', [True, False])
def test_the_solvers_behind_the_exact_solve_take_every_row(monkeypatch, limits):
    """Where the exact solve gives no certified answer, OSQP (and the interior point) solve
    the QP of every row: the same answers as the exact solve's."""
    rng = np.random.default_rng(8)
    params = world('unicycle', rng, 120)
    if not limits:
        params.update({'input_limits.min': [], 'input_limits.max': []})
    problem = filter_config_from_params(params).problem
    exact, fallback = SafetyFilter(problem), SafetyFilter(problem)
    assert exact.problem.has_limits is limits
    every = [inputs('unicycle', rng, 3, 2) for _ in range(120)]
    wanted = [exact.filter(*call) for call in every]
    monkeypatch.setattr(filter_module, '_active_set_steps', lambda *args: None)
    corrected = 0
    for call, want in zip(every, wanted):
        got = fallback.filter(*call)
        assert got.fail_safe == want.fail_safe
        corrected += want.active
        np.testing.assert_allclose(got.u_safe, want.u_safe, rtol=0, atol=1e-5)
        assert got.constraint_values.min() >= -max(got.slack, 0.0) - 1e-6 * (
            1.0 + np.abs(got.constraint_values).max())
    assert corrected


def test_a_problem_without_rows_over_arrays_takes_the_many_row_path_past_its_size():
    """Many circles on the autograd assembly (no closed form asked for): the filter's loops
    are not generated per row past GENERATED_ROWS; the answers are the rows over arrays'."""
    rng = np.random.default_rng(6)
    problem = filter_config_from_params(
        world('unicycle', rng, filter_module.GENERATED_ROWS + 1, spread=30.0)).problem
    autograd, vector = SafetyFilter(problem, closed_form=False), SafetyFilter(problem)
    assert (autograd.assembly, vector.assembly) == ('autograd', 'vectorised')
    assert autograd._many is not None
    corrected = 0
    for _ in range(40):
        call = inputs('unicycle', rng, 3, 2)
        got, want = autograd.filter(*call), vector.filter(*call)
        corrected += want.active
        assert (got.status, got.fail_safe) == (want.status, want.fail_safe)
        np.testing.assert_allclose(got.u_safe, want.u_safe, rtol=0, atol=1e-8)
    assert corrected

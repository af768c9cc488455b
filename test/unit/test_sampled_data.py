"""The sampled-data margins: h >= 0 between samples and under latency, and the bounds behind it.

The fine-step simulation is benchmarks/bench_sampled_data.py's (1 ms Euler steps of the true
unicycle, commands held for T and computed from states L old), on a few worlds: no violation
with the margin, and violations in the same worlds without it (else the scenario proves
nothing). The bounds nu_i are checked against the true change of each row's left side along
fine-step trajectories, the left side evaluated by the torch assembly of RCBFProblem.qp (not the
margin's code).
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math

from benchmark_modules import load_benchmark
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import (
    BandBarrier,
    cascade,
    CircleObstacles,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.dynamics import CarFollowing, PVTOL, Unicycle
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import least_per_row, sampled_data_margin, split_rows
from rcbf_ros.parameters.rules import find_config, load_params

bench = load_benchmark('bench_sampled_data')

T, L = 0.1, 0.05


@pytest.mark.parametrize('points', [False, True], ids=['circles', 'sensor_points'])
def test_no_fine_step_violation_with_the_margin_and_some_without(points):
    worlds = bench.random_worlds(6, seed=3)
    tight = bench.simulate(worlds, period=T, latency=L, tightened=True, points=points,
                           duration=2.0)
    loose = bench.simulate(worlds, period=T, latency=L, tightened=False, points=points,
                           duration=2.0)
    assert not tight.violated.any(), tight.least_h
    assert loose.violated.sum() >= 2, loose.least_h


def test_a_margin_that_lets_slow_commands_creep_closer_is_not_what_holds_worlds_safe():
    """Closed loop at T = 50 ms, L = 0. A margin that charges only the command's own speed over
    the hold (not any input within the limits) is smaller for slow commands: it lets the robot
    creep close, to states where no command meets the tightened rows, and these worlds are
    entered; it also assumes wheels without lag. The margin of any input within the limits
    keeps them safe."""
    worlds = [bench.random_worlds(60, seed=11)[i] for i in (0, 1, 2, 3)]
    tight = bench.simulate(worlds, period=0.05, latency=0.0, tightened=True, duration=2.5)
    assert not tight.violated.any(), tight.least_h


def test_a_short_period_without_latency_is_safe_with_the_margin_too():
    # T = 1 ms, no latency: the margin is small and the rows still keep every fine step safe
    worlds = bench.random_worlds(3, seed=5)
    tight = bench.simulate(worlds, period=0.001, latency=0.0, tightened=True, duration=0.6)
    assert not tight.violated.any()


def test_the_benchmark_prints_its_cases_and_writes_nothing_with_no_write(capsys):
    before = bench_results_text()
    assert bench.main(['--worlds', '1', '--pvtol-worlds', '1', '--no-write']) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [line for line in lines if line.startswith(('| circles', '| sensor points'))]
    assert len(rows) == 6 and all('/ 1 |' in row for row in rows)
    pvtol = [line for line in lines if line.startswith(
        ('| T = L = 0', '| constant margin', '| margin of the command'))]
    assert len(pvtol) == 3 and all('/ 1 |' in row for row in pvtol)
    hover = [line for line in lines if line.startswith('| PVTOL, config/pvtol.yaml')]
    assert len(hover) == 2 and all(row.endswith('| fail-safe | passes |') for row in hover)
    stops = [line for line in lines if line.startswith('| Unicycle,')]
    assert len(stops) == 2
    for row in stops:  # the command's margin lets the robot come closer, never into the circle
        constant, linear = (float(cell) for cell in row.split('|')[2:4])
        assert 0.6 < linear < constant
    assert bench_results_text() == before


def bench_results_text() -> str:
    from benchmark_modules import BENCHMARKS
    return (BENCHMARKS / 'RESULTS.md').read_text()


# ------------------------------------------------------------------ the bounds themselves
def _families(kind: str, data) -> tuple:
    centre = tuple(data.draw(st.tuples(st.floats(-2, 2), st.floats(-2, 2))))
    if kind == 'lookahead':
        return (CircleObstacles(centers=(centre,), radii=(data.draw(st.floats(0.1, 0.8)),),
                                margin=0.1, heading_index=2,
                                lookahead=data.draw(st.floats(0.01, 0.3))),)
    if kind == 'circle':
        return (CircleObstacles(centers=(centre,), radii=(0.4,), margin=0.1),)
    if kind == 'wall':
        angle = data.draw(st.floats(-math.pi, math.pi))
        return (HalfPlane(normals=((math.cos(angle), math.sin(angle)),),
                          offsets=(data.draw(st.floats(-3, 3)),)),)
    if kind == 'band':
        return (BandBarrier(index=data.draw(st.sampled_from([0, 1, 2])), half_width=1.5,
                            center=centre[0],
                            form=data.draw(st.sampled_from(['quadratic', 'sides']))),)
    return (PairGap(pairs=((0, 1),), delta=0.5),)


@pytest.mark.parametrize('kind', ['lookahead', 'circle', 'wall', 'band', 'gap'])
@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), period=st.floats(0.01, 0.15), latency=st.floats(0.0, 0.1))
def test_the_true_change_of_every_row_stays_within_its_margin(data, kind, period, latency):
    """|phi_i(x(t), u) - phi_i(x_k, u)| <= nu_i for t in [t_k, t_k + L + T], along 1 ms
    Euler steps under inputs within the limits that switch at random and a disturbance
    drawn within the box at every step."""
    system = Unicycle(u_min=(-2.0, -3.0), u_max=(2.5, 1.5))
    problem = RCBFProblem(system=system, families=_families(kind, data),
                          alpha=data.draw(st.sampled_from([0.1, 1.0, 5.0, 20.0])),
                          k_c=2.0)
    margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency)
    x_k = np.array(data.draw(st.tuples(st.floats(-2, 2), st.floats(-2, 2),
                                       st.floats(-math.pi, math.pi))))
    mean, std = np.zeros(3), np.zeros(3)
    if data.draw(st.booleans()):  # a box, else the bare rows (the tightest case)
        mean = np.array(data.draw(st.tuples(*[st.floats(-0.3, 0.3)] * 3)))
        std = np.array(data.draw(st.tuples(*[st.floats(0.0, 0.1)] * 3)))
    rest, linear = margin.split_rows(x_k.tolist(), mean.tolist(), std.tolist())
    assert np.all(linear >= 0.0)
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    low, high = np.array(system.u_min), np.array(system.u_max)
    # the row's command: each entry at a limit, inside them, a tenth of that or 0 (the margin
    # follows |u|; v >= 0: the point ahead)
    held = np.where(rng.random(2) < 0.5, high, rng.uniform(low, high)) * rng.choice(
        [1.0, 1.0, 0.1, 0.0], 2)
    held[0] = abs(held[0])
    nu = rest + linear @ np.abs(held)  # the margin of this command
    whole, rest = divmod(period + latency, 1e-3)  # 1 ms steps over exactly tau
    steps = [1e-3] * int(whole) + ([rest] if rest > 0 else [])
    states = [x_k]
    x = x_k.copy()
    # the plant's input: a vertex of the limits held throughout (the fastest motion), or one
    # that switches at random within them
    switching = data.draw(st.booleans())
    u = np.where(rng.random(2) < 0.5, low, high) if not switching else rng.uniform(low, high)
    for dt in steps:
        if switching and rng.random() < 0.05:
            u = np.where(rng.random(2) < 0.7, np.where(rng.random(2) < 0.5, low, high),
                         rng.uniform(low, high))
        psi = mean + 2.0 * std * rng.choice([-1.0, 1.0], 3) * rng.random(3) ** 0.2
        g = np.array([[math.cos(x[2]), 0.0], [math.sin(x[2]), 0.0], [0.0, 1.0]])
        x = x + dt * (g @ u + psi)
        states.append(x.copy())
    batch = torch.tensor(np.array(states), dtype=torch.float64)
    count = batch.shape[0]
    qp = problem.qp(batch, torch.tensor(held, dtype=torch.float64).expand(count, 2),
                    torch.tensor(mean, dtype=torch.float64).expand(count, 3),
                    torch.tensor(std, dtype=torch.float64).expand(count, 3))
    phi = qp.h[:, :problem.n_barriers].numpy()  # L_f h + L_g h u + alpha h + rho
    change = np.abs(phi - phi[0]).max(axis=0)
    assert np.all(change <= nu + 1e-9), (change, nu, held)


@pytest.mark.parametrize('bearing', [0.5, 1.6, 2.8, -1.2])
def test_a_turn_in_place_is_covered_by_the_turn_rate_part_of_the_margin(bearing):
    """Held v = 0 and the fastest turn, the robot turning in place (no box, alpha 0.1): the
    look-ahead row's change is almost all 2 l_p d^T n omega's, which only c_omega |omega|
    covers (the change exceeds nu0), and it stays within nu0 + c^T |u|."""
    system = Unicycle(u_min=(-2.0, -3.0), u_max=(2.5, 1.5))
    centre = (2.0 * math.cos(bearing), 2.0 * math.sin(bearing))
    problem = RCBFProblem(system=system, families=(CircleObstacles(
        centers=(centre,), radii=(0.4,), margin=0.1, heading_index=2, lookahead=0.3),),
        alpha=0.1)
    period, latency = 0.2, 0.05
    margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency)
    x_k = np.zeros(3)
    held = np.array([0.0, -3.0])
    rest, linear = margin.split_rows(x_k.tolist(), [0.0] * 3, [0.0] * 3)
    states = [x_k + np.array([0.0, 0.0, -3.0 * t]) for t in np.linspace(0.0, period + latency,
                                                                         251)]
    batch = torch.tensor(np.array(states), dtype=torch.float64)
    qp = problem.qp(batch, torch.tensor(held).expand(251, 2))
    phi = qp.h[:, 0].numpy()
    change = float(np.abs(phi - phi[0]).max())
    assert rest[0] < change <= rest[0] + linear[0] @ np.abs(held)


@settings(max_examples=30, deadline=None)
@given(x=st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-math.pi, math.pi)),
       period=st.floats(0.01, 0.15), latency=st.floats(0.0, 0.1))
def test_a_sensor_point_row_has_the_margin_of_the_same_circle(x, period, latency):
    footprint = CircleObstacles(centers=((0.0, 0.0),), radii=(0.2,), margin=0.1,
                                heading_index=2, lookahead=0.03)
    problem = RCBFProblem(system=Unicycle(), families=(
        CircleObstacles(centers=((1.0, -0.5),), radii=(0.2,), margin=0.1, heading_index=2,
                        lookahead=0.03),), alpha=2.0)
    margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency,
                                 footprint=footprint)
    box = ([-0.05, 0.0, 0.0], [0.025, 0.025, 0.0])
    assert margin.points(list(x), *box, np.array([1.0]), np.array([-0.5])) == pytest.approx(
        margin.rows(list(x), *box))
    point_rest, point_linear = margin.split_points(list(x), *box, np.array([1.0]),
                                                   np.array([-0.5]))
    rest, linear = margin.split_rows(list(x), *box)
    assert point_rest == pytest.approx(rest) and point_linear == pytest.approx(linear)
    assert np.all(point_linear > 0.0)  # both inputs move the look-ahead point's row


# ------------------------------------------------------------------ the split rows
@settings(max_examples=200, deadline=None)
@given(data=st.data(), n_u=st.integers(1, 3), count=st.integers(0, 6))
def test_the_split_rows_are_the_row_tightened_by_the_margin_of_the_command(data, n_u, count):
    """min over the sign vectors of the split rows at u = upper + lg^T (u - applied) - nu0 -
    c^T |u| (the closed form), for c with zero entries too; a row takes 2^m rows, m its
    entries of c > 0."""
    number = st.floats(-5.0, 5.0)
    arrays = [np.array(data.draw(st.lists(number, min_size=size, max_size=size))).reshape(shape)
              for size, shape in ((count * n_u, (count, n_u)), (count, (count,)),
                                  (n_u, (n_u,)), (count, (count,)))]
    lg, upper, applied, rest = arrays
    rest = np.abs(rest)
    linear = np.array(data.draw(st.lists(st.sampled_from([0.0, 0.5, 3.0]),
                                         min_size=count * n_u, max_size=count * n_u))
                      ).reshape(count, n_u) * np.abs(data.draw(number))
    u = np.array(data.draw(st.lists(number, min_size=n_u, max_size=n_u)))
    split_lg, split_upper, starts = split_rows(lg, upper, applied, rest, linear)
    sizes = np.diff(np.append(starts, split_upper.size))
    assert sizes.tolist() == (2 ** (linear > 0.0).sum(axis=1)).tolist()
    got = least_per_row(split_upper + split_lg @ (u - applied), starts)
    want = upper + lg @ (u - applied) - rest - linear @ np.abs(u)
    assert got == pytest.approx(want, abs=1e-9)


@pytest.mark.parametrize('vector_rows', [64, 1], ids=['per_row', 'over_arrays'])
def test_each_answer_meets_the_row_tightened_by_the_margin_of_its_own_command(vector_rows):
    """At the filter's action u: phi_i(x_k, u) - nu0_i - c_i^T |u| (phi by the torch assembly
    of RCBFProblem.qp at the proposal, whose sign of v picks the look-ahead point, not by the
    filter's) is the reported value, >= -the slack it needed."""
    config = filter_config_from_params(_unicycle_params(control_period_s=T, latency_s=L))
    problem, box = config.problem, (config.static_mean, config.static_std)
    tight = SafetyFilter(problem, control_period_s=T, latency_s=L, vector_rows=vector_rows)
    margin = sampled_data_margin(problem, control_period_s=T, latency_s=L)
    rng = np.random.default_rng(1)
    active = 0
    for _ in range(40):
        state = [*rng.uniform(-3.5, 3.5, 2), rng.uniform(-math.pi, math.pi)]
        proposal = rng.uniform(-2.5, 2.5, 2)  # within the limits: not clipped
        result = tight.filter(state, proposal, *box)
        if result.fail_safe:
            continue
        active += result.active
        action = result.u_safe
        qp = problem.qp(*(torch.tensor(np.array([a]), dtype=torch.float64)
                          for a in (state, proposal, *box)))
        k = problem.n_barriers
        phi = qp.h[0, :k].numpy() - qp.G[0, :k, :2].numpy() @ (action - proposal)
        rest, linear = margin.split_rows(state, *box)
        row = phi - rest - linear @ np.abs(action)
        assert result.constraint_values == pytest.approx(row, abs=1e-6)
        assert row.min() >= -result.needed_slack - 1e-6
    assert active >= 10


def test_without_period_and_latency_the_filter_has_no_margin_and_keeps_its_row_path():
    config = filter_config_from_params(_unicycle_params())
    plain = SafetyFilter(config.problem)
    assert plain._margin is None and plain._many is None  # the per-row path, untouched


# ------------------------------------------------------------------ the filter and its rows
def _unicycle_params(**extra) -> dict:
    params = load_params(find_config('unicycle'), 'safety_filter')
    params.update(extra)
    return params


def test_zero_period_and_latency_leave_every_row_as_it_was():
    config = filter_config_from_params(_unicycle_params())
    assert (config.control_period_s, config.latency_s) == (0.0, 0.0)
    plain = SafetyFilter(config.problem)
    zero = SafetyFilter(config.problem, control_period_s=0.0, latency_s=0.0)
    for state in ([-1.0, 0.2, 0.1], [2.0, -2.0, 3.0]):
        a = plain.filter(state, [2.5, 0.3], config.static_mean, config.static_std)
        b = zero.filter(state, [2.5, 0.3], config.static_mean, config.static_std)
        assert np.array_equal(a.u_safe, b.u_safe)
        assert np.array_equal(a.constraint_values, b.constraint_values)


@pytest.mark.parametrize('vector_rows', [64, 1], ids=['per_row', 'over_arrays'])
def test_every_assembly_path_lowers_each_row_by_its_margin(vector_rows):
    config = filter_config_from_params(_unicycle_params(control_period_s=T, latency_s=L))
    assert (config.control_period_s, config.latency_s) == (T, L)
    state, proposal = [-9.0, 9.0, 0.2], [0.4, -0.3]  # far out: no correction, either way
    plain = SafetyFilter(config.problem, vector_rows=vector_rows)
    tight = SafetyFilter(config.problem, vector_rows=vector_rows, control_period_s=T,
                         latency_s=L)
    box = (config.static_mean, config.static_std)
    margin = sampled_data_margin(config.problem, control_period_s=T, latency_s=L)
    rest, linear = margin.split_rows(state, *box)
    nu = rest + linear @ np.abs(proposal)  # the margin of this command
    a, b = plain.filter(state, proposal, *box), tight.filter(state, proposal, *box)
    assert np.all(nu > 0) and not a.active and not b.active
    assert a.constraint_values - b.constraint_values == pytest.approx(nu)
    assert np.all(nu < margin.rows(state, *box))  # below the largest command's


def test_the_interior_point_fallback_solves_the_tightened_rows(monkeypatch):
    import rcbf_ros.core.filter as filter_module
    config = filter_config_from_params(_unicycle_params())
    box = (config.static_mean, config.static_std)
    exact = SafetyFilter(config.problem, control_period_s=T, latency_s=L)
    fallback = SafetyFilter(config.problem, control_period_s=T, latency_s=L)
    states = ([-2.9, 0.3, 0.0], [-2.4, 0.0, 0.0], [-2.6, 0.2, 0.3])
    wants = [exact.filter(state, [2.5, 0.4], *box) for state in states]
    # the exact solve and OSQP both fail: the interior point must solve the tightened QP
    monkeypatch.setattr(filter_module, '_active_set_steps', lambda *args: None)
    monkeypatch.setattr(filter_module, '_solve_once', lambda *args: (None, 'max'))
    for state, want in zip(states, wants):
        got = fallback.filter(state, [2.5, 0.4], *box)
        assert got.status == 'solved_interior_point', got.reason
        assert want.status == 'solved' and want.active
        assert got.u_safe == pytest.approx(want.u_safe, abs=1e-5)
        assert got.constraint_values == pytest.approx(want.constraint_values, abs=1e-5)


def test_the_rows_left_out_of_the_qp_hold_with_their_margin(monkeypatch):
    # the many-row path solves a QP of the split rows that can bind only: its answers are
    # those of the QP of every split row
    import rcbf_ros.core.filter as filter_module
    rng = np.random.default_rng(0)
    params = _unicycle_params(control_period_s=T, latency_s=L, **{
        'obstacles.x': rng.uniform(-25, 25, 80).tolist(),
        'obstacles.y': rng.uniform(-25, 25, 80).tolist(),
        'obstacles.radius': rng.uniform(0.1, 0.3, 80).tolist()})
    config = filter_config_from_params(params)
    pruned = SafetyFilter(config.problem, control_period_s=T, latency_s=L)
    whole = SafetyFilter(config.problem, control_period_s=T, latency_s=L, vector_rows=10 ** 6)
    assert (pruned.assembly, whole.assembly) == ('vectorised', 'closed_form')
    box = (config.static_mean, config.static_std)
    left_out = active = 0
    for _ in range(60):
        state = [*rng.uniform(-25, 25, 2), rng.uniform(-math.pi, math.pi)]
        proposal = rng.uniform(-2.5, 2.5, 2)
        got = pruned.filter(state, proposal, *box)
        left_out += pruned._pruned
        with monkeypatch.context() as patch:  # the whole filter keeps every row
            patch.setattr(filter_module, 'binding_rows', lambda **rows: np.arange(
                rows['upper'].size))
            want = whole.filter(state, proposal, *box)
        assert whole._pruned == 0 or not want.active
        active += want.active
        assert got.status == want.status == 'solved'  # no fallback rescued a pruned QP
        assert got.u_safe == pytest.approx(want.u_safe, abs=1e-6)
        assert got.constraint_values == pytest.approx(want.constraint_values, abs=1e-6)
    assert left_out > 0 and active >= 10


@pytest.mark.parametrize(('system', 'extra', 'key', 'words'), [
    ('car_following', {'latency_s': 0.02}, 'latency_s', 'car_following'),
    ('car_following', {'latency_s': 0.02, 'input_limits.min': [-10.0],
                       'input_limits.max': [10.0]}, 'latency_s', 'braking switches'),
    ('pvtol', {'control_period_s': 0.02, 'observation_sources': ['scan'], 'scan.type': 'scan',
               'scan.topic': '/scan'}, 'control_period_s', 'sensor points'),
    ('unicycle', {'control_period_s': 0.02, 'walls.nx': [1.0], 'walls.ny': [0.0],
                  'walls.offset': [-5.0], 'walls.gammas': [1.0], 'observation_sources': ['scan'],
                  'scan.type': 'scan', 'scan.topic': '/scan'}, 'control_period_s',
     'sensor points'),
    ('unicycle', {'control_period_s': 2.0}, 'control_period_s', '<= 1'),
    ('unicycle', {'latency_s': -0.01}, 'latency_s', '>= 0'),
    ('unicycle', {'latency_s': 0.02, 'obstacles.gammas': [1.0], 'obstacles.speed_input': -1},
     'latency_s', 'Cascaded'),
    ('unicycle', {'latency_s': 0.02, 'input_limits.min': [], 'input_limits.max': []},
     'latency_s', 'input limits'),
])
def test_what_has_no_derived_margin_is_refused_naming_the_key(system, extra, key, words):
    params = load_params(find_config(system), 'safety_filter')
    params.update(extra)
    with pytest.raises(ValueError) as error:
        filter_config_from_params(params)
    line = str(error.value)
    assert line.startswith(f'{key}:') and words in line and '\n' not in line, line


@dataclass(frozen=True)
class _OwnPVTOL(PVTOL):
    """A user's system (a subclass may change f or g: it has no closed form)."""


def test_the_filter_refuses_what_the_config_refuses():
    for problem in (RCBFProblem(system=_OwnPVTOL(), families=(HalfPlane(((1.0, 0.0),),
                                                                        (0.0,)),)),
                    RCBFProblem(system=CarFollowing(u_min=(-5.0,), u_max=(5.0,)), families=(
                        cascade(PairGap(((4, 6),), 3.5), CarFollowing(), [1.0]),))):
        with pytest.raises(ValueError, match='^control_period_s: no sampled-data margin'):
            SafetyFilter(problem, control_period_s=0.1)


# ------------------------------------------------------------------ the node's parameters
@pytest.fixture
def harness(ros_domain_id):
    from test_safety_filter_callbacks import EVERY_DIAGNOSTIC, FilterHarness, UNICYCLE

    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    rclpy.init(args=['--ros-args', '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC],
               domain_id=ros_domain_id)
    instance = FilterHarness()
    yield instance
    instance.node.destroy_node()
    rclpy.try_shutdown()


def test_period_and_latency_change_at_runtime_and_rebuild_the_filter(harness):
    from rcbf_ros.ros.dds.node import Parameter
    node = harness.node
    assert (node.filter.control_period_s, node.filter.latency_s) == (0.0, 0.0)
    old = node.filter
    result = node.set_parameters([Parameter('control_period_s', value=T),
                                  Parameter('latency_s', value=L)])
    assert all(r.successful for r in result), [r.reason for r in result]
    assert node.filter is not old
    assert (node.filter.control_period_s, node.filter.latency_s) == (T, L)
    assert (node.config.control_period_s, node.config.latency_s) == (T, L)
    current = node.filter
    for name, value in (('control_period_s', 1.5), ('latency_s', -0.02),
                        ('control_period_s', math.nan)):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and name in result.reason, result.reason
        assert node.filter is current


@pytest.mark.parametrize('value', [math.nan, math.inf, -0.01, 1.01, True, '0.1', None])
@pytest.mark.parametrize('key', ['control_period_s', 'latency_s'])
def test_a_bad_period_or_latency_is_refused_by_the_filter_naming_the_key(key, value):
    problem = filter_config_from_params(_unicycle_params()).problem
    with pytest.raises(ValueError, match=f'^{key}: must be a number in \\[0, 1\\] s'):
        SafetyFilter(problem, **{key: value})


@settings(max_examples=15, deadline=None)
@given(state=st.tuples(*[st.floats(-1e6, 1e6)] * 3),
       mean=st.tuples(*[st.floats(-1e6, 1e6)] * 3), std=st.tuples(*[st.floats(0, 1e6)] * 3))
def test_hostile_states_and_boxes_within_the_bounds_give_a_verified_answer_or_the_fail_safe(
        state, mean, std):
    for tight in _tight_filters():
        result = tight.filter(state, [2.5, -2.5], mean, std)
        assert result.fail_safe or result.needed_slack <= 1e-4
        assert np.all(np.abs(result.u_safe) <= 2.5)


@functools.cache
def _tight_filters() -> tuple[SafetyFilter, SafetyFilter]:
    """The Unicycle's filter with the margin, per row and over arrays (built once)."""
    config = filter_config_from_params(_unicycle_params(control_period_s=T, latency_s=L))
    return tuple(SafetyFilter(config.problem, control_period_s=T, latency_s=L,
                              vector_rows=vector_rows, slack_tolerance=1e-4)
                 for vector_rows in (64, 1))

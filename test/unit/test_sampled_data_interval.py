"""The interval margin (rcbf_ros/core/sampled_data.py, IntervalMargin) of cascaded rows: its
bound holds along fine-step trajectories, and PVTOL's filter with it keeps every fine step safe
where the continuous-time rows do not.

The bound is checked against the true change of each row's left side along 1 ms Euler
trajectories, the left side evaluated by the torch assembly of RCBFProblem.qp (autograd through
the cascades: not the generated code the margin runs on). The closed loop is
benchmarks/bench_sampled_data.py's PVTOL simulation on a few worlds.
"""
from __future__ import annotations

import functools
import math

from benchmark_modules import load_benchmark
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import BandBarrier, cascade, CircleObstacles, HalfPlane
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.dynamics import PVTOL, Unicycle
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import IntervalMargin, sampled_data_margin
from rcbf_ros.parameters.rules import find_config, load_params

bench = load_benchmark('bench_sampled_data')

T, L = 0.02, 0.02


def _pvtol_problem(alpha: float, centre: tuple[float, float]) -> RCBFProblem:
    """config/pvtol.yaml's rows (cascaded obstacles, operator and arena bands, the envelope)
    with one circle at ``centre`` added and the gain ``alpha``."""
    params = load_params(find_config('pvtol'), 'safety_filter')
    params.update({'alpha': alpha, 'obstacles.x': [centre[0], 3.0],
                   'obstacles.y': [centre[1], -0.8], 'obstacles.radius': [0.4, 0.4]})
    return filter_config_from_params(params).problem


def _true_change(problem: RCBFProblem, x_k: np.ndarray, mean: np.ndarray, std: np.ndarray,
                 horizon: float, rng: np.random.Generator, switching: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The largest |phi_i(x(t), u) - phi_i(x_k, u)| along one 1 ms Euler trajectory of the
    nominal model plus a disturbance in the box, under inputs within the limits (a vertex held,
    or switching at random), phi at one held command u within the limits (each entry at a
    limit, inside them, a tenth of that or 0: the margin follows |u|), and u."""
    system = problem.system
    low, high = np.array(system.u_min), np.array(system.u_max)
    held = np.where(rng.random(system.n_u) < 0.5, rng.choice([-1, 1], system.n_u) * high,
                    rng.uniform(low, high)) * rng.choice([1.0, 1.0, 0.1, 0.0], system.n_u)
    whole, rest = divmod(horizon, 1e-3)
    steps = [1e-3] * int(whole) + ([rest] if rest > 0 else [])
    u = np.where(rng.random(system.n_u) < 0.5, low, high)
    states, x = [x_k], torch.tensor(x_k)[None]
    for dt in steps:
        if switching and rng.random() < 0.1:
            u = np.where(rng.random(system.n_u) < 0.7, np.where(rng.random(system.n_u) < 0.5,
                                                                low, high),
                         rng.uniform(low, high))
        psi = mean + problem.k_c * std * rng.choice([-1.0, 1.0], system.n_x)
        x_dot = system.f(x) + (system.g(x) @ torch.tensor(u)[None, :, None])[..., 0]
        x = x + dt * (x_dot + torch.tensor(psi)[None])
        states.append(x[0].numpy())
    batch = torch.tensor(np.array(states), dtype=torch.float64)
    count = batch.shape[0]
    qp = problem.qp(batch, torch.tensor(held).expand(count, system.n_u),
                    torch.tensor(mean).expand(count, system.n_x),
                    torch.tensor(std).expand(count, system.n_x))
    phi = qp.h[:, :problem.n_barriers].numpy()
    return np.abs(phi - phi[0]).max(axis=0), held


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), period=st.floats(0.005, 0.1), latency=st.floats(0.0, 0.05),
       alpha=st.sampled_from([1.0, 5.0, 15.0]))
def test_the_true_change_of_every_pvtol_row_stays_within_its_margin(data, period, latency,
                                                                    alpha):
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    x_k = np.array([rng.uniform(-4, 4), rng.uniform(-2, 2), *rng.uniform(-1.5, 1.5, 2),
                    rng.uniform(-1.2, 1.2), rng.uniform(0.4, 1.6), rng.uniform(-4, 4)])
    centre = (x_k[0] + rng.uniform(-1.5, 1.5), x_k[1] + rng.uniform(-1.5, 1.5))
    problem = _pvtol_problem(alpha, centre)
    mean, std = np.zeros(7), np.zeros(7)
    if data.draw(st.booleans()):
        mean = rng.uniform(-0.1, 0.1, 7)
        std = rng.uniform(0.0, 0.1, 7)
    margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency)
    assert isinstance(margin, IntervalMargin)
    rest, linear = margin.split_rows(x_k.tolist(), mean.tolist(), std.tolist())
    assert np.all(np.isfinite(rest)) and np.all((linear >= 0.0) & np.isfinite(linear))
    for switching in (False, True):
        change, held = _true_change(problem, x_k, mean, std, period + latency, rng, switching)
        nu = rest + linear @ np.abs(held)  # the margin of this command
        assert np.all(change <= nu + 1e-9), (change, nu, held)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), horizon=st.floats(0.005, 0.3))
def test_every_fine_step_trajectory_stays_in_the_enclosure(data, horizon):
    """|x(t) - x_k| <= D entrywise over [0, tau] along 1 ms Euler steps of f + g u + psi,
    u at vertices of the limits (switching at random), psi at vertices of the box."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    problem = _pvtol_problem(5.0, (0.0, 0.0))
    system = problem.system
    margin = sampled_data_margin(problem, control_period_s=horizon)
    x_k = np.array([*rng.uniform(-3, 3, 4), rng.uniform(-3, 3), rng.uniform(-2, 2),
                    rng.uniform(-3, 3)])
    mean, std = rng.uniform(-0.2, 0.2, 7), rng.uniform(0.0, 0.1, 7)
    found = margin.enclosure(x_k.tolist(), (np.abs(mean) + 2.0 * std).tolist())
    if found is None:  # no box closes (tau k_h near 1): no bound, the margins are inf
        assert horizon > 0.2
        assert np.all(margin.rows(x_k.tolist(), mean.tolist(), std.tolist()) == math.inf)
        return
    spread = np.array(found)
    low, high = np.array(system.u_min), np.array(system.u_max)
    jet = system.closed_form_source().function()
    for _ in range(4):
        x, u = x_k.copy(), np.where(rng.random(2) < 0.5, low, high)
        psi = mean + 2.0 * std * rng.choice([-1.0, 1.0], 7)
        whole, rest = divmod(horizon, 1e-3)
        for dt in [1e-3] * int(whole) + ([rest] if rest > 0 else []):
            if rng.random() < 0.05:
                u = np.where(rng.random(2) < 0.5, low, high)
                psi = mean + 2.0 * std * rng.choice([-1.0, 1.0], 7)
            f, _, g = jet(x)
            x = x + dt * (f + g @ u + psi)
            assert np.all(np.abs(x - x_k) <= spread + 1e-12), (x - x_k, spread)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), period=st.floats(0.01, 0.15), latency=st.floats(0.0, 0.1))
def test_cascaded_rows_on_the_unicycle_take_the_interval_margin_and_it_holds(data, period,
                                                                           latency):
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    system = Unicycle(u_min=(-2.0, -3.0), u_max=(2.5, 1.5))
    families = (cascade(CircleObstacles(centers=((0.5, -0.3),), radii=(0.4,), margin=0.1),
                        system, [2.0]),
                cascade(HalfPlane(normals=((0.6, 0.8),), offsets=(-2.0,)), system, [1.0]),
                BandBarrier(index=2, half_width=1.0, center=0.0),
                # the look-ahead point follows the direction of travel: either point's row
                CircleObstacles(centers=((-0.5, 0.8),), radii=(0.3,), margin=0.1,
                                heading_index=2, lookahead=0.05, speed_input=0))
    problem = RCBFProblem(system=system, families=families, alpha=5.0, k_c=2.0)
    margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency)
    assert isinstance(margin, IntervalMargin)
    x_k = np.array([*rng.uniform(-2, 2, 2), rng.uniform(-math.pi, math.pi)])
    mean, std = rng.uniform(-0.2, 0.2, 3), rng.uniform(0.0, 0.1, 3)
    rest, linear = margin.split_rows(x_k.tolist(), mean.tolist(), std.tolist())
    for switching in (False, True):
        change, held = _true_change(problem, x_k, mean, std, period + latency, rng, switching)
        nu = rest + linear @ np.abs(held)  # the margin of this command
        assert np.all(change <= nu + 1e-9), (change, nu, held)


def test_no_fine_step_violation_on_pvtol_with_the_margin_and_some_without():
    worlds = _pvtol_worlds()
    tight = bench.simulate_pvtol(worlds, period=T, latency=L, tightened=True, duration=2.0)
    loose = bench.simulate_pvtol(worlds, period=T, latency=L, tightened=False, duration=2.0)
    assert not tight.violated.any() and not tight.touched.any(), tight.least_h
    assert tight.fail_safe == 0  # the margin keeps the rows feasible: the drone flies
    assert loose.violated.sum() >= 2 and loose.touched.sum() >= 1, loose.least_h


@functools.cache
def _pvtol_worlds() -> list:
    """The benchmark's first worlds (two of them violated by the continuous-time rows, held
    and delayed)."""
    return bench.pvtol_worlds(4, 0)


@settings(max_examples=15, deadline=None)
@given(state=st.tuples(*[st.floats(-1e6, 1e6)] * 7),
       mean=st.tuples(*[st.floats(-1e6, 1e6)] * 7), std=st.tuples(*[st.floats(0, 1e6)] * 7))
def test_hostile_states_and_boxes_on_pvtol_give_a_verified_answer_or_the_fail_safe(
        state, mean, std):
    result = _pvtol_filter().filter(state, [2.5, -2.5], mean, std)
    assert result.fail_safe or result.needed_slack <= 1e-4
    assert np.all(np.abs(result.u_safe) <= 2.5)


def test_a_margin_without_bound_is_infinite_and_the_filter_answers_with_its_fail_safe():
    problem = _pvtol_problem(5.0, (1.0, 1.0))
    margin = sampled_data_margin(problem, control_period_s=T, latency_s=L)
    hover, zero = [-4.0, 0.0, 0.0, 0.0, 0.0, 1.0, -4.0], [0.0] * 7
    assert np.all(np.isfinite(margin.rows(hover, zero, zero)))
    unbounded = [0.0, 0.0, 0.0, 0.0, math.inf, 0.0, 0.0]  # no enclosure: every margin inf
    assert np.all(margin.rows(hover, zero, unbounded) == math.inf)
    far = [1e300, 0.0, 1e300, 0.0, 0.0, 1e300, 0.0]  # overflows: inf, never NaN
    nu = margin.rows(far, zero, zero)
    assert not np.isnan(nu).any() and np.isinf(nu).any(), nu
    for state, std in ((hover, [0.0, 0.0, 0.0, 0.0, 1e300, 0.0, 0.0]), (far, zero)):
        result = _pvtol_filter().filter(state, [0.0, 0.0], zero, std)
        assert result.fail_safe and np.array_equal(result.u_safe, [0.0, 0.0]), result


@functools.cache
def _pvtol_filter(command_linear: bool = True) -> SafetyFilter:
    """PVTOL's shipped filter with the margin (built once); ``command_linear`` False: with the
    constant margin of the largest input instead."""
    problem = filter_config_from_params(load_params(find_config('pvtol'), 'safety_filter')
                                        ).problem
    safety_filter = SafetyFilter(problem, control_period_s=T, latency_s=L,
                                 slack_tolerance=1e-4)
    if not command_linear:
        safety_filter._margin = sampled_data_margin(problem, control_period_s=T, latency_s=L,
                                                    command_linear=False)
    return safety_filter


def test_the_config_builds_pvtol_with_the_margin_and_the_rows_carry_it():
    params = load_params(find_config('pvtol'), 'safety_filter')
    params.update(control_period_s=T, latency_s=L, alpha=10.0)  # alpha 1: see the next test
    config = filter_config_from_params(params)
    assert (config.control_period_s, config.latency_s) == (T, L)
    plain = SafetyFilter(config.problem)
    tight = SafetyFilter(config.problem, control_period_s=T, latency_s=L)
    state, box = [-4.5, 2.0, 0.0, 0.0, 0.0, 1.0, -4.5], ([0.0] * 7, [0.0] * 7)
    proposal = [0.3, -0.2]
    margin = sampled_data_margin(config.problem, control_period_s=T, latency_s=L)
    rest, linear = margin.split_rows(state, *box)
    nu = rest + linear @ np.abs(proposal)  # the margin of this command
    a, b = plain.filter(state, proposal, *box), tight.filter(state, proposal, *box)
    assert np.all(nu > 0) and not a.active and not b.active
    assert a.constraint_values - b.constraint_values == pytest.approx(nu)


def test_in_hover_the_thrust_band_takes_a_margin_that_follows_the_thrust_rate():
    """The thrust row -2 (f - 1) u_f + alpha h changes by up to 2 (tau U) |u_f| while f moves
    under the held command. The constant margin charges the largest rate, 2 (tau U) U = 0.25
    for tau = 20 ms and U = 2.5, as large as alpha h = 0.25 in hover with alpha = 1
    (config/pvtol.yaml): with it the filter answers with its fail-safe there. The margin that
    follows the command charges 2 (tau U) |u_f|, about 0 for the hover command, which then
    passes."""
    problem = filter_config_from_params(load_params(find_config('pvtol'), 'safety_filter')
                                        ).problem
    hover, zero = [-4.5, 2.0, 0.0, 0.0, 0.0, 1.0, -4.5], [0.0] * 7
    thrust = problem.barrier_names.index('thrust')
    margin = sampled_data_margin(problem, control_period_s=T, latency_s=L)
    nu = margin.rows(hover, zero, zero)
    assert 2.0 * (T + L) * 2.5 * 2.5 <= nu[thrust] <= 1.2 * 2.0 * (T + L) * 2.5 * 2.5 + 0.01
    rest, linear = margin.split_rows(hover, zero, zero)
    assert 2.0 * (T + L) * 2.5 <= linear[thrust, 1] and rest[thrust] < 0.05  # [omega, u_f]
    constant = _pvtol_filter(command_linear=False).filter(hover, [0.0, 0.0], zero, zero)
    assert constant.fail_safe
    linear_result = _pvtol_filter(command_linear=True).filter(hover, [0.0, 0.0], zero, zero)
    assert not linear_result.fail_safe and linear_result.needed_slack <= 1e-4
    short = sampled_data_margin(problem, control_period_s=0.005).rows(hover, zero, zero)
    assert short[thrust] < 0.25


def test_a_pvtol_without_the_operator_has_the_margin_too():
    problem = RCBFProblem(system=PVTOL(with_operator=False), families=(
        cascade(CircleObstacles(centers=((0.0, 1.0),), radii=(0.4,), margin=0.1),
                PVTOL(with_operator=False), [1.0, 1.0]),))
    margin = sampled_data_margin(problem, control_period_s=T)
    assert margin.rows([0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [0.0] * 6, [0.0] * 6).shape == (1,)

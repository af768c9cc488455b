"""Car Following between samples: the bound behind its refusal
(benchmarks/_car_following_bound.py, CarFollowingBound) holds along fine-step trajectories
across the braking switches, and pays a switch's jump exactly where the switch can be reached.

The bound is checked along 1 ms Euler trajectories of the prior plus a disturbance in the box,
car 4's input at the limits (switching at random), from states whose gaps sit near, on and
across the switches of cars 2, 3 and 5: its speeds and gaps' reach hold the trajectory, and
the true decrease of each cascaded gap row's left side, evaluated by the torch assembly of
RCBFProblem.qp (autograd through the cascade: not the bound's code), stays within it, term by
term (the rest within nu0, L_g h* within c).
"""
from __future__ import annotations

from dataclasses import replace

from benchmark_modules import load_benchmark
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.parameters.rules import find_config, load_params

bench = load_benchmark('bench_sampled_data')
CarFollowingBound = load_benchmark('_car_following_bound').CarFollowingBound

K_B = 20.0
"""The prior's braking gain (rcbf_ros/core/dynamics.py, CarFollowing.k_b)."""


def _problem(limit: float, alpha: float = 5.0, gamma: float = 8.0) -> RCBFProblem:
    """config/car_following.yaml's cascaded gap rows with limits +/- ``limit``."""
    params = load_params(find_config('car_following'), 'safety_filter')
    params.update({'input_limits.min': [-limit], 'input_limits.max': [limit],
                   'alpha': alpha, 'gaps.gammas': [gamma]})
    return filter_config_from_params(params).problem


def _hostile_state(rng: np.random.Generator) -> np.ndarray:
    """Positions with the gaps of cars 2, 3 (to the car ahead) near 6 m and of car 5 to car 3
    near 12 m (on either side, sometimes exactly on the switch, sometimes anywhere within
    +/- 15 m: cars overtaken), car 4 anywhere between; speeds 30 +/- 8 m/s (sometimes all at
    v_des)."""
    def gap(switch: float) -> float:
        pick = rng.random()
        if pick < 0.15:
            return switch
        if pick < 0.3:
            return rng.uniform(-15.0, 15.0)
        return switch + rng.uniform(-0.6, 0.6)

    p5 = 0.0
    p3 = p5 + gap(12.0)
    p2 = p3 + gap(6.0)
    p1 = p2 + gap(6.0)
    p4 = p5 + rng.uniform(-3.0, 15.0)
    speeds = np.full(5, 30.0) if rng.random() < 0.1 else 30.0 + rng.uniform(-8.0, 8.0, 5)
    state = np.empty(10)
    state[0::2] = (p1, p2, p3, p4, p5)
    state[1::2] = speeds
    return state


def _trajectory(problem: RCBFProblem, x_k: np.ndarray, mean: np.ndarray, std: np.ndarray,
                horizon: float, rng: np.random.Generator) -> np.ndarray:
    """(steps + 1, 10) one 1 ms Euler trajectory of the prior plus a disturbance at vertices
    of the box and car 4's input at its limits (both switching at random)."""
    system = problem.system
    limit = system.u_max[0]
    whole, rest = divmod(horizon, 1e-3)
    steps = [1e-3] * int(whole) + ([rest] if rest > 0 else [])
    u = limit * rng.choice([-1.0, 1.0])
    psi = mean + problem.k_c * std * rng.choice([-1.0, 1.0], 10)
    states, x = [x_k], torch.tensor(x_k)[None]
    for dt in steps:
        if rng.random() < 0.1:
            u = limit * rng.choice([-1.0, 1.0])
            psi = mean + problem.k_c * std * rng.choice([-1.0, 1.0], 10)
        x_dot = system.f(x) + system.g(x)[..., 0] * u
        x = x + dt * (x_dot + torch.tensor(psi)[None])
        states.append(x[0].numpy())
    return np.array(states)


def _rows(problem: RCBFProblem, states: np.ndarray, mean: np.ndarray, std: np.ndarray,
          held: float) -> np.ndarray:
    """(steps + 1, K) phi_i(x, u) along ``states`` at the command u = ``held``, by the torch
    assembly of the QP."""
    batch = torch.tensor(states, dtype=torch.float64)
    count = batch.shape[0]
    qp = problem.qp(batch, torch.full((count, 1), held, dtype=torch.float64),
                    torch.tensor(mean).expand(count, 10), torch.tensor(std).expand(count, 10))
    return qp.h[:, :problem.n_barriers].numpy()


def _decrease(problem: RCBFProblem, x_k: np.ndarray, mean: np.ndarray, std: np.ndarray,
              horizon: float, held: float, rng: np.random.Generator) -> np.ndarray:
    """The largest phi_i(x_k, u) - phi_i(x(t), u) along one :func:`_trajectory`, phi at the
    held command u = ``held``."""
    phi = _rows(problem, _trajectory(problem, x_k, mean, std, horizon, rng), mean, std, held)
    return (phi[0] - phi).max(axis=0)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), period=st.floats(0.005, 0.1), latency=st.floats(0.0, 0.1),
       limit=st.sampled_from([1.0, 10.0, 50.0]), alpha=st.sampled_from([1.0, 5.0, 15.0]),
       gamma=st.sampled_from([2.0, 8.0]))
def test_the_true_decrease_of_every_gap_row_stays_within_the_bound(data, period, latency,
                                                                   limit, alpha, gamma):
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    problem = _problem(limit, alpha, gamma)
    x_k = _hostile_state(rng)
    mean, std = np.zeros(10), np.zeros(10)
    if data.draw(st.booleans()):
        mean = rng.uniform(-1.0, 1.0, 10) * (rng.random(10) < 0.5)
        std = rng.uniform(0.0, 3.0, 10) * (rng.random(10) < 0.5)
    bound = CarFollowingBound(problem, period + latency)
    rest, linear, braking = bound.parts(x_k, mean, std)
    assert np.all(np.isfinite(rest)) and np.all(linear >= 0.0) and np.all(braking <= rest)
    w = np.abs(mean) + problem.k_c * std
    speeds, _ = bound._motion(x_k, w, bound._switches(x_k, w)[0])
    reach = bound._switches(x_k, w)[1]
    tau = period + latency
    for _ in range(3):
        states = _trajectory(problem, x_k, mean, std, tau, rng)
        # every speed within tau R of its start, every follower's gap within its interval S
        assert np.all(np.abs(states[:, 1::2] - x_k[1::2]) <= tau * speeds + 1e-9)
        for car, (lo, hi, _) in reach.items():
            leader = {1: 0, 2: 1, 4: 2}[car]
            gap = states[:, 2 * leader] - states[:, 2 * car]
            assert np.all((lo - 1e-9 <= gap) & (gap <= hi + 1e-9)), (car, lo, hi)
        # the rest (phi at u = 0) falls by at most nu0, L_g h changes by at most c, and the
        # row of a held command by at most nu0 + c |u|
        still = _rows(problem, states, mean, std, 0.0)
        assert np.all((still[0] - still).max(axis=0) <= rest + 1e-9), (x_k, rest, braking)
        moved = _rows(problem, states, mean, std, 1.0) - still  # L_g h along the trajectory
        assert np.all(np.abs(moved - moved[0]).max(axis=0) <= linear[:, 0] + 1e-9)
        for held in (limit * rng.uniform(-1.0, 1.0), limit, -limit):
            phi = _rows(problem, states, mean, std, held)
            assert np.all((phi[0] - phi).max(axis=0)
                          <= rest + linear[:, 0] * abs(held) + 1e-9), (x_k, held)


def test_a_switch_that_can_be_reached_pays_its_jump_and_one_that_cannot_pays_nothing():
    problem = _problem(10.0)
    bound = CarFollowingBound(problem, 0.04)
    box = (np.zeros(10), np.full(10, 0.5))
    # car 3 exactly on its switch (6 m behind car 2), car 5 inside its own, 0.1 m from it
    # (11.9 m behind car 3), car 4 4 m behind car 3: car 3 may start braking (row 3-4 loses
    # k_b 6 d_34), car 5 may stop (row 4-5 loses k_b 11.9 |d_45|)
    on = np.array([40.0, 30.0, 34.0, 30.0, 28.0, 30.0, 24.0, 30.0, 16.1, 30.0])
    _, _, braking = bound.parts(on, *box)
    assert braking == pytest.approx([K_B * 6.0 * 4.0, K_B * 11.9 * 7.9])
    # the same cars 0.5 m farther from every switch, at equal speeds: no switch within 40 ms
    away = on + np.array([1.5, 0, 1.0, 0, 0.5, 0, 0.5, 0, -0.4, 0])
    _, _, braking = bound.parts(away, *box)
    assert np.all(braking == 0.0)
    # car 3 braking already (5 m behind car 2) only gets closer to braking harder: row 3-4
    # pays the change of k_b (p_2 - p_3) within the switch, k_b times the gap's reach
    inside = on + np.array([-1.0, 0, -1.0, 0, 0, 0, 0, 0, 0, 0])
    _, _, braking = bound.parts(inside, *box)
    assert 0.0 < braking[0] < 0.1 * K_B * 6.0 * 4.0


def test_a_leaders_braking_that_carries_its_follower_into_the_switch_is_paid():
    """Car 2 3 m behind car 1 brakes at k_b 3 = 60 m/s^2; car 3, 6.05 m behind car 2 at the
    same speed, is carried into its own switch within 0.1 s by car 2's braking alone (0.3 m),
    and row 3-4 then loses k_b (p_2 - p_3) d_34: the bound charges it, and the trajectory's
    true decrease stays within it."""
    problem = _problem(10.0)
    x_k = np.array([37.0, 30.0, 34.0, 30.0, 27.95, 30.0, 23.95, 30.0, 10.0, 30.0])
    zero = np.zeros(10)
    rest, linear, braking = CarFollowingBound(problem, 0.1).parts(x_k, zero, zero)
    assert braking[0] > 0.5 * K_B * 6.0 * 4.0
    rng = np.random.default_rng(0)
    decrease = _decrease(problem, x_k, zero, zero, 0.1, 0.0, rng)
    assert decrease[0] > 0.5 * K_B * 6.0 * 4.0  # the jump happened along the trajectory
    assert np.all(decrease <= rest)


@pytest.mark.parametrize(('horizon', 'entry', 'value'), [
    (0.25, None, 0.0), (0.04, 'state', np.nan), (0.04, 'state', np.inf),
    (0.04, 'std', np.nan), (0.04, 'mean', -np.inf)])
def test_no_bound_where_the_speeds_cannot_be_bounded_or_the_data_is_not_finite(
        horizon, entry, value):
    """tau k_v >= 1 (the speeds' bound does not close) or a non-finite state or box: the
    margins are inf (a filter would answer with its fail-safe)."""
    data = {'state': np.full(10, 30.0), 'mean': np.zeros(10), 'std': np.zeros(10)}
    if entry is not None:
        data[entry][3] = value
    rest, linear, _ = CarFollowingBound(_problem(10.0), horizon).parts(
        data['state'], data['mean'], data['std'])
    assert np.all(rest == np.inf) and np.all(linear == 0.0)


def test_the_bound_needs_the_cars_with_limits_and_cascaded_gaps():
    problem = _problem(10.0)
    with pytest.raises(ValueError, match='input limits'):
        CarFollowingBound(replace(problem, system=replace(problem.system, u_min=None,
                                                          u_max=None)), 0.04)
    with pytest.raises(ValueError, match='cascaded once'):
        CarFollowingBound(replace(problem, families=(problem.families[0].base,)), 0.04)


def test_the_benchmarks_car_physics_are_the_envs():
    """bench_sampled_data's Car Following run steps rcbf_ros/envs/car_following.py's true
    accelerations: the fine-step run on a short horizon keeps its decisions' count and meets
    every row where the untightened rows hold (a smoke check of the section)."""
    starts = bench.car_starts(1, seed=0)
    out = bench.simulate_cars(starts[:1], period=0.02, latency=0.02, tightened=False,
                              limit=50.0, duration=0.5)
    assert out.decided.tolist() == out.feasible.tolist() == [25]
    assert out.box_left == 0


def test_the_shipped_start_has_no_command_meeting_the_tightened_rows():
    """The refusal's reason at its first decision (docs/SAFETY_FILTER.md): the shipped start at
    T = L = 20 ms, limits +/- 50, the benchmark's box. The continuous-time rows leave commands;
    the tightened rows leave none, car 3 sitting on its switch (row 3-4 pays k_b 6 d_34)."""
    start = bench.car_starts(0, seed=0)[0]
    problem = _problem(50.0)
    mean, std = bench.car_box(0.1)
    from rcbf_ros.core.lie_closed_form import ClosedFormTerms
    at = ClosedFormTerms.from_problem(problem).terms(start)
    rho = at.grad_h @ mean - problem.k_c * np.abs(at.grad_h) @ std
    upper, lg = at.lf_h + rho + problem.alpha * at.h, at.lg_h[:, 0]
    assert bench.car_decide(upper, lg, 5.0, 50.0) is not None
    rest, linear, braking = CarFollowingBound(problem, 0.04).parts(start, mean, std)
    assert braking[0] == pytest.approx(K_B * 6.0 * (start[4] - start[6]))
    assert bench.car_decide(np.concatenate([upper - rest] * 2),
                            np.concatenate([lg - linear[:, 0], lg + linear[:, 0]]),
                            5.0, 50.0) is None

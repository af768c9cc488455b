"""Simulated systems: true dynamics vs hand-computed Euler steps, reward, goal, determinism."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.envs import (
    CarFollowingEnv,
    env_class,
    gymnasium_id,
    make_env,
    PVTOLEnv,
    UnicycleEnv,
)
from rcbf_ros.messages.systems import system_names
from rcbf_ros.parameters.rules import find_config, load_params


def sim_params(system: str) -> dict:
    return load_params(find_config(system), 'simulator')


def test_unicycle_step_matches_hand_euler_with_slope():
    env = UnicycleEnv(sim_params('unicycle'), start=[0.1, -0.2, 0.7])
    env.reset(seed=0)
    u = np.array([1.2, -0.4])
    _, _, _, _, info = env.step(u)
    # x_dot = g(x) (u + u_d), u_d = -0.1 cos(theta) [1, 0]
    x, y, th = 0.1, -0.2, 0.7
    v = 1.2 - 0.1 * math.cos(th)
    expected = [x + 0.02 * v * math.cos(th), y + 0.02 * v * math.sin(th), th + 0.02 * -0.4]
    np.testing.assert_allclose(info['state'], expected, rtol=0, atol=1e-12)


def test_car_following_step_matches_hand_euler_with_gains():
    env = CarFollowingEnv(sim_params('car_following'), velocity_noise=0.0,
                          initial_positions=[40.0, 35.0, 22.0, 16.0, 12.0])
    env.reset(seed=0)
    env.step([0.0])  # t = 0 -> t = dt: the leader's sinusoid is 0 at t = 0
    s = env.state
    u4 = 2.0
    _, _, _, _, info = env.step([u4])
    p, v = s[0::2], s[1::2]
    t = 0.02
    track = 4.0 * (30.0 - v)
    a = np.array([
        track[0] + 10.0 * math.sin(0.2 * t),
        track[1] - 20.0 * (p[0] - p[1]) if abs(p[0] - p[1]) < 6 else track[1],
        track[2] - 20.0 * (p[1] - p[2]) if abs(p[1] - p[2]) < 6 else track[2],
        0.0,
        track[4] - 20.0 * (p[2] - p[4]) if abs(p[2] - p[4]) < 12 else track[4],
    ]) * 1.1
    a[3] = u4
    expected = np.empty(10)
    expected[0::2] = p + 0.02 * v
    expected[1::2] = v + 0.02 * a
    np.testing.assert_allclose(info['state'], expected, rtol=0, atol=1e-10)
    # Car 5 at 10 m behind car 3 brakes: the branch must have been taken.
    assert abs(p[2] - p[4]) < 12


def test_pvtol_step_matches_hand_euler_with_attitude_error_and_operator():
    env = PVTOLEnv(sim_params('pvtol'), operator_noise=0.0)
    env.reset(seed=0)
    env._state = np.array([-1.0, 0.5, 0.3, -0.2, 0.25, 1.3, -1.2])
    u = np.array([0.4, -0.6])
    _, _, _, _, info = env.step(u)
    x1, x2, v1, v2, th, f, xh = -1.0, 0.5, 0.3, -0.2, 0.25, 1.3, -1.2
    d_omega = 0.1 * ((f - 1.0) - math.sin(th))
    expected = [x1 + 0.02 * v1, x2 + 0.02 * v2, v1 + 0.02 * (-math.sin(th) * f),
                v2 + 0.02 * (math.cos(th) * f - 1.0), th + 0.02 * (0.4 + d_omega),
                f + 0.02 * -0.6, xh + 0.02 * 3.5 * (x1 - xh)]
    np.testing.assert_allclose(info['state'], expected, rtol=0, atol=1e-12)
    assert info['h_true'][-1] == pytest.approx(0.6 - abs(expected[0] - expected[6]))


def test_actions_saturate_at_the_actuator_limits():
    env = UnicycleEnv(sim_params('unicycle'), start=[0.0, 0.0, 0.0], obstacles__x=[],
                      obstacles__y=[], obstacles__radius=[])
    env.reset(seed=0)
    _, _, _, _, info = env.step([10.0, 0.0])
    assert info['state'][0] == pytest.approx(0.02 * (2.5 - 0.1))


def test_unicycle_reward_is_progress_and_goal_terminates_with_bonus():
    env = UnicycleEnv(sim_params('unicycle'), start=[2.5 - 0.31, 2.5, 0.0])
    env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step([1.0, 0.0])
    moved = 0.02 * (1.0 - 0.1)
    assert info['goal_reached'] and terminated and not truncated
    assert reward == pytest.approx(moved + 1.0)
    env = UnicycleEnv(sim_params('unicycle'), start=[-2.0, -2.5, 0.0], max_steps=3)
    env.reset(seed=0)
    rewards = []
    for _ in range(3):
        _, reward, terminated, truncated, info = env.step([1.0, 0.0])
        rewards.append(reward)
    assert truncated and not terminated and not info['goal_reached']
    d0 = math.hypot(4.5, 5.0)
    d3 = math.hypot(4.5 - 3 * 0.02 * 0.9, 5.0)
    assert sum(rewards) == pytest.approx(d0 - d3)


def test_pvtol_goal_bonus_and_car_reward():
    env = PVTOLEnv(sim_params('pvtol'), start=[5.0, -1.5 + 0.29])
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step([0.0, 0.0])
    assert terminated and info['goal_reached'] and reward > 3.0 - 0.01
    cars = CarFollowingEnv(sim_params('car_following'))
    cars.reset(seed=0)
    _, reward, terminated, truncated, _ = cars.step([3.0])
    assert reward == pytest.approx(-9.0 / 300.0) and not terminated and not truncated


def test_observations_follow_their_documented_layout():
    env = UnicycleEnv(sim_params('unicycle'), start=[0.0, 0.0, math.pi / 2])
    obs, _ = env.reset(seed=0)
    # Goal at (2.5, 2.5), heading +y: in the body frame the goal is ahead (x) and to the right.
    assert obs[:4] == pytest.approx([0.0, 0.0, 0.0, 1.0], abs=1e-12)
    assert obs[4] > 0 and obs[5] < 0
    assert obs[6] == pytest.approx(math.exp(-math.hypot(2.5, 2.5)))
    cars = CarFollowingEnv(sim_params('car_following'), velocity_noise=0.0)
    obs, _ = cars.reset(seed=0)
    assert obs.shape == (15,) and obs[9] == pytest.approx(0.16)
    assert obs[10] == pytest.approx(35 / 30)


@pytest.mark.parametrize('system, kwargs', [
    ('unicycle', {'layout': 'random', 'random_start': True}),
    ('car_following', {}),
    ('pvtol', {'layout': 'random', 'random_start': True}),
])
def test_same_seed_same_trajectory(system, kwargs):
    def rollout(seed):
        env = make_env(system, sim_params(system), **kwargs)
        rng = np.random.default_rng(123)
        obs, info = env.reset(seed=seed)
        states, layout = [info['state']], env.filter_params()
        for _ in range(30):
            _, _, term, trunc, info = env.step(rng.uniform(-1, 1, env.nominal_system.n_u))
            states.append(info['state'])
            if term or trunc:
                break
        return np.concatenate(states), layout

    a, layout_a = rollout(7)
    b, layout_b = rollout(7)
    c, _ = rollout(8)
    np.testing.assert_array_equal(a, b)
    assert layout_a == layout_b
    assert a.shape != c.shape or not np.array_equal(a, c)


@pytest.mark.parametrize('system', ['unicycle', 'car_following', 'pvtol'])
def test_filter_params_build_the_current_layout(system):
    kwargs = {} if system == 'car_following' else {'layout': 'random'}
    env = make_env(system, sim_params(system), **kwargs)
    env.reset(seed=3)
    config = filter_config_from_params(env.filter_params())
    problem = config.problem
    assert problem.system.n_x == env.state.size
    if system != 'car_following':
        assert env.filter_params()['obstacles.x'] == [o.x for o in env.obstacles]
        n_obstacles = len(env.obstacles)
        assert sum(n.startswith('obstacle') for n in problem.barrier_names) == n_obstacles
        assert any(n.startswith('operator') for n in problem.barrier_names) == (
            system == 'pvtol' and env.with_operator)


def test_pvtol_without_operator_drops_state_and_band():
    env = PVTOLEnv(sim_params('pvtol'), system_params__with_operator=False)
    _, info = env.reset(seed=0)
    assert info['state'].shape == (6,)
    params = env.filter_params()
    assert not any(k.startswith('bands.operator') for k in params)
    assert filter_config_from_params(params).problem.system.n_x == 6


def test_bad_parameters_name_the_key():
    with pytest.raises(ValueError, match='goal_radius'):
        UnicycleEnv(sim_params('unicycle'), goal_radius=-1.0)
    with pytest.raises(ValueError, match='obstacles.y'):
        UnicycleEnv(sim_params('unicycle'), obstacles__y=[0.0])
    with pytest.raises(ValueError, match='layout'):
        PVTOLEnv(sim_params('pvtol'), layout='maze')
    with pytest.raises(ValueError, match='system'):
        UnicycleEnv(sim_params('pvtol'))
    env = UnicycleEnv(sim_params('unicycle'))
    env.reset(seed=0)
    with pytest.raises(ValueError, match='action'):
        env.step([1.0])


@pytest.mark.parametrize('system', system_names())
def test_registered_with_gymnasium_and_passes_its_checker(system):
    """gymnasium.make builds the same env as make_env, and Gymnasium's own checker (spaces,
    reset/step signatures, seeding determinism, dtypes) accepts it."""
    import gymnasium
    from gymnasium.utils.env_checker import check_env
    params = load_params(find_config(system), 'simulator')
    env = gymnasium.make(gymnasium_id(system), params=params)
    assert isinstance(env.unwrapped, env_class(system))
    check_env(env.unwrapped, skip_render_check=True)
    ours = make_env(system, params)
    obs_gym, _ = env.reset(seed=3)
    obs_ours, _ = ours.reset(seed=3)
    np.testing.assert_array_equal(obs_gym, obs_ours)
    action = ours.action_space.sample() if np.isfinite(ours.action_space.high).all() else \
        np.zeros(ours.action_space.shape)
    np.testing.assert_array_equal(env.step(action)[0], ours.step(action)[0])


def test_make_env_takes_a_dotted_path_as_well_as_a_name():
    """One registry: a built-in name and the dotted path of its class build the same env."""
    params = sim_params('pvtol')
    by_name = make_env('pvtol', params)
    by_path = make_env('rcbf_ros.envs.pvtol.PVTOLEnv', params)
    assert type(by_path) is type(by_name) is PVTOLEnv
    np.testing.assert_array_equal(by_path.reset(seed=5)[0], by_name.reset(seed=5)[0])
    action = np.array([0.3, -0.2])
    np.testing.assert_array_equal(by_path.step(action)[0], by_name.step(action)[0])


@pytest.mark.parametrize('system, match', [
    ('segway', "no simulator for 'segway'"),
    ('rcbf_ros.envs.nowhere.Env', "cannot import 'rcbf_ros.envs.nowhere.Env'"),
    ('rcbf_ros.envs.unicycle.Missing', "cannot import 'rcbf_ros.envs.unicycle.Missing'"),
    ('rcbf_ros.core.dynamics.Unicycle', 'not a subclass of rcbf_ros.envs.base.SafetyEnv'),
])
def test_make_env_names_the_system_it_cannot_build(system, match):
    with pytest.raises(ValueError, match=f'^system: .*{match}'):
        make_env(system, sim_params('unicycle'))

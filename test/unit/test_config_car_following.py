"""The shipped Car Following gains keep the QP feasible from the first step on.

With gamma_1 = 2 the cascaded barrier was already negative at reset (car 4 starts 5 m/s faster
than car 3, 6 m behind), the filter demanded extreme braking that the rear gap row contradicted,
and the QP ran on slack (up to ~250) in most episodes; in one training run the true gap
crossed 3.5 m. These tests pin the fix.
"""
from __future__ import annotations

import numpy as np
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.envs import make_env
from rcbf_ros.envs.nominal import cars_accelerate
from rcbf_ros.parameters.rules import find_config, load_params


def _env_and_filter():
    path = find_config('car_following')
    env = make_env('car_following', load_params(path, 'simulator'))
    config = filter_config_from_params(env.filter_params(load_params(path, 'safety_filter')))
    return env, config.problem, SafetyFilter(config.problem)


def test_reset_states_are_inside_the_cascaded_safe_set():
    env, problem, _ = _env_and_filter()
    for seed in range(20):
        _, info = env.reset(seed=seed)
        h_star = problem.terms(torch.as_tensor(info['state'])[None]).h[0]
        assert (h_star > 0).all(), (seed, h_star)


def test_unsafe_controllers_never_need_real_slack():
    env, _, safety_filter = _env_and_filter()
    rng = np.random.default_rng(0)
    max_slack, violations = 0.0, 0
    for episode in range(4):
        _, info = env.reset(seed=episode)
        done = False
        while not done:
            x = info['state']
            u = cars_accelerate(x) if episode % 2 == 0 else rng.uniform(-10, 10, 1)
            result = safety_filter.filter(x, u)
            max_slack = max(max_slack, result.slack)
            _, _, terminated, truncated, info = env.step(result.u_safe)
            violations += int(info['violation'])
            done = terminated or truncated
    assert violations == 0
    assert max_slack < 1e-3  # only the soft penalty's ~1e-5, never a conflict

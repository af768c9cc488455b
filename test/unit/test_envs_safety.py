"""Core integration without middleware: unsafe controllers + SafetyFilter -> zero true violations.

Each env runs with the safety problem its own ``filter_params()`` builds (config/*.yaml, no
disturbance estimate: the true disturbances stay unknown to the filter). The same controllers
without the filter do violate, and the filter is shown to be active near the boundary, so the
zero is earned by the filter.
"""
from __future__ import annotations

import numpy as np

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.envs import make_env
from rcbf_ros.envs.nominal import cars_accelerate, pvtol_go_to_goal, unicycle_go_to_goal
from rcbf_ros.parameters.rules import find_config, load_params


def controller(env):
    if env.system_name == 'unicycle':
        return lambda x: unicycle_go_to_goal(x, env.goal)
    if env.system_name == 'pvtol':
        return lambda x: pvtol_go_to_goal(x, env.goal)
    return lambda x: cars_accelerate(x)


def run(system: str, seed: int, *, filtered: bool, **overrides) -> dict:
    env = make_env(system, load_params(find_config(system), 'simulator'), **overrides)
    _, info = env.reset(seed=seed)
    config = filter_config_from_params(env.filter_params())
    safety = SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action)
    nominal = controller(env)
    steps = violations = fail_safes = 0
    min_h_true, min_h_filter = np.inf, np.inf
    done = False
    while not done:
        u = nominal(info['state'])
        if filtered:
            result = safety.filter(info['state'], u)
            fail_safes += result.fail_safe
            min_h_filter = min(min_h_filter, float(result.h.min()))
            u = result.u_safe
        _, _, terminated, truncated, info = env.step(u)
        steps += 1
        violations += info['violation']
        min_h_true = min(min_h_true, float(info['h_true'].min()))
        done = terminated or truncated
    return {'steps': steps, 'violations': violations, 'fail_safes': fail_safes,
            'min_h_true': min_h_true, 'min_h_filter': min_h_filter,
            'goal': info['goal_reached']}


def test_unicycle_filtered_go_to_goal_never_violates():
    runs = [run('unicycle', 0, filtered=True),
            *(run('unicycle', seed, filtered=True, layout='random', random_start=True)
              for seed in range(1, 6))]
    assert all(r['violations'] == 0 and r['fail_safes'] == 0 for r in runs)
    # The filter held the robot at its boundary (it was pushed into an obstacle) ...
    assert min(r['min_h_true'] for r in runs) < 0.25
    # ... and, with cheap steering (config input_weight), led it around: every run reaches the
    # goal, where equal weights leave it stopped in front of the first obstacle on its line.
    assert all(r['goal'] for r in runs)
    unfiltered = run('unicycle', 0, filtered=False)
    assert unfiltered['violations'] > 0


def test_car_following_filtered_acceleration_never_violates():
    runs = [run('car_following', seed, filtered=True) for seed in range(3)]
    assert all(r['steps'] == 300 for r in runs)
    assert all(r['violations'] == 0 and r['fail_safes'] == 0 for r in runs)
    assert max(r['min_h_true'] for r in runs) < 0.3  # squeezed to the filter's margin
    assert run('car_following', 0, filtered=False)['violations'] > 0


def test_pvtol_filtered_pd_never_violates_obstacles_or_operator():
    result = run('pvtol', 0, filtered=True)
    # The operator band caps the speed along x1 (the operator follows at 3.5/s): the goal is
    # reached within the episode's 2000 steps.
    assert result['goal']
    assert result['violations'] == 0 and result['fail_safes'] == 0
    assert result['min_h_true'] < 0.2  # held near a boundary (the filter's margins are 0.1)
    assert run('pvtol', 0, filtered=False)['violations'] > 0


def pvtol_filtered(filter_overrides: dict | None = None):
    """(env, reset info, SafetyFilter) of config/pvtol.yaml's training layout, with
    ``filter_overrides`` (flat parameter names) on the env's filter parameters."""
    env = make_env('pvtol', load_params(find_config('pvtol'), 'simulator'))
    _, info = env.reset(seed=0)
    config = filter_config_from_params({**env.filter_params(), **(filter_overrides or {})})
    return env, info, SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action)


def test_pvtol_filtered_random_exploration_stays_in_the_envelope():
    """SAC's first steps are uniform random actions. Through the filter the drone must neither
    collide nor leave the envelope (tilt, thrust band, arena) that keeps the cascaded
    relative-degree-3 rows feasible under |u| <= 2.5; without that envelope the same actions
    flip it (|theta| > pi) and the obstacle and operator rows are then violated."""
    env, info, safety = pvtol_filtered()
    rng = np.random.default_rng(0)
    states, violations = [], 0
    for _ in range(1500):
        result = safety.filter(info['state'], rng.uniform(-2.5, 2.5, size=2))
        _, _, terminated, truncated, info = env.step(result.u_safe)
        states.append(info['state'])
        violations += info['violation']
        assert not (terminated or truncated)
    states = np.array(states)
    assert violations == 0
    assert np.abs(states[:, 4]).max() <= np.pi / 3 + 0.02
    assert 0.5 - 0.02 <= states[:, 5].min() and states[:, 5].max() <= 1.5 + 0.02
    assert np.abs(states[:, 0]).max() <= 6.0 and np.abs(states[:, 1]).max() <= 3.0
    # Exploration is filtered, not frozen: the drone moved and tilted.
    assert np.ptp(states[:, 0]) > 0.5 or np.ptp(states[:, 1]) > 0.5
    assert np.abs(states[:, 4]).max() > 0.05



def bang_bang_run(period: int, thrust_rate: float,
                  filter_overrides: dict | None = None) -> tuple[int, int]:
    """1000 steps of proposals that tilt fully one way, then the other, every ``period`` steps
    (period 0: always the same way), through the PVTOL filter of config/pvtol.yaml with
    ``filter_overrides`` (flat parameter names). Returns (true violations, infeasible steps): a
    step is infeasible when the QP needed slack (> 1e-4) or the solve failed (fail-safe)."""
    env, info, safety = pvtol_filtered(filter_overrides)
    violations = infeasible = 0
    for step in range(1000):
        tilt = 2.5 if period == 0 or (step // period) % 2 else -2.5
        result = safety.filter(info['state'], [tilt, thrust_rate])
        infeasible += result.fail_safe or result.slack > 1e-4
        _, _, terminated, truncated, info = env.step(result.u_safe)
        violations += info['violation']
        assert not (terminated or truncated)
    return violations, infeasible


def test_pvtol_filter_stays_feasible_under_bang_bang_proposals():
    """The relative-degree-3 bands (operator, arena) are written as their two linear sides in
    config/pvtol.yaml. Proposals that throw the drone from one side to the other keep the QP
    feasible (slack at solver precision) and never cross the operator's true band. The
    paper's quadratic form of the same bands does not: its cascade cannot see a fast crossing
    of the centre line (see BandBarrier)."""
    for period, thrust_rate in ((0, 0.0), (100, 0.5), (150, 1.0)):
        assert bang_bang_run(period, thrust_rate) == (0, 0), (period, thrust_rate)
    # The quadratic operator band with cascade gains of 1: a slow bang-bang outruns its cascade,
    # which then needs slack (with the operator at the old 0.5/s it also crossed the true band).
    quadratic = {'bands.operator.form': 'quadratic', 'bands.operator.gammas': [1.0, 1.0]}
    assert bang_bang_run(150, 1.0, quadratic)[1] > 0
    # The quadratic arena: tilting one way for good drives the drone at the arena's wall
    # faster than the cascade can brake.
    assert bang_bang_run(0, 0.0, {'bands.arena_x.form': 'quadratic',
                                  'bands.arena_y.form': 'quadratic'})[1] > 0


def operator_band_slack(gammas: list[float], std: float) -> float:
    """Slack of the PVTOL filter in level hover at the operator band's centre, with a GP std of
    ``std`` on every state and the operator band's cascade gains set to ``gammas``."""
    _, info, safety = pvtol_filtered({'bands.operator.gammas': gammas})
    n_x = safety.problem.system.n_x
    result = safety.filter(info['state'], [0.0, 0.0], np.zeros(n_x), np.full(n_x, std))
    assert not result.fail_safe
    return float(result.slack)


def test_operator_band_gains_match_the_operators_pursuit():
    """The operator follows at k_h = 3.5/s. Each side's top cascade level weighs x1 - x_h by
    (k_h - g1)(k_h - g2): with gains of 1 that is 6.25, and the GP prior's std (0.1, k_c 2) on
    x1 and x_h asks both sides, even in hover at the band's centre, for more margin than they
    can share: the QP needs slack. With gains equal to k_h (config/pvtol.yaml) the weight is 0."""
    assert operator_band_slack([3.5, 3.5], 0.1) < 1e-4
    assert operator_band_slack([1.0, 1.0], 0.1) > 0.1
    assert operator_band_slack([1.0, 1.0], 0.0) < 1e-4  # the std, not the gains alone

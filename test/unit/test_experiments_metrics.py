"""Experiment metrics, definitions, backend selection and the 200 transfer layouts."""
from __future__ import annotations

import importlib.util
import itertools
import math
import socket

import numpy as np
import pytest

from rcbf_ros.experiments import runner
from rcbf_ros.experiments.command import ExperimentRequest, plan_runs
from rcbf_ros.experiments.definitions import (
    BUDGETS,
    experiment_methods,
    experiment_runs,
    METHODS,
    PLAN,
)
from rcbf_ros.experiments.metrics import (
    completion_rate,
    count_violations,
    episode_ending,
    episode_tail,
    final_window_mean,
    mean_std,
    reward_band,
    Tail,
)
from rcbf_ros.experiments.runner import (
    check_reachable,
    parse_address,
    ray_available,
    select_backend,
)


def test_mean_std_is_the_population_std():
    mean, std = mean_std([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5
    assert std == pytest.approx(math.sqrt(1.25))  # ddof=0: sqrt(mean of squared deviations)
    assert mean_std([7.0]) == (7.0, 0.0)
    with pytest.raises(ValueError, match='values'):
        mean_std([])


def test_completion_rate_counts_goals():
    assert completion_rate([True, False, True, True]) == 0.75
    assert completion_rate([0, 0]) == 0.0
    with pytest.raises(ValueError, match='goal_reached'):
        completion_rate([])


def test_count_violations_sums_and_rejects_bad_rows():
    assert count_violations([{'violations': 0}, {'violations': 3}, {'violations': 2}]) == 5
    assert count_violations([]) == 0
    with pytest.raises(ValueError, match='violations: missing in row 1'):
        count_violations([{'violations': 0}, {'ret': 1.0}])
    with pytest.raises(ValueError, match='negative'):
        count_violations([{'violations': -1}])


def test_reward_band_truncates_to_the_shortest_run_and_spans_two_std():
    band = reward_band([[0.0, 2.0, 9.0], [2.0, 6.0]])
    np.testing.assert_array_equal(band.episode, [1, 2])
    np.testing.assert_allclose(band.mean, [1.0, 4.0])
    # population std of {0, 2} is 1 and of {2, 6} is 2; the band is mean +/- 2 std.
    np.testing.assert_allclose(band.lower, [-1.0, 0.0])
    np.testing.assert_allclose(band.upper, [3.0, 8.0])
    assert band.n_runs == 2
    one = reward_band([[1.0, 5.0]], k=3.0)
    np.testing.assert_allclose(one.upper, one.mean)  # one seed: no spread
    with pytest.raises(ValueError, match='curves'):
        reward_band([])
    with pytest.raises(ValueError, match='no episodes'):
        reward_band([[1.0], []])


def test_final_window_mean():
    assert final_window_mean([0.0] * 5 + [1.0, 3.0], window=2) == 2.0
    assert final_window_mean([4.0, 6.0], window=10) == 5.0
    with pytest.raises(ValueError, match='window'):
        final_window_mean([1.0], window=0)


def test_episode_tail_looks_back_window_steps():
    # 5 steps along x by 1, 2, 3, 4, 5 m: positions 0, 1, 3, 6, 10, 15.
    xs = np.cumsum([0.0, 1, 2, 3, 4, 5])
    positions = np.stack([xs, np.zeros(6)], axis=1)
    active = [True, True, False, True, False]
    assert episode_tail(positions, active, window=2) == Tail(9.0, 0.5, 2)
    assert episode_tail(positions, active, window=3) == Tail(12.0, pytest.approx(1 / 3), 3)
    # A window longer than the episode covers all of it; net displacement, not path length.
    back = np.array([[0, 0], [3, 4], [0, 0.5]])
    assert episode_tail(back, [False, False], window=200) == Tail(0.5, 0.0, 2)
    with pytest.raises(ValueError, match='window'):
        episode_tail(positions, active, window=0)
    with pytest.raises(ValueError, match='active'):
        episode_tail(positions[:1], [], window=3)
    with pytest.raises(ValueError, match='positions'):
        episode_tail(positions[:5], active, window=3)


def test_episode_ending_classes():
    assert episode_ending(True, Tail(0.0, 1.0, 200)) == 'goal'
    assert episode_ending(False, Tail(0.1, 1.0, 200)) == 'moving'  # 0.1 m is not still
    assert episode_ending(False, Tail(0.099, 0.5, 200)) == 'held'
    assert episode_ending(False, Tail(0.099, 0.49, 200)) == 'stalled'
    assert episode_ending(False, Tail(0.3, 0.0, 200), still=0.5) == 'stalled'
    assert episode_ending(False, Tail(0.0, 0.3, 200), held_share=0.25) == 'held'


def test_experiment_runs_cover_the_plan_without_duplicates():
    budget = BUDGETS['smoke']
    sample = experiment_runs('sample_efficiency', budget, 3)
    assert len(sample) == (4 + 3) * 3
    assert not any(s.system == 'car_following' and s.method == 'sac_rcbf_mb' for s in sample)
    transfer = experiment_runs('transfer', budget, 2)
    assert {(s.system, s.method) for s in transfer} == {
        (system, m) for system in ('unicycle', 'pvtol') for m in PLAN['transfer'][system]}
    everything = experiment_runs('all', budget, 2)
    # value_maps reuses the Unicycle transfer runs; baseline and MF SAC-RCBF on the Unicycle
    # are shared by sample_efficiency and transfer.
    assert len(everything) == len(set(everything)) == 2 * (4 + 3 + 4 + 4 - 2)
    assert METHODS['sac_no_obstacles'].no_obstacles and METHODS['sac_rcbf_mb'].model_based
    config = transfer[0].run_config('runs')
    assert config.learner.seed == transfer[0].seed and config.episodes == 2
    by_system = {s.system: s.run_config('runs') for s in transfer}
    assert by_system['unicycle'].random_start is True  # the paper's starts
    assert by_system['pvtol'].random_start is None  # the config file decides
    assert not any(s.method == 'modular_envelope' for s in everything)  # only when named
    with pytest.raises(ValueError, match='experiment'):
        experiment_runs('bogus', budget, 1)
    with pytest.raises(ValueError, match='seeds'):
        experiment_runs('transfer', budget, 0)


def test_the_envelope_variant_runs_only_when_named_and_only_on_pvtol():
    budget = BUDGETS['smoke']
    request = ExperimentRequest(name='all', budget=budget, seeds=2, out='runs',
                                methods=('modular', 'modular_envelope'))
    specs = plan_runs(request)
    assert {(s.system, s.method) for s in specs} == {
        ('unicycle', 'modular'), ('pvtol', 'modular'), ('pvtol', 'modular_envelope')}
    configs = {(s.system, s.method): s.run_config('runs').learner for s in specs}
    assert configs['pvtol', 'modular_envelope'].uses_envelope
    assert configs['pvtol', 'modular_envelope'].mode == 'modular'
    assert not configs['pvtol', 'modular'].uses_envelope
    assert 'modular_envelope' in str(specs[-1].run_dir('root'))
    assert experiment_methods('transfer', 'unicycle', ('modular_envelope',)) == \
        PLAN['transfer']['unicycle']
    # A filter that leaves nothing to run is an error naming the field, not an empty report.
    with pytest.raises(ValueError, match='methods: .* select no run'):
        plan_runs(ExperimentRequest(name='transfer', budget=budget, seeds=1, out='runs',
                                    systems=('unicycle',), methods=('modular_envelope',)))


def test_overrides_rename_the_budget_so_runs_never_mix():
    budget = BUDGETS['paper'].with_overrides(episodes=12, max_steps=500, layouts=50)
    assert budget.name == 'paper-e12-s500'
    assert budget.episodes['unicycle'] == 12 and budget.max_steps['pvtol'] == 500
    assert budget.layouts == 50
    assert BUDGETS['paper'].with_overrides(layouts=10).name == 'paper'  # evaluation only
    spec = experiment_runs('transfer', budget, 1)[0]
    assert 'paper-e12-s500' in str(spec.run_dir('root'))
    with pytest.raises(ValueError, match='layouts'):
        BUDGETS['smoke'].with_overrides(layouts=0)


def test_the_input_box_is_a_budget_of_its_own_and_reaches_the_learner(tmp_path):
    from rcbf_ros.training.build import resolve_run
    box = BUDGETS['paper'].with_overrides(episodes=12, policy_box='inputs')
    assert box.name == 'paper-e12-box_inputs'
    assert BUDGETS['paper'].with_overrides(policy_box='config').name == 'paper'
    runs = {b.policy_box: experiment_runs('transfer', b, 1)[0]
            for b in (box, BUDGETS['paper'].with_overrides(episodes=12))}
    assert runs['inputs'].run_dir('r') != runs['config'].run_dir('r')
    # Through the trainer's resolution: the config file's forward-only box, or the inputs'.
    learners = {k: resolve_run(spec.run_config(tmp_path)).learner for k, spec in runs.items()}
    assert learners['config'].policy_min == (0.0, -2.5)
    assert learners['inputs'].policy_min == () and learners['inputs'].policy_max == ()
    with pytest.raises(ValueError, match='policy_box'):
        BUDGETS['paper'].with_overrides(policy_box='forward')


def test_without_ray_the_sequential_path_is_used(capsys, monkeypatch):
    from rcbf_ros.cli.main import main as cli_main
    find_spec = importlib.util.find_spec  # ray uninstalled, as far as the import system says
    monkeypatch.setattr(importlib.util, 'find_spec',
                        lambda name, *rest: None if name == 'ray' else find_spec(name, *rest))
    assert not ray_available()
    messages: list[str] = []
    assert select_backend(use_ray=False, address=None) == 'sequential'
    assert select_backend(use_ray=True, address=None, log=messages.append) == 'sequential'
    assert 'ray is not installed' in messages[0]
    with pytest.raises(RuntimeError, match='--address'):
        select_backend(use_ray=False, address='127.0.0.1:6379')
    assert cli_main(['experiment', 'transfer', '--address', '127.0.0.1:6379']) == 2
    assert '--address' in capsys.readouterr().err


def test_cluster_addresses_parse_in_rays_forms():
    assert parse_address('127.0.0.1:6379') == ('127.0.0.1', 6379)
    assert parse_address('ray://head.lan:10001') == ('head.lan', 10001)
    assert parse_address('[::1]:6379') == ('::1', 6379)
    assert parse_address('auto') is None and parse_address('local') is None
    for bad in ('127.0.0.1', 'head:', ':6379', 'head:port', 'head:0', 'head:70000'):
        with pytest.raises(ValueError, match='--address'):
            parse_address(bad)


def _closed_port() -> int:
    """A loopback port nobody listens on (just released by us)."""
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def test_an_address_where_nothing_answers_fails_fast_naming_the_flag(capsys, monkeypatch):
    """Ray retries an unreachable head forever; the CLI must stop with exit 2 instead."""
    with socket.socket() as server:  # something listening: accepted
        server.bind(('127.0.0.1', 0))
        server.listen()
        check_reachable(f'127.0.0.1:{server.getsockname()[1]}')
    port = _closed_port()
    with pytest.raises(RuntimeError, match='--address.*nothing answers'):
        check_reachable(f'127.0.0.1:{port}')
    # Through the CLI, as if ray were installed: the check comes before any Ray call.
    from rcbf_ros.cli.main import main as cli_main
    from rcbf_ros.experiments import command

    def no_ray(*_args, **_kwargs):
        raise AssertionError('reached Ray with an unreachable --address')
    monkeypatch.setattr(runner, 'ray_available', lambda: True)
    monkeypatch.setattr(runner, 'parallel_map', no_ray)
    monkeypatch.setattr(command, 'parallel_map', no_ray)
    assert cli_main(['experiment', 'transfer', '--budget', 'smoke',
                     '--address', f'127.0.0.1:{port}']) == 2
    assert 'nothing answers' in capsys.readouterr().err
    assert cli_main(['experiment', 'transfer', '--address', 'head']) == 2
    assert '--address' in capsys.readouterr().err


def test_cli_rejects_bad_experiment_arguments(capsys):
    from rcbf_ros.cli.main import main as cli_main
    assert cli_main(['experiment', 'transfer', '--seeds', '0']) == 2
    assert 'seeds' in capsys.readouterr().err
    assert cli_main(['experiment', 'transfer', '--layouts', '0']) == 2
    assert 'layouts' in capsys.readouterr().err


def _dist(a, b) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def test_the_200_transfer_layouts_follow_the_rules_and_reach_the_filter():
    """The evaluation's env with layout_seed s runs unicycle_random_layout(s) (rules hold for
    all 200 seeds) and hands exactly those barrier circles to the filter."""
    from rcbf_ros.envs import make_env
    from rcbf_ros.envs.layouts import (
        PVTOL_GOAL,
        pvtol_random_layout,
        PVTOL_STARTS,
        UNICYCLE_GOAL,
        unicycle_random_layout,
        UNICYCLE_STARTS,
    )
    from rcbf_ros.parameters.rules import find_config, load_params
    params = load_params(find_config('unicycle'), 'simulator')
    for seed in range(200):
        layout = unicycle_random_layout(seed)
        assert layout == unicycle_random_layout(seed) and len(layout) >= 1
        for a, b in itertools.combinations(layout, 2):
            assert _dist((a.x, a.y), (b.x, b.y)) > 2.1
        for o in layout:
            assert all(_dist((o.x, o.y), p) > 1.2 for p in (UNICYCLE_GOAL, *UNICYCLE_STARTS))
        env = make_env('unicycle', {**params, 'layout': 'random', 'layout_seed': seed})
        env.reset(seed=seed)
        assert env.obstacles == layout
        filt = env.filter_params()
        assert filt['obstacles.x'] == [o.x for o in layout]
        assert filt['obstacles.radius'] == [o.radius for o in layout]
        pv_layout, operator = pvtol_random_layout(seed)
        assert (pv_layout, operator) == pvtol_random_layout(seed)
        for a, b in itertools.combinations(pv_layout, 2):
            assert _dist((a.x, a.y), (b.x, b.y)) > 1.4
        for o in pv_layout:
            assert all(_dist((o.x, o.y), p) > 1.2 for p in (PVTOL_GOAL, *PVTOL_STARTS))
    assert len({unicycle_random_layout(s) for s in range(200)}) == 200


def test_methods_filter_keeps_only_those_runs_and_names_unknown_ones():
    from rcbf_ros.experiments.command import ExperimentRequest, plan_runs
    request = ExperimentRequest(name='transfer', budget=BUDGETS['smoke'], seeds=2, out='o',
                                first_seed=3, systems=('unicycle',), methods=('modular',))
    specs = plan_runs(request)
    assert [(s.system, s.method, s.seed) for s in specs] == [
        ('unicycle', 'modular', 3), ('unicycle', 'modular', 4)]
    with pytest.raises(ValueError, match="methods: unknown \\['modualr'\\]"):
        plan_runs(ExperimentRequest(name='transfer', budget=BUDGETS['smoke'], seeds=1,
                                    out='o', methods=('modualr',)))


def test_map_contrast_reads_the_paper_figure_on_constructed_maps():
    from rcbf_ros.experiments.value_map import map_contrast
    xs = ys = np.linspace(-3.0, 3.0, 61)
    gx, gy = np.meshgrid(xs, ys)
    task = -np.hypot(gx - 2.5, gy - 2.5)  # value rises toward the goal
    obstacles = [(0.0, 0.0, 0.6), (-1.5, 1.5, 0.6)]
    clearance = np.minimum(np.hypot(gx, gy) - 0.6, np.hypot(gx + 1.5, gy - 1.5) - 0.6)
    dips = task - 5.0 * np.exp(-np.clip(clearance, 0, None) / 0.3)  # low next to obstacles
    maps = {'sac_no_obstacles': (xs, ys, task), 'modular': (xs, ys, 3.0 * task + 1.0),
            'sac_rcbf': (xs, ys, dips)}
    out = map_contrast(maps, obstacles)
    # An affine copy has the reference's shape exactly: correlation 1, same ring value.
    assert out['modular']['corr_reference'] == pytest.approx(1.0, abs=1e-12)
    assert out['modular']['ring_z'] == pytest.approx(out['sac_no_obstacles']['ring_z'],
                                                     abs=1e-12)
    # Hand check of ring_z for the reference: standardise over the outside cells, average
    # over the cells whose edge clearance is in (0, 0.4].
    outside = clearance > 0
    z = (task - task[outside].mean()) / task[outside].std()
    assert out['sac_no_obstacles']['ring_z'] == pytest.approx(
        z[outside & (clearance <= 0.4)].mean(), abs=1e-12)
    # Dips near the obstacles: lower correlation, clearly negative ring value.
    assert out['sac_rcbf']['corr_reference'] < 0.95
    assert out['sac_rcbf']['ring_z'] < out['sac_no_obstacles']['ring_z'] - 0.5
    with pytest.raises(ValueError, match='ring'):
        map_contrast(maps, obstacles, ring=0.0)
    with pytest.raises(ValueError, match='maps'):
        map_contrast({**maps, 'x': (xs[:10], ys, task)}, obstacles)


def test_a_run_file_that_cannot_be_written_ends_the_experiment_in_one_line(capsys,
                                                                          monkeypatch):
    """A full disk under a run (a bag write, a checkpoint) is one line and exit 1, not a
    traceback; a Ctrl-C held by that write does not turn it into an exit 130."""
    import errno
    import os
    import signal

    from rcbf_ros.bag.writer import BagWriteError
    from rcbf_ros.cli.main import main as cli_main
    from rcbf_ros.experiments import command

    def full_disk(*_args, **_kwargs):
        from rcbf_ros.bag.interrupts import held
        with held:  # as the bag writer: a Ctrl-C lands in the write that then fails
            os.kill(os.getpid(), signal.SIGINT)
            raise BagWriteError(errno.ENOSPC, "cannot write '/x/bag_0.mcap' (ENOSPC: No "
                                              'space left on device): bag closed')
    monkeypatch.setattr(command, 'run_experiment', full_disk)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    assert cli_main(['experiment', 'transfer', '--budget', 'smoke', '--no-report']) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("error: cannot write '/x/bag_0.mcap' (ENOSPC") and 'resume' in line

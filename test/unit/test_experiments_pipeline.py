"""Every experiment at the smoke budget end to end through the CLI; the runner resumes.

The smoke pipeline takes ~45 s on two loaded cores (measured), so it stays in the unit suite
unmarked: the pipeline cannot rot unnoticed.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.envs import make_env
from rcbf_ros.envs.layouts import unicycle_random_layout
from rcbf_ros.experiments.definitions import Budget, BUDGETS, RunSpec
from rcbf_ros.experiments.evaluate import evaluate_transfer, load_trained_learner
from rcbf_ros.experiments.metrics import ENDINGS
from rcbf_ros.experiments.runner import run_all, run_status
from rcbf_ros.parameters.rules import find_config, load_params

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open() as stream:
        return list(csv.DictReader(stream))


def _mtimes(root: Path, pattern: str) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in sorted(root.rglob(pattern))}


def test_smoke_budget_of_every_experiment_writes_the_report(tmp_path, capsys):
    out = tmp_path / 'experiments'
    assert cli_main(['experiment', 'all', '--budget', 'smoke', '--seeds', '1',
                     '--out', str(out)]) == 0
    capsys.readouterr()
    report = out / 'smoke' / 'report'
    budget = BUDGETS['smoke']

    # Sample efficiency: one row per (method, episode); MB only on the Unicycle; no violations.
    rows = _csv(report / 'sample_efficiency_unicycle.csv')
    assert sorted({r['method'] for r in rows}) == [
        'baseline', 'baseline_compensator', 'sac_rcbf', 'sac_rcbf_mb']
    assert len(rows) == 4 * budget.episodes['unicycle']
    cars = _csv(report / 'sample_efficiency_car_following.csv')
    assert sorted({r['method'] for r in cars}) == ['baseline', 'baseline_compensator',
                                                   'sac_rcbf']
    assert all(int(r['violations']) == 0 for r in rows + cars)
    band = _csv(report / 'sample_efficiency_unicycle_band.csv')
    assert len(band) == 4 * budget.episodes['unicycle']
    for b in band:  # one seed: the band collapses onto the mean, which is that seed's return
        match = next(r for r in rows if r['method'] == b['method']
                     and r['episode'] == b['episode'])
        assert float(b['mean']) == pytest.approx(float(match['return']))
        assert float(b['lower_2std']) == pytest.approx(float(b['upper_2std']))

    # Transfer: four approaches per system, each on every layout; the summary is the episodes'.
    for system in ('unicycle', 'pvtol'):
        summary = {r['method']: r for r in _csv(report / f'transfer_{system}.csv')}
        assert list(summary) == ['sac_no_obstacles', 'baseline', 'sac_rcbf', 'modular']
        episodes = _csv(report / f'transfer_{system}_episodes.csv')
        assert len(episodes) == 4 * budget.layouts
        for method, row in summary.items():
            returns = [float(e['return']) for e in episodes if e['method'] == method]
            assert [int(e['layout_seed']) for e in episodes if e['method'] == method] == [0, 1, 2]
            assert float(row['mean_reward']) == pytest.approx(np.mean(returns))
            assert float(row['std_reward']) == pytest.approx(np.std(returns))
            assert int(row['violations']) == 0
            assert row['paper_completion']  # the paper's value sits next to ours
        # How each episode ended: 'goal' exactly when it reached the goal; the endings table
        # counts the episodes' endings.
        assert all((e['ending'] == 'goal') == (e['goal_reached'] == '1') for e in episodes)
        for row in _csv(report / f'transfer_{system}_endings.csv'):
            mine = [e['ending'] for e in episodes if e['method'] == row['method']]
            assert {k: int(row[k]) for k in ENDINGS} == {k: mine.count(k) for k in ENDINGS}
            assert int(row['episodes']) == len(mine) == budget.layouts
        training = _csv(report / f'transfer_training_{system}.csv')
        assert len(training) == 4 * budget.episodes[system]
        # The critic at each episode's first step vs the return: one row per episode, the
        # run's own metrics.
        critic = _csv(report / f'transfer_training_{system}_critic.csv')
        assert len(critic) == 4 * budget.episodes[system]
        run_dir = out / 'smoke' / system / 'modular' / 'seed0'
        logged = [json.loads(line)
                  for line in (run_dir / 'metrics.jsonl').read_text().splitlines()]
        assert [float(r['q_start']) for r in critic if r['method'] == 'modular'] == \
            pytest.approx([r['q_start'] for r in logged])
    # The evaluation ran each layout with ITS obstacles (the filter got the new barriers).
    cached = out / 'smoke' / 'unicycle' / 'modular' / 'seed0' / 'transfer_learned_L3_T40.jsonl'
    for line in cached.read_text().splitlines():
        row = json.loads(line)
        assert row['n_obstacles'] == len(unicycle_random_layout(row['layout_seed']))

    # Value maps: 3 methods x grid^2 points; V at one grid point equals the critic at the
    # env's own observation, maximised over the 8 headings.
    maps = _csv(report / 'value_maps_unicycle.csv')
    grid = budget.value_map_grid
    assert len(maps) == 3 * grid * grid
    learner = load_trained_learner(out / 'smoke' / 'unicycle' / 'modular' / 'seed0')[1]
    point = next(r for r in maps if r['method'] == 'modular'
                 and float(r['x']) == -2.25 and float(r['y']) == 0.75)
    env = make_env('unicycle', load_params(find_config('unicycle'), 'simulator'))
    env.reset(seed=0)
    values = []
    for theta in np.linspace(-np.pi, np.pi, 8, endpoint=False):
        env._state = np.array([-2.25, 0.75, theta])
        obs = torch.as_tensor(env._observation(), dtype=torch.float32)[None]
        action = learner.sac.policy_action(obs, deterministic=True)
        with torch.no_grad():
            values.append(float(torch.minimum(learner.sac.q1(obs, action),
                                              learner.sac.q2(obs, action))))
    assert float(point['value']) == pytest.approx(max(values), rel=1e-5, abs=1e-6)

    for name in ('sample_efficiency_unicycle', 'sample_efficiency_car_following',
                 'transfer_unicycle_completion', 'transfer_pvtol_completion',
                 'transfer_unicycle_endings',
                 'transfer_training_pvtol_critic',
                 'value_maps_unicycle'):
        data = (report / f'{name}.png').read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5000, name
    text = (report / 'report.md').read_text()
    for needle in ('## Sample efficiency', '## Zero-shot transfer', '## Value maps',
                   '| Mod. SAC-RCBF | 6.189 | 2.317 | 0.63 |', 'SAC-RCBF (MB)',
                   '## Training curves of the transfer runs',
                   'rcbf_ros experiment all --budget smoke'):
        assert needle in text, needle

    # Every run is recorded to MCAP as `rcbf_ros train` records it.
    from rosbags.highlevel import AnyReader
    run_dir = out / 'smoke' / 'pvtol' / 'sac_rcbf' / 'seed0'
    history = [json.loads(line) for line in (run_dir / 'metrics.jsonl').read_text().splitlines()]
    with AnyReader([next(run_dir.glob('bag_*'))]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts['/cmd_safe'] == sum(r['steps'] for r in history)

    # Second call: nothing is retrained or re-evaluated.
    before = {**_mtimes(out, 'metrics.jsonl'), **_mtimes(out, 'transfer_*.jsonl')}
    assert cli_main(['experiment', 'all', '--budget', 'smoke', '--seeds', '1',
                     '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    assert '13 runs, 13 already complete, 0 to train' in printed
    assert {**_mtimes(out, 'metrics.jsonl'), **_mtimes(out, 'transfer_*.jsonl')} == before


def test_runner_skips_finished_runs_and_resumes_partial_ones(tmp_path):
    def budget(episodes: int) -> Budget:
        return Budget(name='tiny', episodes={'unicycle': episodes},
                      max_steps={'unicycle': 30}, start_steps=10, update_after=10,
                      batch_size=8, gp_refit_interval=20, hidden_sizes=(8, 8),
                      record_bag=False)
    one = RunSpec('unicycle', 'modular', 0, budget(1))
    assert run_status(one, tmp_path) == 'missing'
    assert [r['status'] for r in run_all([one], tmp_path, log=lambda _: None)] == ['ran']
    assert run_status(one, tmp_path) == 'complete'
    metrics = one.run_dir(tmp_path) / 'metrics.jsonl'
    stamp = metrics.stat().st_mtime_ns
    assert [r['status'] for r in run_all([one], tmp_path, log=lambda _: None)] == ['skipped']
    assert metrics.stat().st_mtime_ns == stamp
    # The same run planned for two episodes: resumed from its checkpoint, not restarted.
    two = RunSpec('unicycle', 'modular', 0, budget(2))
    assert run_status(two, tmp_path) == 'partial'
    result = run_all([two], tmp_path, log=lambda _: None)[0]
    assert result['status'] == 'resumed' and result['episodes'] == 2
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert [r['episode'] for r in rows] == [0, 1]
    summary = json.loads((one.run_dir(tmp_path) / 'summary.json').read_text())
    assert summary['episodes'] == 2 and summary['safety_violations'] == 0
    # Its transfer evaluation: each layout's row is on disk when its episode ends, so a cut-short
    # evaluation (a torn last line included) resumes after its last finished layout and gives
    # the rows an uninterrupted one gives; a complete file is read back, not recomputed.
    seeds = [0, 1, 2]
    lines: list[str] = []
    full = evaluate_transfer(one.run_dir(tmp_path), seeds, max_steps=15, log=lines.append,
                             progress_every=1)
    cache = one.run_dir(tmp_path) / 'transfer_learned_L3_T15.jsonl'
    assert len(lines) == 3 and lines[-1].startswith('unicycle/modular/seed0: transfer 3/3 layouts')
    text = cache.read_text().splitlines()
    cache.write_text(text[0] + '\n' + text[1][:25])
    lines.clear()
    resumed = evaluate_transfer(one.run_dir(tmp_path), seeds, max_steps=15, log=lines.append,
                                progress_every=1)
    assert lines[0] == 'unicycle/modular/seed0: transfer resumes after 1/3 layouts'
    drop = {'eval_wall_s'}
    assert [{k: v for k, v in r.items() if k not in drop} for r in resumed] == \
        [{k: v for k, v in r.items() if k not in drop} for r in full]
    assert [json.loads(line) for line in cache.read_text().splitlines()] == resumed
    stamp = cache.stat().st_mtime_ns
    lines.clear()
    assert evaluate_transfer(one.run_dir(tmp_path), seeds, max_steps=15, log=lines.append) == \
        resumed
    assert lines == [] and cache.stat().st_mtime_ns == stamp
    # Another layout count of the same run lends its rows: 3 -> 4 computes only layout 3, and
    # 4 -> 2 computes nothing.
    lines.clear()
    four = evaluate_transfer(one.run_dir(tmp_path), [0, 1, 2, 3], max_steps=15,
                             log=lines.append, progress_every=1)
    assert lines[:2] == ['unicycle/modular/seed0: transfer reuses 3 layouts of '
                         'transfer_learned_L3_T15.jsonl',
                         'unicycle/modular/seed0: transfer resumes after 3/4 layouts']
    assert four[:3] == resumed and four[3]['layout_seed'] == 3 and len(lines) == 3
    lines.clear()
    assert evaluate_transfer(one.run_dir(tmp_path), [0, 1], max_steps=15,
                             log=lines.append) == four[:2]
    assert lines == ['unicycle/modular/seed0: transfer reuses 2 layouts of '
                     'transfer_learned_L3_T15.jsonl']
    assert (one.run_dir(tmp_path) / 'transfer_learned_L2_T15.jsonl').exists()


def test_rows_recorded_without_their_ending_get_it_by_a_checked_re_run(tmp_path):
    budget = Budget(name='tiny', episodes={'unicycle': 1}, max_steps={'unicycle': 30},
                    start_steps=10, update_after=10, batch_size=8, gp_refit_interval=20,
                    hidden_sizes=(8, 8), record_bag=False)
    run = RunSpec('unicycle', 'modular', 0, budget)
    run_all([run], tmp_path, log=lambda _: None)
    run_dir = run.run_dir(tmp_path)
    seeds = [0, 1, 2]
    rows = evaluate_transfer(run_dir, seeds, max_steps=15)
    assert [r['ending'] for r in rows] == ['moving'] * 3  # 15 steps: none arrives, none stops
    cache = run_dir / 'transfer_learned_L3_T15.jsonl'
    added = ('goal_dist', 'tail_moved', 'tail_active', 'ending')
    old = [{k: v for k, v in r.items() if k not in added} for r in rows]
    old[1].update(goal_reached=True)  # a goal row needs no re-run: its ending is 'goal'
    cache.write_text(''.join(json.dumps(r) + '\n' for r in old))
    lines: list[str] = []
    again = evaluate_transfer(run_dir, seeds, max_steps=15, log=lines.append, progress_every=1)
    assert lines == ['unicycle/modular/seed0: 3 layouts were recorded without their ending; '
                     're-running the 2 that missed the goal',
                     'unicycle/modular/seed0: endings 1/2 re-run',
                     'unicycle/modular/seed0: endings 2/2 re-run']
    assert [again[0], again[2]] == [rows[0], rows[2]]  # eval_wall_s too: the recorded one
    assert again[1] == {**old[1], 'ending': 'goal'}
    assert [json.loads(line) for line in cache.read_text().splitlines()] == again
    # An old file cut short: its rows get their endings, then the evaluation goes on.
    cache.write_text(''.join(json.dumps(r) + '\n' for r in old[:2]))
    resumed = evaluate_transfer(run_dir, seeds, max_steps=15)
    assert resumed[:2] == again[:2]
    assert {**resumed[2], 'eval_wall_s': 0} == {**rows[2], 'eval_wall_s': 0}
    # A re-run that does not reproduce the recorded row is refused, naming layout and field.
    old[2]['ret'] += 1e-6
    cache.write_text(''.join(json.dumps(r) + '\n' for r in old))
    with pytest.raises(RuntimeError, match=r'layout 2 re-run .* gave ret -?[0-9.]+ \(recorded'):
        evaluate_transfer(run_dir, seeds, max_steps=15)


def test_policy_box_flag_lets_the_trained_policy_reverse(tmp_path, capsys):
    # The Unicycle config's box is forward-only; --policy-box inputs trains with the input
    # limits, in its own directory, and the restored policy then proposes v < 0 too.
    out = tmp_path / 'experiments'
    proposals = {}
    for flag in ([], ['--policy-box', 'inputs']):
        assert cli_main(['experiment', 'transfer', '--budget', 'smoke', '--seeds', '1',
                         '--systems', 'unicycle', '--methods', 'modular', '--no-report',
                         '--no-bag', '--out', str(out), *flag]) == 0
        name = 'smoke-box_inputs' if flag else 'smoke'
        _, learner = load_trained_learner(out / name / 'unicycle' / 'modular' / 'seed0')
        obs = np.random.default_rng(0).normal(size=(200, 7))
        proposals[name] = np.array([learner.sac.act(o, deterministic=False) for o in obs])
    capsys.readouterr()
    assert proposals['smoke'][:, 0].min() >= 0.0
    assert proposals['smoke-box_inputs'][:, 0].min() < -0.1
    assert np.abs(proposals['smoke-box_inputs']).max() <= 2.5

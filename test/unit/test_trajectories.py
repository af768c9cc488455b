"""The trajectory picture of a run: from a bag (run summary) and from the in-process trainer.

The closest approach the picture labels is checked against an independent computation from
the recorded states (read back with rosbags, not with our reader).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import re

import numpy as np
import pytest

from rcbf_ros.bag import BagWriter
from rcbf_ros.core.scene import scene_geometry
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.reports.plots import closest_approach, EpisodePath, plot_trajectories
from rcbf_ros.reports.run_summary import episode_paths, trajectory_line

ARRAY = 'std_msgs/msg/Float64MultiArray'
MIN_PNG_BYTES = 20_000
"""A drawn picture (axes, obstacles, paths, legend) is well above this; an empty figure is not."""


def _array(**sections) -> dict:
    dims = [{'label': k, 'size': int(np.size(v)), 'stride': int(np.size(v))}
            for k, v in sections.items()]
    data = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1)
                           for v in sections.values()])
    return {'layout': {'dim': dims, 'data_offset': 0}, 'data': data}


def _unicycle_obstacles() -> list[tuple[float, float, float]]:
    params = load_params(find_config('unicycle'), 'simulator')
    return list(zip(params['obstacles.x'], params['obstacles.y'], params['obstacles.radius']))


def _independent_closest(states: np.ndarray) -> tuple[float, int]:
    """(min over states and obstacles of |p - c| - r, that obstacle's index), plain numpy."""
    best, index = math.inf, -1
    for i, (x, y, r) in enumerate(_unicycle_obstacles()):
        value = float(np.min(np.sqrt((states[:, 0] - x) ** 2 + (states[:, 1] - y) ** 2) - r))
        if value < best:
            best, index = value, i
    return best, index


def _episodes(seed: int = 0) -> list[np.ndarray]:
    """Two hand-made Unicycle episodes: a pass close by obstacle 4 and one toward the centre."""
    rng = np.random.default_rng(seed)
    first = np.stack([np.linspace(-2.5, 2.3, 40), np.linspace(-2.5, 0.4, 40),
                      np.full(40, 0.6)], axis=1)
    second = np.stack([np.linspace(-2.5, -0.9, 25), np.linspace(-2.5, -0.3, 25),
                       rng.uniform(-1, 1, 25)], axis=1)
    return [first, second]


def _write_node_bag(bag: Path, episodes: list[np.ndarray], corrected: list[set[int]],
                    form: str = 'filter_info') -> None:
    """A bag as the node launches record it: /sim/step, the filter's answers (with the answered
    state), /episode events; every state of step k is published twice (lock-step watchdog).

    ``form`` 'filter_info': /cmd_safe holds the command alone, /filter_info the correction;
    'earlier': /cmd_safe with sections u, u_rl, u_s and state, as bags were recorded before the
    filter published filter_info."""
    writer = BagWriter(bag)
    for topic, type_name in (('/sim/step', ARRAY), ('/state', ARRAY), ('/cmd_safe', ARRAY),
                             ('/filter_info', ARRAY), ('/episode', 'std_msgs/msg/String')):
        if topic != '/filter_info' or form == 'filter_info':
            writer.add_topic(topic, type_name)
    t = 1_000
    for number, states in enumerate(episodes, 1):
        writer.write_message('/episode', {'data': json.dumps(
            {'event': 'start', 'episode': number, 'system': 'unicycle', 'layout_seed': None})}, t)
        for k, state in enumerate(states):
            for _ in range(2 if k == 3 else 1):
                t += 10
                writer.write_message('/sim/step', _array(state=state, episode=[number],
                                                         step=[k]), t)
            if k + 1 == len(states):
                break
            u_s = [0.0, 0.3] if k in corrected[number - 1] else [0.0, 0.0]
            t += 10
            if form == 'earlier':
                writer.write_message('/cmd_safe', _array(u=[1.0, 0.3], u_rl=[1.0, 0.0],
                                                         u_s=u_s, state=state), t)
                continue
            writer.write_message('/cmd_safe', _array(u=[1.0, 0.3]), t)
            writer.write_message('/filter_info', _array(
                u=[1.0, 0.3], u_rl=[1.0, 0.0], u_s=u_s, fail_safe=[0.0], status=[0.0],
                state=state), t)
        t += 10
        writer.write_message('/episode', {'data': json.dumps({'event': 'end', 'episode': number})},
                             t)
    # the run ends right after the simulator reset into a third episode
    t += 10
    writer.write_message('/sim/step', _array(state=episodes[0][0], episode=[3], step=[0]), t)
    writer.close()


def _rosbags_states(bag: Path, topic: str) -> np.ndarray:
    from rosbags.highlevel import AnyReader
    rows = []
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            offset = 0
            for dim in msg.layout.dim:
                if dim.label == 'state':
                    rows.append(np.array(msg.data[offset:offset + dim.size]))
                offset += dim.size
    return np.array(rows)


@pytest.mark.parametrize('form', ['filter_info', 'earlier'])
def test_run_summary_draws_the_bag_and_labels_the_closest_approach(tmp_path, form):
    episodes = _episodes()
    corrected = [{5, 6, 30}, {0, 24 - 1}]
    bag = tmp_path / 'run' / 'bag'
    _write_node_bag(bag, episodes, corrected, form)
    paths = episode_paths(bag, n_x=3)
    assert [p.episode for p in paths] == [1, 2]  # the stepless third one is left out
    for path, states, marks in zip(paths, episodes, corrected):
        np.testing.assert_array_equal(path.states, states)  # the repeated state kept once
        assert set(np.flatnonzero(path.corrected)) == marks

    png = tmp_path / 'run' / 'trajectories.png'
    line = trajectory_line(bag, png)
    assert png.is_file() and png.stat().st_size > MIN_PNG_BYTES, line
    recorded = _rosbags_states(bag, '/sim/step')
    expected, index = _independent_closest(recorded)
    episode = 1 + int(_independent_closest(recorded[:len(episodes[0]) + 1])[0] > expected)
    reported = float(re.search(r'closest approach (-?[0-9.]+) m', line).group(1))
    assert reported == pytest.approx(expected, abs=5e-4)  # printed to 3 decimals
    assert f'obstacle_{index} (episode {episode},' in line


@pytest.mark.parametrize('empty_sim_step', [False, True])
def test_run_summary_without_sim_step_splits_state_at_episode_events(tmp_path, empty_sim_step):
    """An in-process bag: /state and /cmd_safe (no state section), end events only; a
    /sim/step topic without messages (a recorder subscribed, nobody published) is none."""
    episodes = _episodes()
    bag = tmp_path / 'bag'
    writer = BagWriter(bag)
    for topic, type_name in (('/state', ARRAY), ('/cmd_safe', ARRAY),
                             ('/episode', 'std_msgs/msg/String')):
        writer.add_topic(topic, type_name)
    if empty_sim_step:
        writer.add_topic('/sim/step', ARRAY)
    t = 0
    for number, states in enumerate(episodes):
        for k, state in enumerate(states):
            t += 10
            writer.write_message('/state', _array(state=state), t)
            writer.write_message('/cmd_safe', _array(
                u=[1.0, 0.0], u_rl=[1.0, 0.0], u_s=[1e-3 if k == 2 else 1e-8, 0.0]), t)
        writer.write_message('/episode', {'data': json.dumps({'event': 'end',
                                                              'episode': number})}, t)
    writer.close()
    paths = episode_paths(bag, n_x=3)
    assert [p.episode for p in paths] == [1, 2]
    for path, states in zip(paths, episodes):
        np.testing.assert_array_equal(path.states, states)
        assert list(np.flatnonzero(path.corrected)) == [2]  # 1e-8 is below the threshold
    line = trajectory_line(bag, tmp_path / 'trajectories.png', params_file='unicycle')
    assert line.startswith('trajectories: ') and 'closest approach' in line


def test_random_layouts_and_unknown_systems_are_said_not_drawn(tmp_path):
    bag = tmp_path / 'bag'
    writer = BagWriter(bag)
    writer.add_topic('/episode', 'std_msgs/msg/String')
    writer.add_topic('/state', ARRAY)
    writer.write_message('/episode', {'data': json.dumps(
        {'event': 'start', 'episode': 1, 'system': 'unicycle', 'layout_seed': 7})}, 1)
    writer.close()
    assert trajectory_line(bag, tmp_path / 't.png') == \
        'trajectories: not drawn: the episodes ran on random layouts'
    assert not (tmp_path / 't.png').exists()
    empty = tmp_path / 'empty'
    writer = BagWriter(empty)
    writer.add_topic('/state', ARRAY)
    writer.close()
    assert 'no /episode start event names the system' in trajectory_line(empty, tmp_path / 'e')
    assert 'no state of 3 values' in trajectory_line(empty, tmp_path / 'e',
                                                    params_file='unicycle')


def test_in_process_run_writes_its_picture(tmp_path):
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import RunConfig
    from rcbf_ros.training.loop import train
    lines: list[str] = []
    out = tmp_path / 'run'
    history = train(RunConfig(system='unicycle', episodes=2, max_steps=60, out_dir=str(out),
                              learner=LearnerConfig(mode='modular', seed=3)),
                    log=lines.append)
    png = out / 'trajectories.png'
    assert png.is_file() and png.stat().st_size > MIN_PNG_BYTES, lines
    (line,) = [entry for entry in lines if entry.startswith('trajectories:')]
    reported = float(re.search(r'closest approach (-?[0-9.]+) m', line).group(1))
    # The bag holds each step's state before the step; the env's own true clearance after
    # each step (min_h_true) covers the last state.
    recorded = _rosbags_states(out / 'bag_0000', '/state')
    assert len(recorded) == 120
    expected = min(_independent_closest(recorded)[0], *(row['min_h_true'] for row in history))
    assert reported == pytest.approx(expected, abs=5e-4)
    # As the nodes publish them: the command alone on /cmd_safe, the details on /filter_info.
    from rosbags.highlevel import AnyReader
    with AnyReader([out / 'bag_0000']) as reader:
        by_topic = {}
        for connection, _, raw in reader.messages(connections=[
                c for c in reader.connections if c.topic in ('/cmd_safe', '/filter_info')]):
            msg = reader.deserialize(raw, connection.msgtype)
            by_topic.setdefault(connection.topic, []).append(msg)
    assert len(by_topic['/cmd_safe']) == len(by_topic['/filter_info']) == 120
    for command, info in zip(by_topic['/cmd_safe'], by_topic['/filter_info']):
        assert [d.label for d in command.layout.dim] == ['u'] and len(command.data) == 2
        labels = [d.label for d in info.layout.dim]
        assert labels[:5] == ['u', 'u_rl', 'u_s', 'fail_safe', 'status'] and labels[-1] == 'state'
        np.testing.assert_array_equal(info.data[:2], command.data)
        assert np.all(np.isfinite(info.data))


def test_pvtol_and_car_following_pictures(tmp_path):
    pvtol = scene_geometry(load_params(find_config('pvtol'), 'safety_filter'))
    states = np.zeros((50, 7))
    states[:, 0], states[:, 1] = np.linspace(-4.5, -1.2, 50), np.linspace(2.0, 0.9, 50)
    corrected = np.zeros(50, dtype=bool)
    corrected[20:25] = True
    picture = plot_trajectories([EpisodePath(1, states, corrected)], pvtol,
                                tmp_path / 'pvtol.png', goal=(5.0, -1.5))
    assert picture.path.stat().st_size > MIN_PNG_BYTES
    centres = [(d.x, d.y, d.radius) for d in pvtol.obstacles]
    expected = min(float(np.min(np.hypot(states[:, 0] - x, states[:, 1] - y) - r))
                   for x, y, r in centres)
    assert picture.closest.distance == pytest.approx(expected, rel=1e-12)

    cars = scene_geometry(load_params(find_config('car_following'), 'safety_filter'))
    t = np.linspace(0.0, 2.0, 101)
    paths = []
    for episode, squeeze in ((1, 1.0), (2, 1.6)):
        state = np.zeros((t.size, 10))
        state[:, 0::2] = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + 30.0 * t[:, None]
        state[:, 6] += squeeze * np.sin(np.pi * t / 2.0)  # car 4 closes on car 3
        paths.append(EpisodePath(episode, state, np.zeros(t.size, dtype=bool)))
    picture = plot_trajectories(paths, cars, tmp_path / 'cars.png', dt=0.02, true_gap=3.5)
    assert picture.path.stat().st_size > MIN_PNG_BYTES
    assert (picture.closest.barrier, picture.closest.episode) == ('gap_4_6', 2)
    assert picture.closest.distance == pytest.approx(6.0 - 1.6, abs=1e-9)
    assert picture.closest.step == 50


def test_closest_approach_to_shaped_obstacles_uses_their_true_boundary():
    from rcbf_ros.envs.layouts import Obstacle
    geometry = scene_geometry(load_params(find_config('unicycle'), 'safety_filter'))
    square = Obstacle(0.0, 0.0, math.sqrt(2.0), 'square')  # half-size 1
    path = EpisodePath(1, np.array([[1.5, 0.0, 0.0], [1.2, 0.5, 0.0]]), np.zeros(2, bool))
    closest = closest_approach([path], geometry, obstacles=[square])
    # 0.2 from the square's face, though inside its circumscribed (barrier) circle
    assert closest.distance == pytest.approx(0.2) and closest.step == 1


def test_mismatched_paths_are_refused():
    geometry = scene_geometry(load_params(find_config('unicycle'), 'safety_filter'))
    with pytest.raises(ValueError, match='do not match'):
        EpisodePath(1, np.zeros((3, 3)), np.zeros(2, bool))
    with pytest.raises(ValueError, match='no episode'):
        plot_trajectories([], geometry, 'x.png')
    with pytest.raises(ValueError, match='states of 2 values, the filter 3'):
        plot_trajectories([EpisodePath(1, np.zeros((3, 2)), np.zeros(3, bool))], geometry,
                          'x.png')


def test_experiment_report_draws_every_method_on_the_first_transfer_layouts(tmp_path):
    from rcbf_ros.envs import make_env
    from rcbf_ros.experiments.definitions import Budget, METHODS, RunSpec
    from rcbf_ros.experiments.evaluate import evaluate_transfer
    from rcbf_ros.experiments.report import transfer_paths_report
    from rcbf_ros.experiments.runner import run_all
    budget = Budget(name='tiny', episodes={'unicycle': 1}, max_steps={'unicycle': 30},
                    start_steps=10, update_after=10, batch_size=8, gp_refit_interval=20,
                    hidden_sizes=(8, 8), record_bag=False)
    specs = [RunSpec('unicycle', method, 0, budget) for method in ('baseline', 'modular')]
    run_all(specs, tmp_path, log=lambda _: None)
    rows = {spec.method: evaluate_transfer(spec.run_dir(tmp_path), [0, 1], max_steps=25)
            for spec in specs}
    report = tmp_path / 'report'
    report.mkdir()
    text = transfer_paths_report(specs, tmp_path, report, layouts=2,
                                 eval_max_steps={'unicycle': 25})
    for seed in (0, 1):
        png = report / f'transfer_unicycle_paths_layout{seed}.png'
        assert png.stat().st_size > MIN_PNG_BYTES
        assert f'![unicycle layout {seed}]({png.name})' in text
        # independent: the evaluation's own true clearances after each step, and the start's
        params = load_params(find_config('unicycle'), 'simulator')
        env = make_env('unicycle', {**params, 'layout': 'random', 'layout_seed': seed})
        _, info = env.reset(seed=seed)
        closest = min(float(np.min(info['h_true'])),
                      *(rows[method][seed]['min_h_true'] for method in rows))
        line = next(entry for entry in text.splitlines()
                    if entry.startswith(f'Closest approach on layout {seed}:'))
        assert float(line.split(': ')[1].split(' m')[0]) == pytest.approx(closest, abs=5e-4)
        assert any(METHODS[m].label in line for m in rows)
    assert (report / 'transfer_paths.md').read_text() == text


def test_summary_of_a_run_directory_ends_with_its_picture(tmp_path, capsys):
    from rcbf_ros.reports.run_summary import main
    run = tmp_path / 'run'
    (run / 'learner').mkdir(parents=True)
    (run / 'learner' / 'summary.json').write_text(json.dumps(
        {'episodes': 2, 'env_steps': 63, 'steps_per_s': 50.0, 'best_return': 0.5,
         'goals_reached': 0, 'safety_violations': 0}))
    _write_node_bag(run / 'bag', _episodes(), [set(), set()])
    assert main([str(run)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1].startswith(f'trajectories: {run / "trajectories.png"}; closest approach ')
    assert main([str(run), '--params-file', str(find_config('unicycle'))]) == 0
    assert main([str(run), '--params']) == 2
    assert 'usage: rcbf_ros summary' in capsys.readouterr().err

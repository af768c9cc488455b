"""``rcbf_ros train`` and the learner node resume each other's runs, and both stop in one line,
their previous checkpoint intact, when the disk is full at a checkpoint.

The node runs its own ``main()`` in a process of its own with the simulator played inside that
process (``learner_feed.py``); a full disk is a file-size limit (RLIMIT_FSIZE, SIGXFSZ
ignored) under which the bag, metrics and policy fit and a checkpoint does not.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.envs import make_env
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.checkpoint import env_seed, learner_identity, read_checkpoint
from rcbf_ros.training.run_files import load_payload

FEED = Path(__file__).with_name('learner_feed.py')
STEPS = 40
TRAIN = ['train', '--system', 'unicycle', '--mode', 'baseline', '--max-steps', str(STEPS),
         '--start-steps', '20', '--update-after', '20', '--batch-size', '16']
NODE = ['-p', 'mode:=baseline', '-p', 'start_steps:=20', '-p', 'update_after:=20',
        '-p', 'batch_size:=16']
LIMIT = 1_000_000
"""Bytes: more than a bag, metrics file or policy of these runs, less than a checkpoint
(about 3 MB with the default networks)."""


def run_node(out: Path, domain: int, *args: str, fsize: int | None = None
             ) -> subprocess.CompletedProcess:
    """The learner node's main() on ``out`` (``args``: more -p), to its end."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), OMP_NUM_THREADS='1')
    limit = [] if fsize is None else ['--fsize', str(fsize)]
    return subprocess.run([sys.executable, str(FEED), *limit, '--max-steps', str(STEPS), '--',
                           *NODE, '-p', f'out_dir:={out}', *args],
                          capture_output=True, text=True, timeout=180, env=env)


def run_cli(*args: str, fsize: int | None = None) -> subprocess.CompletedProcess:
    """``rcbf_ros <args>`` in a process of its own, under a file-size limit if given."""
    code = ('import resource, runpy, signal, sys\n'
            f'limit = {fsize!r}\n'
            'if limit is not None:\n'
            '    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n'
            '    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))\n'
            'sys.argv = ["rcbf_ros", *sys.argv[1:]]\n'
            'runpy.run_module("rcbf_ros", run_name="__main__")\n')
    return subprocess.run([sys.executable, '-c', code, *args], capture_output=True, text=True,
                          timeout=180, env=dict(os.environ, OMP_NUM_THREADS='1'))


def rows_of(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def error_lines(stderr: str) -> list[str]:
    """stderr without the node's log lines ([INFO] ...)."""
    return [line for line in stderr.splitlines() if not line.startswith('[')]


def test_the_learner_node_resumes_a_run_of_rcbf_ros_train(tmp_path, ros_domain_id):
    """The node continues the trainer's run at its episode with its learner (buffer, step
    count); the env generator is the simulator's, so the node's checkpoint holds none."""
    out = tmp_path / 'run'
    assert cli_main([*TRAIN, '--episodes', '1', '--out', str(out)]) == 0
    bag = (out / 'bag_0000' / 'bag_0000_0.mcap').read_bytes()
    done = run_node(out, ros_domain_id, '-p', 'episodes:=2', '-p', 'resume:=true')
    assert done.returncode == 0, done.stderr[-3000:]
    assert 'resumed at episode 1 of a run of rcbf_ros train' in done.stderr
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0, 1]
    checkpoint = load_payload(out / 'checkpoint.pt')
    assert checkpoint['episode'] == 2 and checkpoint['made_by'] == 'learner node'
    assert checkpoint['env_rng'] is None
    assert checkpoint['learner']['buffer']['size'] == checkpoint['learner']['env_steps'] == \
        2 * STEPS
    assert (out / 'bag_0000' / 'bag_0000_0.mcap').read_bytes() == bag


def test_rcbf_ros_train_resumes_a_run_of_the_learner_node(tmp_path, ros_domain_id):
    """The trainer continues the node's run; the node's checkpoint holds no env generator, so
    the env's next episode is seeded from (seed, episode): with random starts, the first
    resumed transition starts where that seed puts it."""
    out = tmp_path / 'run'
    done = run_node(out, ros_domain_id, '-p', 'episodes:=1')
    assert done.returncode == 0, done.stderr[-3000:]
    assert load_payload(out / 'checkpoint.pt')['env_rng'] is None
    assert cli_main([*TRAIN, '--random-start', '--episodes', '2', '--out', str(out),
                     '--resume']) == 0
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0, 1]
    checkpoint = load_payload(out / 'checkpoint.pt')
    assert checkpoint['episode'] == 2 and checkpoint['made_by'] == 'rcbf_ros train'
    assert checkpoint['env_rng'] is not None
    states = checkpoint['learner']['buffer']['data']['state']
    assert len(states) == 2 * STEPS
    params = {**load_params(find_config('unicycle'), 'simulator'), 'random_start': True}
    _, info = make_env('unicycle', params).reset(seed=env_seed(0, 1))
    np.testing.assert_allclose(states[STEPS].numpy(), info['state'], rtol=1e-6)  # float32


def test_the_learner_node_refuses_a_run_of_another_network_in_one_line(tmp_path,
                                                                       ros_domain_id):
    """A trainer's run with a network the node does not have: exit 2 before anything is
    loaded or written, one line naming the difference."""
    from rcbf_ros.learning.sac import SACConfig
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import RunConfig
    from rcbf_ros.training.loop import train
    out = tmp_path / 'run'
    train(RunConfig(system='unicycle', episodes=1, max_steps=20, out_dir=str(out),
                    record_bag=False,
                    learner=LearnerConfig(mode='baseline', start_steps=10, update_after=10,
                                          batch_size=8, sac=SACConfig(hidden_sizes=(8, 8)))),
          log=lambda _: None)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    done = run_node(out, ros_domain_id, '-p', 'episodes:=2', '-p', 'resume:=true')
    assert done.returncode == 2, done.stderr[-3000:]
    assert error_lines(done.stderr) == [
        f"learner: invalid parameters: resume: {out / 'checkpoint.pt'} was made with "
        'hidden_sizes [8, 8]; this run has hidden_sizes [256, 256]']
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def _check_kept(out: Path, episodes: int, checkpoint: bytes) -> None:
    """The checkpoint on disk is the one of ``episodes`` episodes, byte for byte, and still
    resumes; no partial file is left anywhere."""
    assert (out / 'checkpoint.pt').read_bytes() == checkpoint
    env = make_env('unicycle', load_params(find_config('unicycle'), 'simulator'))
    kept = read_checkpoint(out / 'checkpoint.pt', identity=learner_identity(
        system_name='unicycle', system=env.nominal_system, config=_resolved_config(),
        obs_dim=None))
    assert kept.episode == episodes
    assert not list(out.rglob('*.partial'))


def _resolved_config():
    """The learner configuration both entry points resolve for these runs."""
    from rcbf_ros.training.agent import LearnerConfig
    return LearnerConfig(mode='baseline', policy_min=(0.0, -2.5), policy_max=(2.5, 2.5),
                         modular_envelope=False)


def test_a_full_disk_at_a_checkpoint_of_rcbf_ros_train_is_one_line_and_keeps_the_last(
        tmp_path):
    out = tmp_path / 'run'
    assert run_cli(*TRAIN, '--episodes', '1', '--out', str(out)).returncode == 0
    checkpoint = (out / 'checkpoint.pt').read_bytes()
    done = run_cli(*TRAIN, '--episodes', '3', '--out', str(out), '--resume', fsize=LIMIT)
    assert done.returncode == 1, done.stderr[-3000:]
    assert done.stderr == (f"error: {out / 'checkpoint.pt'}: File too large; the run stopped "
                           '(checkpoint.pt holds 1 episode(s); --resume continues from it)\n')
    _check_kept(out, 1, checkpoint)
    # The bag of this start was closed: it reads back, with the episode played.
    from rosbags.highlevel import AnyReader
    with AnyReader([out / 'bag_0001']) as reader:
        assert sum(c.msgcount for c in reader.connections if c.topic == '/cmd_safe') == STEPS
    # And the run goes on from the kept checkpoint once there is room.
    assert cli_main([*TRAIN, '--episodes', '2', '--no-bag', '--out', str(out),
                     '--resume']) == 0
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0, 1]


def test_a_full_disk_at_a_checkpoint_of_the_learner_node_is_one_line_and_keeps_the_last(
        tmp_path, ros_domain_id):
    out = tmp_path / 'run'
    assert run_node(out, ros_domain_id, '-p', 'episodes:=1').returncode == 0
    checkpoint = (out / 'checkpoint.pt').read_bytes()
    summary = (out / 'summary.json').read_bytes()
    done = run_node(out, ros_domain_id, '-p', 'episodes:=3', '-p', 'resume:=true',
                    fsize=LIMIT)
    assert done.returncode == 1, done.stderr[-3000:]
    assert 'Traceback' not in done.stderr
    assert error_lines(done.stderr) == [
        f"learner: {out / 'checkpoint.pt'}: File too large; the run stopped (checkpoint.pt "
        'holds 1 episode(s); resume:=true continues from it)']
    _check_kept(out, 1, checkpoint)
    # Nothing more was written after the failure: the summary is the first start's.
    assert (out / 'summary.json').read_bytes() == summary


@pytest.mark.parametrize('entry', ['train', 'node'])
def test_a_first_checkpoint_that_does_not_fit_leaves_no_file(tmp_path, ros_domain_id, entry):
    """No checkpoint yet and the first does not fit: one line saying so, nothing partial."""
    out = tmp_path / 'run'
    if entry == 'train':
        done = run_cli(*TRAIN, '--episodes', '2', '--out', str(out), fsize=LIMIT)
        expected = f"error: {out / 'checkpoint.pt'}: File too large; the run stopped (no " \
                   'checkpoint written yet)'
    else:
        done = run_node(out, ros_domain_id, '-p', 'episodes:=2', fsize=LIMIT)
        expected = f"learner: {out / 'checkpoint.pt'}: File too large; the run stopped (no " \
                   'checkpoint written yet)'
    assert done.returncode == 1, done.stderr[-3000:]
    assert error_lines(done.stderr) == [expected]
    assert not (out / 'checkpoint.pt').exists() and not list(out.rglob('*.partial'))
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0]


def test_one_run_passes_from_the_node_to_the_trainer_and_back(tmp_path, ros_domain_id):
    """One out_dir, three starts: the node plays episode 0, ``rcbf_ros train`` episode 1, the
    node episode 2. Each start continues the last one's learner and rows, and each writes its
    own ``made_by``: the two entry points drive one run, not two formats."""
    out = tmp_path / 'run'
    first = run_node(out, ros_domain_id, '-p', 'episodes:=1')
    assert first.returncode == 0, first.stderr[-3000:]
    assert cli_main([*TRAIN, '--episodes', '2', '--out', str(out), '--resume']) == 0
    assert load_payload(out / 'checkpoint.pt')['made_by'] == 'rcbf_ros train'
    last = run_node(out, ros_domain_id, '-p', 'episodes:=3', '-p', 'resume:=true')
    assert last.returncode == 0, last.stderr[-3000:]
    assert 'resumed at episode 2 of a run of rcbf_ros train' in last.stderr
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0, 1, 2]
    checkpoint = load_payload(out / 'checkpoint.pt')
    assert checkpoint['episode'] == 3 and checkpoint['made_by'] == 'learner node'
    assert [r['episode'] for r in checkpoint['history']] == [0, 1, 2]
    assert checkpoint['learner']['buffer']['size'] == checkpoint['learner']['env_steps'] == \
        3 * STEPS

"""The learner node over real DDS: simulator + safety_filter + learner as separate processes.

The node path must produce the same transitions as the in-process trainer for the same seed:
both drive the same SafeLearner, the same env code and the same SafetyFilter.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time

from dds_harness import end_process, node_runtime  # this directory: on sys.path for pytest
import numpy as np
import pytest
import torch

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.parameters.rules import find_config
from rcbf_ros.ros.loopback import LOOPBACK_CYCLONEDDS_URI
from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.build import RunConfig
from rcbf_ros.training.loop import train
from rcbf_ros.training.run_files import load_payload

pytestmark = pytest.mark.integration

STEPS, START, BATCH = 60, 30, 16


def start(module: str, name: str, args: list[str], env: dict, log: Path) -> subprocess.Popen:
    """Run a node with the packaged params file and ``args`` (``-p`` given as ``name:...``,
    after the file, so that they win over its ``/<name>`` section as rcl orders them)."""
    cmd = [sys.executable, '-m', module, '--ros-args', '-r', f'__node:={name}',
           '--params-file', str(find_config('unicycle')), *args]
    return subprocess.Popen(cmd, env=env, stdout=log.open('w'), stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen) -> None:
    """SIGINT (if still running), SIGKILL after 10 s."""
    end_process(proc, timeout=10)


def test_learner_node_matches_the_in_process_trainer(tmp_path, ros_domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id),
               CYCLONEDDS_URI=LOOPBACK_CYCLONEDDS_URI, OMP_NUM_THREADS='1')
    out = tmp_path / 'node'
    learner_args = ['-p', 'learner:episodes:=2', '-p', f'learner:out_dir:={out}',
                    '-p', 'learner:mode:=diff', '-p', f'learner:start_steps:={START}',
                    '-p', f'learner:update_after:={START}', '-p', f'learner:batch_size:={BATCH}',
                    '-p', 'learner:seed:=3']
    # As the launch table wires it: the simulator takes filter_info (the command with the state
    # it answers), so that an answer to a state published again (a learner still starting
    # after action_timeout_s) is dropped, not applied to the next state.
    procs = [
        start('sim_nodes.simulator_node', 'simulator',
              ['-p', f'simulator:max_steps:={STEPS}', '-p', 'simulator:action_timeout_s:=5.0',
               '-p', 'simulator:seed:=3', '-r', 'cmd_safe:=filter_info'],
              env, tmp_path / 'sim.log'),
        start('rcbf_ros.ros.safety_filter_node', 'safety_filter', [], env,
              tmp_path / 'filter.log'),
    ]
    learner = start('rcbf_ros.ros.learner_node', 'learner', learner_args, env,
                    tmp_path / 'learner.log')
    try:
        assert learner.wait(timeout=240) == 0, (tmp_path / 'learner.log').read_text()[-3000:]
    finally:
        stop(learner)
        for proc in procs:
            stop(proc)
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['episodes'] == 2 and summary['safety_violations'] == 0
    assert (out / 'reward_curve.png').stat().st_size > 1000
    assert 'episode    2/2' in (tmp_path / 'learner.log').read_text()

    node_buffer = load_payload(out / 'checkpoint.pt')['learner']['buffer']
    history = train(RunConfig(system='unicycle', episodes=2, max_steps=STEPS,
                              out_dir=str(tmp_path / 'inproc'), record_bag=False,
                              learner=LearnerConfig(mode='diff', seed=3, start_steps=START,
                                                    update_after=START, batch_size=BATCH,
                                                    sac=SACConfig())),
                    log=lambda _: None)
    assert sum(r['steps'] for r in history) == 2 * STEPS
    ours = load_payload(tmp_path / 'inproc' / 'checkpoint.pt')
    in_process = ours['learner']['buffer']
    size = 2 * STEPS
    assert node_buffer['size'] == in_process['size'] == size
    for name in ('state', 'obs', 'u_rl', 'u_safe', 'reward', 'next_state', 'done'):
        np.testing.assert_allclose(node_buffer['data'][name][:size].numpy(),
                                   in_process['data'][name][:size].numpy(), rtol=0, atol=1e-6,
                                   err_msg=name)
    # Both took the policy box of config/unicycle.yaml's /learner section: forward speeds.
    assert node_buffer['data']['u_rl'][:size, 0].min() >= 0.0
    # The critic diagnostics agree too: the first episode's q_start is the seeded critics'
    # value of the same first step; disc_return sums the same rewards.
    node_rows = [json.loads(line) for line in (out / 'metrics.jsonl').read_text().splitlines()]
    assert node_rows[0]['q_start'] == pytest.approx(history[0]['q_start'], rel=1e-4, abs=1e-6)
    assert [r['disc_return'] for r in node_rows] == \
        pytest.approx([r['disc_return'] for r in history], rel=1e-5, abs=1e-6)


def test_killed_learner_resumes_from_its_checkpoint(tmp_path, ros_domain_id):
    """Two launches of unicycle_learner: the second, with resume:=true, continues the first."""
    out = tmp_path / 'run'
    common = ['--domain-id', str(ros_domain_id), '--without', 'recorder',
              '-p', 'simulator:max_steps:=50', '-p', f'learner:out_dir:={out}',
              '-p', 'learner:start_steps:=20', '-p', 'learner:update_after:=20',
              '-p', 'learner:batch_size:=16']
    env = dict(os.environ, OMP_NUM_THREADS='1')
    for extra in (['-p', 'learner:episodes:=1'],
                  ['-p', 'learner:episodes:=2', '-p', 'learner:resume:=true']):
        done = subprocess.run([sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_learner',
                               *common, *extra], capture_output=True, text=True, timeout=240,
                              env=env)
        assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert 'resumed at episode 1' in done.stdout + done.stderr
    rows = [json.loads(line) for line in (out / 'metrics.jsonl').read_text().splitlines()]
    assert [r['episode'] for r in rows] == [0, 1]
    state = load_payload(out / 'checkpoint.pt')
    assert state['episode'] == 2 and state['learner']['buffer']['size'] == 100


@pytest.mark.parametrize('key,value,named', [
    ('threads', '0', 'threads'), ('threads', "'two'", 'threads'),
    ('initial_alpha', '-0.1', 'initial_alpha'), ('checkpoint_every', '0', 'checkpoint_every'),
    # The params file's max is [2.5, 2.5]; checked at start-up, not at the first step.
    ('policy_limits.min', '[0.0]', 'policy_limits'),
    ('policy_limits.min', '[2.6, 0.0]', 'policy_limits')])
def test_invalid_setting_exits_2_naming_the_key(tmp_path, ros_domain_id, key, value, named):
    env = {**os.environ, 'ROS_DOMAIN_ID': str(ros_domain_id), 'RCBF_ROS_RUNTIME': node_runtime(),
           'CYCLONEDDS_URI': LOOPBACK_CYCLONEDDS_URI}
    log = tmp_path / 'learner.log'
    proc = start('rcbf_ros.ros.learner_node', 'learner',
                 ['-p', f'learner:{key}:={value}', '-p', f'learner:out_dir:={tmp_path}'], env, log)
    try:
        code = proc.wait(timeout=60)
    finally:
        stop(proc)
    assert code == 2, log.read_text()
    assert f'learner: invalid parameters: {named}' in log.read_text()


def test_an_out_dir_that_cannot_be_made_exits_2_naming_it(tmp_path, ros_domain_id):
    """out_dir under a file: one line naming the parameter and the path, nothing written."""
    (tmp_path / 'file').write_text('')
    out = tmp_path / 'file' / 'run'
    code, text = _learner_exit(tmp_path, ros_domain_id, ['-p', f'learner:out_dir:={out}'])
    assert code == 2, text
    assert f'learner: invalid parameters: out_dir: {out}: Not a directory; the run did not ' \
        'start' in text
    assert 'Traceback' not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ['file', 'learner.log']


def _learner_exit(tmp_path: Path, ros_domain_id: int, args: list[str]) -> tuple[int, str]:
    """Exit status and log of a learner node that is expected to stop at start-up."""
    env = {**os.environ, 'ROS_DOMAIN_ID': str(ros_domain_id), 'RCBF_ROS_RUNTIME': node_runtime(),
           'CYCLONEDDS_URI': LOOPBACK_CYCLONEDDS_URI}
    log = tmp_path / 'learner.log'
    proc = start('rcbf_ros.ros.learner_node', 'learner', args, env, log)
    try:
        code = proc.wait(timeout=60)
    finally:
        stop(proc)
    return code, log.read_text()


def _tiny_run(out: Path) -> None:
    train(RunConfig(system='unicycle', episodes=1, max_steps=30, out_dir=str(out),
                    record_bag=False,
                    learner=LearnerConfig(mode='baseline', start_steps=20, update_after=20,
                                          batch_size=BATCH, sac=SACConfig(hidden_sizes=(8, 8)))),
          log=lambda _: None)


def test_out_dir_of_an_existing_run_is_refused_without_resume(tmp_path, ros_domain_id):
    out = tmp_path / 'run'
    _tiny_run(out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    code, log = _learner_exit(tmp_path, ros_domain_id, ['-p', f'learner:out_dir:={out}'])
    assert code == 2, log
    assert f'learner: invalid parameters: out_dir: {out} already holds a run (checkpoint.pt, ' \
        in log and 'set resume:=true to continue it or choose another out_dir' in log
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


class _Mkdir:
    """Loading this pickle with a general unpickler creates ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (str(self.path),))


def test_resume_refuses_a_crafted_checkpoint_without_running_it(tmp_path, ros_domain_id):
    out = tmp_path / 'run'
    out.mkdir()
    marker = tmp_path / 'ran'
    torch.save({'learner': _Mkdir(marker), 'episode': 1, 'history': []}, out / 'checkpoint.pt')
    code, log = _learner_exit(tmp_path, ros_domain_id,
                              ['-p', f'learner:out_dir:={out}', '-p', 'learner:resume:=true'])
    assert code == 2, log
    assert (f"learner: invalid parameters: resume: {out / 'checkpoint.pt'}: refused to load: "
            'it holds more than tensors and plain data (it asks for posix.mkdir)') in log
    assert not marker.exists()


def test_resume_without_a_checkpoint_starts_at_episode_0_keeping_the_rows(tmp_path,
                                                                          ros_domain_id):
    """A node killed before its first checkpoint: resume:=true says so, cuts metrics.jsonl
    back to no rows (the row moves to metrics_superseded.jsonl) and waits for episode 0."""
    out = tmp_path / 'run'
    out.mkdir()
    row = json.dumps({'episode': 0, 'ret': 1.0}) + '\n'
    (out / 'metrics.jsonl').write_text(row)
    env = {**os.environ, 'ROS_DOMAIN_ID': str(ros_domain_id), 'RCBF_ROS_RUNTIME': node_runtime(),
           'CYCLONEDDS_URI': LOOPBACK_CYCLONEDDS_URI}
    log = tmp_path / 'learner.log'
    proc = start('rcbf_ros.ros.learner_node', 'learner',
                 ['-p', f'learner:out_dir:={out}', '-p', 'learner:resume:=true'], env, log)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if 'episodes ->' in log.read_text():
                break
            time.sleep(0.1)
    finally:
        stop(proc)
    text = log.read_text()
    assert proc.returncode == 0, text
    assert f'no checkpoint in {out}: starting at episode 0 (the files there are kept)' in text
    assert "metrics.jsonl: cut back to the checkpoint's 0 episode(s); 1 later row(s)" in text
    assert (out / 'metrics.jsonl').read_text() == ''
    assert (out / 'metrics_superseded.jsonl').read_text() == row
    # Nothing ran: no summary, checkpoint or policy is written on the way out.
    assert sorted(p.name for p in out.iterdir()) == ['metrics.jsonl', 'metrics_superseded.jsonl']

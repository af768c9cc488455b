"""The learner node over real DDS: simulator + safety_filter + learner as separate processes.

The node path must produce the same transitions as the in-process trainer for the same seed:
both drive the same SafeLearner, the same env code and the same SafetyFilter.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys

import numpy as np
import pytest

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.params import find_config
from rcbf_ros.ros.loopback import LOOPBACK_CYCLONEDDS_URI
from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.loop import RunConfig, train
from rcbf_ros.training.run_files import load_payload

pytestmark = pytest.mark.integration

STEPS, START, BATCH = 60, 30, 16


def start(module: str, name: str, args: list[str], env: dict, log: Path) -> subprocess.Popen:
    cmd = [sys.executable, '-m', module, '--ros-args', '-r', f'__node:={name}',
           '--params-file', str(find_config('unicycle')), *args]
    return subprocess.Popen(cmd, env=env, stdout=log.open('w'), stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_learner_node_matches_the_in_process_trainer(tmp_path, ros_domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id),
               CYCLONEDDS_URI=LOOPBACK_CYCLONEDDS_URI, OMP_NUM_THREADS='1')
    out = tmp_path / 'node'
    learner_args = ['-p', 'episodes:=2', '-p', f'out_dir:={out}', '-p', 'mode:=diff',
                    '-p', f'start_steps:={START}', '-p', f'update_after:={START}',
                    '-p', f'batch_size:={BATCH}', '-p', 'seed:=3']
    procs = [
        start('sim_nodes.simulator_node', 'simulator',
              ['-p', f'max_steps:={STEPS}', '-p', 'action_timeout_s:=5.0', '-p', 'seed:=3'],
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
        done = subprocess.run([sys.executable, '-m', 'rcbf_ros.launch_local', 'unicycle_learner',
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
    ('initial_alpha', '-0.1', 'initial_alpha'),
    # The params file's max is [2.5, 2.5]; checked at start-up, not at the first step.
    ('policy_limits.min', '[0.0]', 'policy_limits'),
    ('policy_limits.min', '[2.6, 0.0]', 'policy_limits')])
def test_invalid_setting_exits_2_naming_the_key(tmp_path, ros_domain_id, key, value, named):
    env = {**os.environ, 'ROS_DOMAIN_ID': str(ros_domain_id), 'RCBF_ROS_RUNTIME': 'cyclone',
           'CYCLONEDDS_URI': LOOPBACK_CYCLONEDDS_URI}
    log = tmp_path / 'learner.log'
    proc = start('rcbf_ros.ros.learner_node', 'learner',
                 ['-p', f'{key}:={value}', '-p', f'out_dir:={tmp_path}'], env, log)
    try:
        code = proc.wait(timeout=60)
    finally:
        stop(proc)
    assert code == 2, log.read_text()
    assert f'learner: invalid parameters: {named}' in log.read_text()

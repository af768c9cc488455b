"""A trained policy alone behind the safety filter, over DDS (the deployment path)."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.build import RunConfig
from rcbf_ros.training.loop import train
from rcbf_ros.training.policy_io import load_policy

pytestmark = pytest.mark.integration


def test_policy_export_drives_the_simulator_through_the_filter(tmp_path, ros_domain_id):
    train(RunConfig(system='unicycle', episodes=1, max_steps=40, out_dir=str(tmp_path / 'run'),
                    record_bag=False,
                    learner=LearnerConfig(mode='modular', start_steps=20, update_after=20,
                                          batch_size=16, sac=SACConfig(hidden_sizes=(32, 32)))),
          log=lambda _: None)
    policy_path = tmp_path / 'run' / 'policy.pt'
    policy = load_policy(policy_path)
    u = policy(np.zeros(policy.obs_dim))
    assert u.shape == (2,) and np.all(np.abs(u) <= 2.5)
    with pytest.raises(ValueError, match='observation'):
        policy(np.zeros(policy.obs_dim + 1))

    cmd = [sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_policy',
           '--domain-id', str(ros_domain_id), '--without', 'recorder',
           '-p', 'simulator:max_steps:=150', '-p', 'simulator:max_episodes:=1',
           '-p', f'policy:policy_path:={policy_path}']
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180,
                          env=dict(os.environ, OMP_NUM_THREADS='1'))
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-3000:]
    assert 'episode 1: return' in log and ', 150 steps, 0 violations' in log, log[-3000:]


def test_missing_policy_file_is_a_clear_error(tmp_path, ros_domain_id):
    with pytest.raises(FileNotFoundError, match='policy_path: no file'):
        load_policy(tmp_path / 'nope.pt')
    done = subprocess.run(
        [sys.executable, '-m', 'rcbf_ros.ros.policy_node', '--ros-args',
         '-p', f"policy_path:={tmp_path / 'nope.pt'}"], capture_output=True, text=True,
        timeout=60, env=dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id)))
    log = done.stdout + done.stderr
    assert done.returncode == 2, log
    assert f"policy: policy_path: no file {tmp_path / 'nope.pt'}" in log  # said once

"""Setting parameters gives the same outcomes on real rclpy as on the Cyclone runtime.

``parameter_semantics.py`` runs one scenario (per-parameter and atomic sets, pre-set, on-set
and post-set callbacks, read-only and typed descriptors, integer and floating-point ranges,
declarations with callbacks in place, undeclared names, ``list_parameters``) under a real
Jazzy's rclpy and under our runtime; every step's successful flags, reasons, raised exception
type, resulting values and order of callback calls must be equal.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
SCRIPT = HERE / 'parameter_semantics.py'


def test_set_parameters_matches_rclpy(jazzy, ros_domain_id):
    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); "$PY" {SCRIPT} rclpy',
                     domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    theirs = json.loads(done.stdout.strip().splitlines()[-1])
    env = dict(os.environ, RCBF_ROS_RUNTIME='cyclone', ROS_DOMAIN_ID=str(ros_domain_id),
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')])))
    ensure_loopback(env, force=True)
    ours_run = subprocess.run([sys.executable, str(SCRIPT), 'cyclone'], env=env, text=True,
                              capture_output=True, timeout=120)
    assert ours_run.returncode == 0, ours_run.stderr[-3000:]
    ours = json.loads(ours_run.stdout.strip().splitlines()[-1])
    assert [s['step'] for s in ours] == [s['step'] for s in theirs]
    differences = [(o, t) for o, t in zip(ours, theirs) if o != t]
    assert not differences, '\n'.join(f'ours  {json.dumps(o)}\nrclpy {json.dumps(t)}'
                                      for o, t in differences)

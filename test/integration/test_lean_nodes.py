"""The nodes and commands of the filter's path as processes, with torch unimportable in every one.

A ``sitecustomize`` on the children's path refuses torch (as a robot computer without the wheel
would) and notes every attempt in a file: ``rcbf_ros launch unicycle_filter`` (simulator,
safety_filter, nominal_controller, scene_markers, recorder) runs an episode into a bag, then
``replay`` plays it, and ``rcbf_ros bag check``, ``refilter`` and ``summary`` read it (summary
also with matplotlib refused). Nothing may even try to import torch.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import textwrap

from dds_harness import REPO, subprocess_env  # this directory: on sys.path for pytest
import pytest

from rcbf_ros.bag import bag_info

pytestmark = pytest.mark.integration

STEPS = 20

_REFUSE_TORCH = textwrap.dedent("""
    import os
    import sys


    class _NoTorch:
        '''Refuses torch, as an install without it does, and notes who asked.'''

        def find_spec(self, name, path=None, target=None):
            if name == 'torch' or name.startswith('torch.'):
                with open(os.environ['RCBF_TEST_TORCH_ATTEMPTS'], 'a') as attempts:
                    attempts.write(f'{sys.argv!r} imported {name}\\n')
                raise ModuleNotFoundError(f'No module named {name!r}', name=name)
            if os.environ.get('RCBF_TEST_NO_MATPLOTLIB') and name.startswith('matplotlib'):
                raise ModuleNotFoundError(f'No module named {name!r}', name=name)


    sys.meta_path.insert(0, _NoTorch())
""")


def test_the_nodes_and_commands_run_without_torch(tmp_path: Path, ros_domain_id: int) -> None:
    site = tmp_path / 'site'
    site.mkdir()
    (site / 'sitecustomize.py').write_text(_REFUSE_TORCH)
    attempts = tmp_path / 'torch_attempts.txt'
    env = subprocess_env(ros_domain_id)
    env.update(PYTHONPATH=os.pathsep.join([str(site), env['PYTHONPATH']]),
               RCBF_TEST_TORCH_ATTEMPTS=str(attempts), OMP_NUM_THREADS='1')
    run = tmp_path / 'run'

    def command(*args: str) -> subprocess.CompletedProcess:
        done = subprocess.run([sys.executable, *args], env=env, cwd=REPO, capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 0, (args, (done.stdout + done.stderr)[-4000:])
        return done

    probe = command('-c', 'import sys, importlib.util; '
                          'print(importlib.util.find_spec("sitecustomize").origin)')
    assert probe.stdout.strip() == str(site / 'sitecustomize.py')  # the refusal is in place

    launch = command('-m', 'rcbf_ros', 'launch', 'unicycle_filter',
                     '--domain-id', str(ros_domain_id), '-p', 'simulator:max_episodes:=1',
                     '-p', f'simulator:max_steps:={STEPS}',
                     '-p', f'recorder:output:={run / "bag"}')
    output = launch.stdout + launch.stderr
    for node in ('simulator', 'safety_filter', 'nominal_controller', 'scene_markers',
                 'recorder'):
        assert f"'{node}': 0" in output, output[-4000:]  # every node started and ended well
    # The simulator steps on each answer of the filter (lock-step): the episode ran to its end.
    assert 'episode 1: return' in output and f'{STEPS} steps' in output, output[-4000:]
    topics = bag_info(run / 'bag').topics  # the recorder may join a topic late: some of each
    assert topics['/cmd_safe'].message_count > 0 and topics['/state'].message_count > 0

    replay = command('-m', 'rcbf_ros.ros.node_main', 'rcbf_ros.ros.replay_node', '--ros-args',
                     '-p', f'bag:={run / "bag"}', '-p', 'rate:=50.0', '-p', 'linger_s:=0.1')
    assert 'replay finished' in replay.stdout + replay.stderr

    assert 'intact' in command('-m', 'rcbf_ros', 'bag', 'check', str(run / 'bag')).stdout
    command('-m', 'rcbf_ros', 'refilter', str(run / 'bag'), str(tmp_path / 'refiltered'),
            '--params-file', 'unicycle', '--json', str(tmp_path / 'refilter.json'))
    refiltered = json.loads((tmp_path / 'refilter.json').read_text())
    assert refiltered['processed'] == topics['/cmd_proposed'].message_count > 0
    assert refiltered['states_evaluated'] > 0 and len(refiltered['min_h']) == 5

    (run / 'learner').mkdir()  # summary reads a run: the learner's summary, then the bag
    (run / 'learner' / 'summary.json').write_text('{"episodes": 1}\n')
    summary = command('-m', 'rcbf_ros', 'summary', str(run)).stdout
    assert f'trajectories: {run / "trajectories.png"}' in summary, summary
    env['RCBF_TEST_NO_MATPLOTLIB'] = '1'  # the filter's install has none: no picture, and why
    summary = command('-m', 'rcbf_ros', 'summary', str(run)).stdout
    assert f'bag: {run / "bag"}' in summary, summary
    assert 'trajectories: not drawn: matplotlib draws the pictures: pip install matplotlib' in (
        summary), summary

    assert not attempts.exists(), attempts.read_text()

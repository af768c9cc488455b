"""SIGHUP to ``rcbf_ros launch`` (its terminal closed) stops the launch as SIGTERM does.

Each child runs in its own process group, so a terminal's hangup reaches the launcher alone;
a launcher ending at once left every node running without it (the recorder's bag never
closed). Now the nodes get SIGINT, the bag is closed and the launch exits 0.
"""
from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from dds_harness import node_runtime  # this directory: on sys.path for pytest
import pytest

REPO = Path(__file__).resolve().parents[2]
WAIT_S = 90.0
"""Upper bound for a launch to come up or stop on a loaded machine (a hang, not a speed test)."""

pytestmark = pytest.mark.integration


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_hangup_stops_the_launch_and_leaves_no_node_running(tmp_path, ros_domain_id):
    out = tmp_path / 'launch.txt'
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), RCBF_ROS_RUNTIME=node_runtime(),
               PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(REPO), env.get('PYTHONPATH')]))
    with open(out, 'w') as log:
        launcher = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_filter', '--without',
             'simulator', '--without', 'nominal_controller', '--without', 'scene_markers',
             '-p', f'recorder:output:={tmp_path / "bag"}'],
            env=env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    children: list[int] = []
    try:
        deadline = time.monotonic() + WAIT_S
        while 'recording all topics' not in out.read_text():
            assert launcher.poll() is None and time.monotonic() < deadline, out.read_text()
            time.sleep(0.1)
        children = [int(pid) for pid in subprocess.run(
            ['pgrep', '-P', str(launcher.pid)], capture_output=True, text=True).stdout.split()]
        assert len(children) == 2  # safety_filter, recorder
        launcher.send_signal(signal.SIGHUP)
        code = launcher.wait(timeout=WAIT_S)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        for pid in children:  # never left behind, whatever the outcome
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    output = out.read_text()
    assert code == 0, output[-3000:]
    assert 'Traceback' not in output
    assert f'bag {tmp_path / "bag"} closed' in output
    assert not [pid for pid in children if _alive(pid)]

"""The filter launch starts its first episode once the loop listens, and records its start.

``rcbf_ros launch unicycle_filter`` runs with its nominal controller started two seconds after
the simulator is up (a proposer that is slow to start, as the learner is while it loads torch).
The simulator must hold the first state until the controller listens (no "no cmd_safe within"
warning, no warning at all), and the bag must begin with the first episode's start event.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap

from dds_harness import node_runtime  # this directory: on sys.path for pytest
import pytest

from rcbf_ros.bag import bag_info, read_bag_messages, RecordedQos
from rcbf_ros.launch.table import launch_setup, ros_arguments
from rcbf_ros.parameters.rules import find_config

pytestmark = pytest.mark.integration

REPO_ROOT = Path(__file__).resolve().parents[2]
STEPS = 40
LATE_S = 2.0

# Waits until the simulator publishes /state, waits LATE_S more, then becomes the controller.
_LATE_CONTROLLER = textwrap.dedent("""
    import os, sys, time
    from rcbf_ros.ros.runtime import Node, rclpy
    rclpy.init()
    node = Node('late_start_probe')
    deadline = time.monotonic() + 120
    while node.count_publishers('/state') < 1:
        if time.monotonic() > deadline:
            sys.exit('the simulator never came up')
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    time.sleep(float(sys.argv[1]))
    os.execv(sys.executable, [sys.executable, '-m', 'sim_nodes.nominal_controller_node',
                              *sys.argv[2:]])
""")


def test_a_late_controller_gets_the_first_state_and_the_bag_the_first_start(
        tmp_path: Path, ros_domain_id: int) -> None:
    bag = tmp_path / 'bag'
    paths = [str(REPO_ROOT), *filter(None, [os.environ.get('PYTHONPATH')])]  # ROS's kept
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONPATH=os.pathsep.join(paths),
               RCBF_ROS_RUNTIME=node_runtime(), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    controller_args = ros_arguments(launch_setup('unicycle_filter').node('nominal_controller'),
                                    params_file=str(find_config('unicycle.yaml')))
    controller = subprocess.Popen(
        [sys.executable, '-c', _LATE_CONTROLLER, str(LATE_S), *controller_args],
        env=env, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        launch = subprocess.run(
            [sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_filter',
             '--domain-id', str(ros_domain_id), '--without', 'nominal_controller',
             '-p', 'simulator:max_episodes:=1', '-p', f'simulator:max_steps:={STEPS}',
             '-p', f'recorder:output:={bag}'],
            env=env, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    finally:
        if controller.poll() is None:
            controller.send_signal(signal.SIGINT)
        try:
            controller_out, _ = controller.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            controller.kill()
            controller_out, _ = controller.communicate()
    output = launch.stdout + launch.stderr
    assert launch.returncode == 0, output[-4000:]
    assert 'nominal controller for unicycle' in controller_out, controller_out
    assert 'no cmd_safe within' not in output, output
    assert '[WARN]' not in output, output

    events = [json.loads(message.data)
              for _, message in read_bag_messages(bag, topics=['/episode'])]
    assert [(e['event'], e['episode']) for e in events] == [('start', 1), ('end', 1)], events
    start = events[0]
    assert start['system'] == 'unicycle' and start['h_true_names'] and 'layout_seed' in start
    assert events[1]['steps'] == STEPS
    # Latched, so that a recorder (or anyone asking for transient local) that joins late still
    # gets the first start event; the bag says so as rosbag2 would.
    assert bag_info(bag).topics['/episode'].offered_qos == (
        RecordedQos(depth=10, durability='transient_local'),)

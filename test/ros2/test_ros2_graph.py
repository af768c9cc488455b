"""Stock ROS 2 tools see nodes on our Cyclone runtime, and our runtime sees rclpy nodes.

The safety filter and the simulator run as the launch starts them, on ``RCBF_ROS_RUNTIME=
cyclone``; Jazzy's ros2cli (``--no-daemon``) must list them, show their endpoints, name them as
the owners of ``/cmd_safe``'s endpoints and receive their ``/rosout`` lines. The reverse: an
rclpy node started in the Jazzy environment appears in our runtime's ``get_node_names`` and as
the owner of its publisher.
"""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Callable

import pytest

from rcbf_ros.launch.table import launch_setup, ros_arguments
from rcbf_ros.parameters.rules import find_config
from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))
from conftest import Jazzy, stop_group  # noqa: E402

TIMEOUT_S = 90.0


def _poll(check: Callable[[], str | None], what: str, timeout: float = TIMEOUT_S) -> str:
    """Call ``check`` until it returns text; fail naming ``what`` and its last output."""
    deadline = time.monotonic() + timeout
    last = ''
    while time.monotonic() < deadline:
        result = check()
        if isinstance(result, str):
            return result
        last = result[1] if isinstance(result, tuple) else last
        time.sleep(0.5)
    raise AssertionError(f'timed out waiting for {what}; last output:\n{last[-3000:]}')


def _start_ours(module: str, node: str, domain_id: int, log: Path) -> subprocess.Popen:
    """A node of the filter launch on our runtime, in its own process group."""
    entry = launch_setup('unicycle_filter').node(node)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), RCBF_ROS_RUNTIME='cyclone',
               PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')])))
    ensure_loopback(env, force=True)
    args = ros_arguments(entry, params_file=str(find_config('unicycle.yaml')))
    return subprocess.Popen([sys.executable, '-m', module, *args], env=env, cwd=REPO,
                            start_new_session=True, stdout=log.open('w'),
                            stderr=subprocess.STDOUT)


def test_ros2cli_lists_and_describes_nodes_on_our_runtime(jazzy: Jazzy, tmp_path: Path,
                                                          ros_domain_id: int) -> None:
    echo = jazzy.start('ros2 topic echo --once --qos-reliability reliable '
                       '--qos-durability transient_local /rosout rcl_interfaces/msg/Log',
                       domain_id=ros_domain_id, log=tmp_path / 'echo.log')
    nodes = [_start_ours('rcbf_ros.ros.safety_filter_node', 'safety_filter', ros_domain_id,
                         tmp_path / 'safety_filter.log'),
             _start_ours('sim_nodes.simulator_node', 'simulator', ros_domain_id,
                         tmp_path / 'simulator.log')]
    try:
        def listed() -> str | tuple:
            done = jazzy.run('ros2 node list --no-daemon', domain_id=ros_domain_id)
            names = done.stdout.split()
            ok = '/safety_filter' in names and '/simulator' in names
            return done.stdout if ok else (None, done.stdout)
        _poll(listed, 'ros2 node list to show /safety_filter and /simulator')

        def described() -> str | tuple:
            done = jazzy.run('ros2 node info /safety_filter --no-daemon',
                             domain_id=ros_domain_id)
            ok = done.returncode == 0 and '/cmd_safe: std_msgs/msg/Float64MultiArray' in \
                done.stdout.split('Publishers:')[-1]
            return done.stdout if ok else (None, done.stdout)
        info = _poll(described, 'ros2 node info /safety_filter')
        subscribers, publishers = info.split('Subscribers:')[1].split('Publishers:')
        publishers = publishers.split('Service Servers:')[0]
        assert '/state: std_msgs/msg/Float64MultiArray' in subscribers
        assert '/cmd_proposed: std_msgs/msg/Float64MultiArray' in subscribers
        assert '/rosout: rcl_interfaces/msg/Log' in publishers
        simulator = jazzy.run('ros2 node info /simulator --no-daemon', domain_id=ros_domain_id)
        assert '/state: std_msgs/msg/Float64MultiArray' in \
            simulator.stdout.split('Publishers:')[1].split('Service Servers:')[0], simulator.stdout

        def owners() -> str | tuple:
            done = jazzy.run('ros2 topic info -v /cmd_safe --no-daemon',
                             domain_id=ros_domain_id)
            ok = 'Node name: safety_filter' in done.stdout and 'PUBLISHER' in done.stdout
            return done.stdout if ok else (None, done.stdout)
        verbose = _poll(owners, 'ros2 topic info -v /cmd_safe to name the safety filter')
        assert '_NODE_NAME_UNKNOWN_' not in verbose
        assert 'Node namespace: /' in verbose

        echo.wait(timeout=TIMEOUT_S)
        echoed = (tmp_path / 'echo.log').read_text()
        assert 'level: ' in echoed and 'name: ' in echoed, echoed
        assert ('name: safety_filter' in echoed or 'name: simulator' in echoed), echoed
    finally:
        for process in (echo, *nodes):
            stop_group(process)


def test_our_runtime_sees_an_rclpy_node(jazzy: Jazzy, tmp_path: Path,
                                        ros_domain_id: int) -> None:
    from rcbf_ros.ros.dds.context import Context
    from rcbf_ros.ros.dds.node import Node
    script = REPO / 'test' / 'ros2' / 'rclpy_talker.py'
    talker = jazzy.start(f'exec "$(head -1 "$(command -v ros2)" | cut -c3-)" {script}',
                         domain_id=ros_domain_id, log=tmp_path / 'talker.log')
    context = Context()
    context.init(args=[], domain_id=ros_domain_id)
    try:
        observer = Node('observer', context=context)

        def seen() -> str | tuple:
            pairs = observer.get_node_names_and_namespaces()
            return 'yes' if ('jazzy_talker', '/oracle') in pairs else (None, str(pairs))
        _poll(seen, 'the rclpy node in get_node_names_and_namespaces')
        assert 'jazzy_talker' in observer.get_node_names()

        def owner() -> str | tuple:
            infos = observer.get_publishers_info_by_topic('/oracle/chatter')
            named = [(i.node_name, i.node_namespace) for i in infos]
            return 'yes' if named == [('jazzy_talker', '/oracle')] else (None, str(named))
        _poll(owner, 'the rclpy publisher named by its node')
        stop_group(talker)

        def gone() -> str | tuple:
            names = observer.get_node_names()
            return 'yes' if 'jazzy_talker' not in names else (None, str(names))
        _poll(gone, 'the stopped rclpy node leaving the graph')
    finally:
        stop_group(talker)
        context.try_shutdown()

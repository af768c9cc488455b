"""The nodes that read their parameters only at start refuse a set over the parameter services.

scene_markers, unicycle_lidar and the simulator read every parameter once, as they start; a
set the runtime took would be reported as done and shown by ``ros2 param get`` while the node
goes on with the old value. Each is built in this process from the packaged params file; a
probe node sets hostile and harmless values through the node's ``set_parameters`` and
``set_parameters_atomically`` services over Cyclone DDS (loopback): every set is refused with
a reason naming the key, and ``get_parameters`` still answers the value the node uses.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

from dds_harness import node_runtime, REPO  # this directory: on sys.path for pytest
import pytest

UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')

pytestmark = [
    pytest.mark.integration,
    # The nodes are built in this process next to a probe on our runtime; under rclpy they
    # would be rclpy nodes without its init. There rcl itself refuses a set of a read-only
    # parameter, and test/unit/test_parameter_declarations.py checks the declarations.
    pytest.mark.skipif(node_runtime() == 'rclpy',
                       reason='in-process nodes on our runtime; rclpy enforces read_only '
                              'itself (test_parameter_declarations.py)'),
]


def _scene() -> Any:
    from rcbf_ros.ros.scene_node import SceneNode
    return SceneNode()


def _lidar() -> Any:
    from sim_nodes.unicycle_lidar_node import UnicycleLidarNode
    return UnicycleLidarNode()


def _simulator() -> Any:
    from sim_nodes.simulator_node import SimulatorNode
    return SimulatorNode()


NAN, INF = math.nan, math.inf
CASES: list[tuple[str, Callable[[], Any], list[tuple[str, Any]]]] = [
    ('scene_markers', _scene, [('frame_id', '/x y'), ('obstacles.x', [NAN]),
                               ('system', 'pvtol'), ('rate_hz', 5.0)]),
    ('unicycle_lidar', _lidar, [('laser_mount', [NAN, 0.0, 0.0]), ('odom_frame_id', ''),
                                ('laser_frame_id', 'odom'), ('start', [100.0, 100.0, 0.0])]),
    ('simulator', _simulator, [('mode', 'bogus'), ('obstacles.radius', [-1.0]),
                               ('goal', [INF]), ('system', 'pvtol'), ('seed', 7)]),
]


def _spin_until(nodes: list[Any], future: Any, timeout: float = 20.0) -> Any:
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        for node in nodes:
            rclpy.spin_once(node, timeout_sec=0.01)
    assert future.done(), 'no reply from the parameter service'
    return future.result()


@pytest.mark.parametrize('name, make, sets', CASES, ids=[case[0] for case in CASES])
def test_a_parameter_read_at_start_is_refused_at_runtime_naming_it(name, make, sets,
                                                                   ros_domain_id):
    from rcbf_ros.ros.dds import messages, services
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.node import Node, Parameter
    from rcbf_ros.ros.dds.parameter_service import parameter_from_msg, parameter_msg
    parameter_type = messages.get_message('rcl_interfaces/msg/Parameter')
    set_type = services.get_service('rcl_interfaces/srv/SetParameters')
    atomic_type = services.get_service('rcl_interfaces/srv/SetParametersAtomically')
    get_type = services.get_service('rcl_interfaces/srv/GetParameters')
    rclpy.init(args=['node', '--ros-args', '--params-file', UNICYCLE],
               domain_id=ros_domain_id)
    try:
        node = make()
        probe = Node('probe', start_parameter_services=False)
        keys = [key for key, _ in sets]
        before = {key: node.get_parameter(key).value for key in keys}
        clients = {kind: probe.create_client(srv, f'/{name}/{kind}') for kind, srv in (
            ('set_parameters', set_type), ('set_parameters_atomically', atomic_type),
            ('get_parameters', get_type))}
        for client in clients.values():
            assert client.wait_for_service(timeout_sec=20)
        nodes = [node, probe]
        request = set_type.Request(parameters=[
            parameter_msg(Parameter(key, value=value)) for key, value in sets])
        results = _spin_until(nodes, clients['set_parameters'].call_async(request)).results
        atomic = _spin_until(nodes, clients['set_parameters_atomically'].call_async(
            atomic_type.Request(parameters=request.parameters[:1]))).result
        values = _spin_until(nodes, clients['get_parameters'].call_async(
            get_type.Request(names=keys))).values
        shown = {key: parameter_from_msg(parameter_type(name=key, value=value)).value
                 for key, value in zip(keys, values)}
        after = {key: node.get_parameter(key).value for key in keys}
        node.destroy_node()
        probe.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert [(r.successful, r.reason) for r in results] == [
        (False, f'Trying to set a read-only parameter: {key}.') for key in keys]
    assert not atomic.successful and keys[0] in atomic.reason
    assert after == before
    assert {key: _plain(value) for key, value in shown.items()} == {
        key: _plain(value) for key, value in before.items()}


def _plain(value: Any) -> Any:
    """A parameter value comparable across the runtime's list kinds."""
    return value if isinstance(value, (str, bool, int, float)) else list(value)

"""ROS 2 tools reach the parameters of a node running on our Cyclone runtime, and back.

The safety_filter node runs on our runtime (``RCBF_ROS_RUNTIME=cyclone``) with the unicycle
configuration; real Jazzy tools talk to it: ``ros2 service list`` and ``ros2 service call``,
rclpy's ``AsyncParameterClient`` (``rclpy_parameter_client.py``) and the ``ros2 param`` verbs.
The other way round, our client calls the parameter services of an rclpy node
(``rclpy_parameter_node.py``). The service types' RIHS01 hashes must be Jazzy's own.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time

import pytest

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Node, Parameter
from rcbf_ros.ros.dds.parameter_service import parameter_msg, PARAMETER_SERVICES
from rcbf_ros.ros.dds.services import get_service
from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(REPO / 'test'))
from conftest import stop_group  # noqa: E402

SERVICE_TYPES = {
    'describe_parameters': 'DescribeParameters', 'get_parameters': 'GetParameters',
    'get_parameter_types': 'GetParameterTypes', 'list_parameters': 'ListParameters',
    'set_parameters': 'SetParameters', 'set_parameters_atomically': 'SetParametersAtomically'}


def _start_filter(domain_id: int, log: Path) -> subprocess.Popen:
    """The safety_filter on our runtime, in its own process group."""
    env = dict(os.environ)
    ensure_loopback(env, force=True)
    env.update(ROS_DOMAIN_ID=str(domain_id), RCBF_ROS_RUNTIME='cyclone', PYTHONUNBUFFERED='1',
               OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), env.get('PYTHONPATH')])))
    return subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
         '--params-file', str(REPO / 'config' / 'unicycle.yaml')],
        env=env, cwd=REPO, start_new_session=True, stdout=log.open('w'),
        stderr=subprocess.STDOUT)


def _wait_for_services(jazzy, domain_id: int, process: subprocess.Popen, log: Path) -> str:
    """``ros2 service list -t`` once the filter's get_parameters shows up in it."""
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        assert process.poll() is None, f'the safety_filter exited:\n{log.read_text()[-3000:]}'
        listed = jazzy.run('ros2 service list -t --no-daemon', domain_id=domain_id, timeout=60)
        if '/safety_filter/get_parameters' in listed.stdout:
            return listed.stdout
        time.sleep(1.0)
    raise AssertionError(f'no /safety_filter/get_parameters in ros2 service list:\n'
                         f'{listed.stdout[-2000:]}\nnode log:\n{log.read_text()[-2000:]}')


@pytest.fixture
def safety_filter(jazzy, ros_domain_id, tmp_path):
    log = tmp_path / 'safety_filter.log'
    process = _start_filter(ros_domain_id, log)
    try:
        yield _wait_for_services(jazzy, ros_domain_id, process, log)
    finally:
        stop_group(process)


def test_service_types_hash_as_jazzys(jazzy, ros_domain_id):
    done = jazzy.run('ros2 pkg prefix rcl_interfaces', domain_id=ros_domain_id, timeout=60)
    assert done.returncode == 0, done.stdout
    share = Path(done.stdout.strip().splitlines()[-1]) / 'share' / 'rcl_interfaces' / 'srv'
    for name in SERVICE_TYPES.values():
        hashes = {entry['type_name']: entry['hash_string'] for entry in
                  json.loads((share / f'{name}.json').read_text())['type_hashes']}
        srv = get_service(f'rcl_interfaces/srv/{name}')
        for half in (srv.Request, srv.Response):
            assert messages.type_hash(half._type_name) == hashes[half._type_name], half


def test_ros2_service_and_rclpys_parameter_client_reach_the_filter(jazzy, ros_domain_id,
                                                                   safety_filter):
    listed = {line.split()[0]: line.split()[1] for line in safety_filter.splitlines()
              if line.startswith('/safety_filter/')}
    assert listed == {f'/safety_filter/{name}': f'[rcl_interfaces/srv/{SERVICE_TYPES[name]}]'
                      for name in PARAMETER_SERVICES}

    called = jazzy.run('ros2 service call /safety_filter/get_parameters '
                       'rcl_interfaces/srv/GetParameters "{names: [alpha, system]}"',
                       domain_id=ros_domain_id, timeout=60)
    assert called.returncode == 0, called.stdout
    reply = called.stdout.split('response:', 1)[1]
    assert 'type=3' in reply and 'double_value=2.0' in reply, reply
    assert "string_value='unicycle'" in reply, reply

    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                     f'"$PY" {HERE / "rclpy_parameter_client.py"} /safety_filter',
                     domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    assert 'error' not in found, found
    assert {'alpha', 'system', 'obstacles.x'} <= set(found['list'])
    assert found['get'] == [[3, 2.0, ''], [4, 0.0, 'unicycle']]
    assert found['get_undeclared'] == 0
    (good, wrong_type, undeclared) = found['set']
    assert good == [True, '']
    # alpha is declared dynamically typed: the filter's own check words the refusal
    assert wrong_type == [False, "alpha: expected a number, got 'fast'"]
    # rclpy 7.1.1 lists the undeclared names after the first one only
    assert undeclared == [False, 'Invalid access to undeclared parameter(s): []']
    assert found['get_after_set'] == 3.0
    # a refused set of a dynamically typed parameter still leaves its descriptor's type at the
    # value's, as rclpy does
    assert found['describe'] == [['alpha', 4], ['system', 4]]
    assert found['types'] == [3, 4]


def test_ros2_param_verbs_reach_the_filter(jazzy, ros_domain_id, safety_filter):
    """``ros2 param`` first looks the node up in ``ros2 node list`` (ros_discovery_info)."""
    listed = jazzy.run('ros2 param list /safety_filter --no-daemon', domain_id=ros_domain_id,
                       timeout=60)
    assert listed.returncode == 0 and '  alpha' in listed.stdout.splitlines(), listed.stdout
    got = jazzy.run('ros2 param get /safety_filter alpha --no-daemon',
                    domain_id=ros_domain_id, timeout=60)
    assert 'Double value is: 2.0' in got.stdout, got.stdout
    done = jazzy.run('ros2 param set /safety_filter alpha 2.5 --no-daemon',
                     domain_id=ros_domain_id, timeout=60)
    assert 'Set parameter successful' in done.stdout, done.stdout
    got = jazzy.run('ros2 param get /safety_filter alpha --no-daemon',
                    domain_id=ros_domain_id, timeout=60)
    assert 'Double value is: 2.5' in got.stdout, got.stdout


def test_our_client_reaches_an_rclpy_nodes_parameter_services(jazzy, ros_domain_id, tmp_path):
    log = tmp_path / 'rclpy_node.log'
    process = jazzy.start(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                          f'exec "$PY" {HERE / "rclpy_parameter_node.py"}',
                          domain_id=ros_domain_id, log=log)
    rclpy.init(args=[], domain_id=ros_domain_id)
    try:
        probe = Node('probe', start_parameter_services=False)
        get = probe.create_client(get_service('rcl_interfaces/srv/GetParameters'),
                                  '/safety_filter/get_parameters')
        put = probe.create_client(get_service('rcl_interfaces/srv/SetParameters'),
                                  '/safety_filter/set_parameters')
        for client in (get, put):
            assert client.wait_for_service(timeout_sec=60), log.read_text()[-2000:]
        reply = get.call(get.srv_type.Request(names=['alpha']), timeout_sec=30)
        assert reply is not None and [v.double_value for v in reply.values] == [2.0]
        reply = put.call(put.srv_type.Request(parameters=[
            parameter_msg(Parameter('alpha', value=0.5)),
            parameter_msg(Parameter('alpha', value='fast'))]), timeout_sec=30)
        assert [r.successful for r in reply.results] == [True, False]
        reply = get.call(get.srv_type.Request(names=['alpha']), timeout_sec=30)
        assert [v.double_value for v in reply.values] == [0.5]
    finally:
        rclpy.try_shutdown()
        stop_group(process)

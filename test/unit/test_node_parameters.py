"""A node's parameters on the Cyclone runtime follow rclpy's rules (declaration, types,
descriptors), and the project's nodes and configs work under them.

The rules are rclpy 7.1's ``Node.declare_parameters`` / ``_apply_descriptor`` /
``get_parameter``: a value declares a static type (``[]`` a BYTE_ARRAY), ``Parameter.Type``
declares a type without a value, NOT_SET cannot be a static default, and the descriptor passed
in is kept and written into.
"""
from __future__ import annotations

import pytest
from repo_files import CONFIGS, REPO

from rcbf_ros.parameters.rules import read_params_file
from rcbf_ros.ros.dds import rclpy_compat
from rcbf_ros.ros.dds.node import (
    InvalidParameterTypeException,
    Node,
    Parameter,
    parameter_descriptor,
    ParameterUninitializedException,
)

STRING_ARRAY = Parameter.Type.STRING_ARRAY


@pytest.fixture
def init(ros_domain_id):
    def start(*ros_args: str) -> None:
        rclpy_compat.init(args=['prog', '--ros-args', *ros_args], domain_id=ros_domain_id)
    yield start
    rclpy_compat.try_shutdown()


def test_an_empty_list_in_a_params_file_cannot_be_declared(init, tmp_path):
    # rcl reads [] as NOT_SET; declaring the overrides, rclpy infers NOT_SET as a static type
    # and refuses it (the node cannot start), as a node on rclpy does.
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    bands.tilt.gammas: []\n')
    init('--params-file', str(params))
    with pytest.raises(ValueError, match='PARAMETER_NOT_SET'):
        Node('n', automatically_declare_parameters_from_overrides=True)


@pytest.mark.parametrize('config', CONFIGS, ids=lambda p: p.name)
def test_packaged_configs_hold_no_empty_list(config):
    for key, section in read_params_file(config).items():
        unset = [name for name, value in section.items() if value is None]
        assert not unset, f'{config.name} {key}: {unset} have no value under rcl (empty lists)'


@pytest.mark.parametrize('config', CONFIGS, ids=lambda p: p.name)
def test_every_section_of_the_packaged_configs_declares(init, config):
    init('--params-file', str(config))
    for key in read_params_file(config):
        name = key.strip('/').split('/')[-1]
        node = Node(name if name not in ('*', '**') else 'any',
                    automatically_declare_parameters_from_overrides=True)
        node.destroy_node()


def test_a_string_array_declared_by_type(init):
    init('-p', 'topics:=[/a, /b]', '-p', 'bad:=5')
    node = Node('n')
    assert node.declare_parameter('topics', STRING_ARRAY).value == ['/a', '/b']
    node.declare_parameter('unset', STRING_ARRAY)
    with pytest.raises(ParameterUninitializedException):
        node.get_parameter('unset')
    assert node.get_parameter_or('unset', Parameter('unset', STRING_ARRAY, [])).value == []
    with pytest.raises(InvalidParameterTypeException, match="'bad'"):
        node.declare_parameter('bad', STRING_ARRAY)
    node.destroy_node()


def test_an_empty_list_default_is_a_byte_array(init):
    init('-p', 'topics:=[/a]')
    node = Node('n')
    with pytest.raises(InvalidParameterTypeException, match='BYTE_ARRAY'):
        node.declare_parameter('topics', [])
    assert node.declare_parameter('other', []).type_ is Parameter.Type.BYTE_ARRAY
    node.destroy_node()


def test_a_static_declaration_needs_a_type(init):
    init()
    node = Node('n')
    with pytest.raises(ValueError, match='PARAMETER_NOT_SET'):
        node.declare_parameter('x', None, parameter_descriptor())
    assert node.declare_parameter('y', None, parameter_descriptor(dynamic_typing=True)).value \
        is None
    with pytest.warns(UserWarning, match='deprecated'):
        node.declare_parameter('z')
    node.destroy_node()


def test_the_descriptor_passed_in_is_kept_and_written_into(init):
    init()
    node = Node('n')
    shared = parameter_descriptor(dynamic_typing=True)
    node.declare_parameter('a', 1.0, shared)
    node.declare_parameter('b', 'x', shared)
    assert node.describe_parameter('a') is shared
    assert (shared.name, shared.type) == ('b', Parameter.Type.STRING.value)
    node.destroy_node()


def _descriptors_are_each_their_own(node: Node) -> None:
    names = list(node.get_parameters_by_prefix(''))
    descriptors = node.describe_parameters(names)
    assert len({id(d) for d in descriptors}) == len(names)
    for name, descriptor in zip(names, descriptors):
        parameter = node.get_parameters_by_prefix('')[name]
        assert descriptor.name == name
        assert descriptor.type == parameter.type_.value, name


def test_safety_filter_describes_every_parameter_as_itself(init):
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    init('--params-file', str(REPO / 'config' / 'unicycle.yaml'))
    node = SafetyFilterNode()
    assert {'alpha', 'max_state_age_s', 'obstacles.gammas', 'walls.nx'} <= set(
        node.get_parameters_by_prefix(''))
    _descriptors_are_each_their_own(node)
    node.destroy_node()


def test_scene_markers_describes_every_parameter_as_itself(init):
    from rcbf_ros.ros.scene_node import SceneNode
    init('--params-file', str(REPO / 'config' / 'unicycle.yaml'))
    node = SceneNode()
    _descriptors_are_each_their_own(node)
    node.destroy_node()


def test_recorder_takes_topic_lists_and_names_a_bad_one(init, tmp_path):
    from rcbf_ros.ros.recorder_node import RecorderNode
    init('-p', 'topics:=[/state, /cmd_safe]', '-p', 'best_effort_topics:=[/state]',
         '-p', f'output:={tmp_path / "bag"}')
    node = RecorderNode()
    assert node.config.topics == ('/state', '/cmd_safe')
    assert node.config.best_effort_topics == ('/state',)
    node.close()
    node.destroy_node()
    rclpy_compat.try_shutdown()
    init('-p', 'topics:=5', '-p', f'output:={tmp_path / "bag2"}')
    with pytest.raises(ValueError, match="'topics'"):
        RecorderNode()


def test_recorder_records_everything_without_topics(init, tmp_path):
    from rcbf_ros.ros.recorder_node import RecorderNode
    init('-p', f'output:={tmp_path / "bag"}', '-p', 'topics:=[]')
    node = RecorderNode()
    assert node.config.topics == () and node.config.best_effort_topics == ()
    node.close()
    node.destroy_node()


def test_replay_takes_a_topic_list(init):
    from rcbf_ros.ros.replay_node import ReplayNode
    init('-p', 'topics:=[/state]', '-p', 'bag:=some/bag')
    node = Node('replay')
    assert ReplayNode._read_config(node).topics == ('/state',)
    node.destroy_node()

"""``--ros-args``, parameter files, name resolution, and a Node's parameters (Cyclone runtime)."""
from __future__ import annotations

import textwrap

import pytest

from rcbf_ros.core.mappings import flatten as flatten_parameters
from rcbf_ros.parameters.arguments import (
    expand_topic_name,
    parameter_overrides,
    parse_ros_arguments,
    remove_ros_args,
    resolve_topic_name,
    RosArgumentError,
)
from rcbf_ros.ros.dds import rclpy_compat
from rcbf_ros.ros.dds.node import (
    InvalidParameterTypeException,
    Node,
    ParameterNotDeclaredException,
)


def test_parse_params_remaps_and_special_names(tmp_path):
    params_file = tmp_path / 'a.yaml'
    params_file.write_text('/**:\n  ros__parameters: {from_file: 1}\n')
    args = parse_ros_arguments([
        'prog', 'extra', '--ros-args', '-p', 'rate:=50', '-p', 'gain:=0.5', '--param',
        'name:=hello', '-p', 'flag:=true', '-p', 'limits:=[1.0, 2.5]', '-p', 'quoted:="7"',
        '-p', 'filter:only_here:=3',
        '-r', 'cmd:=/safe_cmd', '--remap', 'talker:chatter:=/x', '-r', '__node:=filter',
        '-r', '__ns:=/robot', '--params-file', str(params_file), '--log-level', 'debug', '--',
        'tail'])
    assert args.parameter_rules.sections() == {
        '/**': {'rate': 50, 'gain': 0.5, 'name': 'hello', 'flag': True, 'limits': [1.0, 2.5],
                'quoted': '7', 'from_file': 1},
        'filter': {'only_here': 3}}
    assert [(r.match, r.replacement, r.node) for r in args.remaps] == [
        ('cmd', '/safe_cmd', None), ('chatter', '/x', 'talker')]
    assert (args.node_name, args.namespace, args.log_level) == ('filter', '/robot', 'debug')
    assert args.params_files == (str(params_file),)
    assert args.unparsed == ('prog', 'extra', 'tail')
    assert remove_ros_args(['p', '--ros-args', '-p', 'a:=1', '--', 'x']) == ['p', 'x']


@pytest.mark.parametrize('argv, words', [
    (['--ros-args', '--bogus'], ['--bogus']),
    (['--ros-args', '-p'], ['-p', 'value']),
    (['--ros-args', '-p', 'rate=5'], ['-p', 'NAME:=VALUE']),
    (['--ros-args', '-p', 'rate:='], ['-p', 'empty']),
    (['--ros-args', '-p', '*:rate:=1'], ['-p', 'NAME:=VALUE']),
    (['--ros-args', '-p', 'a:b:c:=1'], ['-p', 'NAME:=VALUE']),
    (['--ros-args', '-p', 'rate:=[1, 2.5]'], ['-p', 'one type']),
    (['--ros-args', '-p', 'rate:={a: 1}'], ['-p', 'scalar']),
    (['--ros-args', '-r', '__node:=9bad'], ['9bad']),
    (['--ros-args', '-r', '__ns:=/a b'], ['a b']),
])
def test_malformed_arguments_are_named(argv, words):
    with pytest.raises(RosArgumentError) as info:
        parse_ros_arguments(argv)
    assert all(word in str(info.value) for word in words)


def test_flatten_nested_parameters_like_rclpy():
    assert flatten_parameters({'qp': {'eps': 1e-6, 'osqp': {'max_iter': 50}}, 'k': 1}) == {
        'qp.eps': 1e-6, 'qp.osqp.max_iter': 50, 'k': 1}


def test_params_file_precedence(tmp_path):
    first = tmp_path / 'first.yaml'
    first.write_text(textwrap.dedent("""
        /**:
          ros__parameters:
            rate: 10
            shared: from_wildcard
        /robot/filter:
          ros__parameters:
            rate: 20
            qp: {eps: 0.001}
        /other:
          ros__parameters:
            rate: 99
    """))
    second = tmp_path / 'second.yaml'
    second.write_text(textwrap.dedent("""
        /**:
          ros__parameters:
            rate: 30
            late: 1
    """))
    args = parse_ros_arguments(['--ros-args', '--params-file', str(first), '--params-file',
                                str(second), '-p', 'late:=2'])
    overrides = parameter_overrides([args], '/robot/filter')
    # rcl keeps one /** key (opened by the first file, so before /robot/filter): the second
    # file and -p late:=2 write into it, and the node's own section, after it, wins on rate.
    assert overrides == {'rate': 20, 'shared': 'from_wildcard', 'qp.eps': 0.001, 'late': 2}
    assert parameter_overrides([args], '/other')['rate'] == 99


def test_params_file_errors_name_the_file(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/node:\n  rate: 5\n')
    with pytest.raises(RosArgumentError, match='bad.yaml'):
        parse_ros_arguments(['--ros-args', '--params-file', str(bad)])
    with pytest.raises(RosArgumentError, match='missing.yaml'):
        parse_ros_arguments(['--ros-args', '--params-file', str(tmp_path / 'missing.yaml')])


@pytest.mark.parametrize('name, expected', [
    ('state', '/robot/state'), ('/state', '/state'), ('~', '/robot/filter'),
    ('~/diagnostics', '/robot/filter/diagnostics'), ('a/b', '/robot/a/b'),
])
def test_expand_topic_names(name, expected):
    assert expand_topic_name(name, 'filter', '/robot') == expected


@pytest.mark.parametrize('name', ['', 'a//b', 'a/', '1abc', 'a b', '~x', 'scan\n', 'a\n/b'])
def test_invalid_topic_names_rejected(name):
    with pytest.raises(RosArgumentError):
        expand_topic_name(name, 'filter', '/robot')


def test_remaps_expand_and_first_match_wins():
    rules = parse_ros_arguments(['--ros-args', '-r', 'other:cmd:=/nope', '-r',
                                 '/robot/cmd:=safe_cmd', '-r', 'cmd:=/later']).remaps
    assert resolve_topic_name('cmd', 'filter', '/robot', rules) == '/robot/safe_cmd'
    assert resolve_topic_name('state', 'filter', '/robot', rules) == '/robot/state'


@pytest.fixture
def context_args(ros_domain_id, tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text('/ns/tuned:\n  ros__parameters:\n    gain: 2.5\n    limits: {u_max: 1.0}\n')
    rclpy_compat.init(args=['prog', '--ros-args', '--params-file', str(params), '-p',
                            'rate:=25', '-r', '__ns:=/ns', '-r', 'cmd:=safe_cmd'],
                      domain_id=ros_domain_id)
    yield
    rclpy_compat.try_shutdown()


def test_node_parameters_names_and_remaps(context_args):
    node = Node('tuned')
    assert node.get_fully_qualified_name() == '/ns/tuned'
    assert node.declare_parameter('gain', 1.0).value == 2.5
    assert node.declare_parameter('rate', 10).value == 25
    assert node.declare_parameter('untouched', 'abc').value == 'abc'
    declared = node.declare_parameters('limits', [('u_max', 5.0), ('u_min', -5.0)])
    assert [p.value for p in declared] == [1.0, -5.0]
    assert node.get_parameter('limits.u_max').value == 1.0
    with pytest.raises(ParameterNotDeclaredException, match='nope'):
        node.get_parameter('nope')
    assert node.resolve_topic_name('cmd') == '/ns/safe_cmd'
    publisher = node.create_publisher('std_msgs/msg/Float64', '~/out', 10)
    assert publisher.topic_name == '/ns/tuned/out'
    node.destroy_node()


def test_node_rejects_override_of_another_type(context_args):
    node = Node('tuned')
    with pytest.raises(InvalidParameterTypeException, match="'rate'"):
        node.declare_parameter('rate', 'fast')  # -p rate:=25 is an INTEGER
    node.destroy_node()


def test_node_renamed_from_command_line(ros_domain_id):
    rclpy_compat.init(args=['--ros-args', '-r', '__node:=renamed'], domain_id=ros_domain_id)
    try:
        node = Node('original', cli_args=['--ros-args', '-r', '__ns:=/inner'])
        assert (node.get_name(), node.get_namespace()) == ('renamed', '/inner')
        node.destroy_node()
        # As rcl: words before --ros-args are the program's, not ROS arguments.
        node = Node('original', cli_args=['-r', '__ns:=/inner'])
        assert (node.get_name(), node.get_namespace()) == ('renamed', '/')
        node.destroy_node()
    finally:
        rclpy_compat.try_shutdown()

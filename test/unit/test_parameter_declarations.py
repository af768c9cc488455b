"""The nodes declare their parameters one way: :func:`rcbf_ros.ros.node_main.declare_specs`.

An AST oracle finds every ``declare_parameter`` / ``has_parameter`` / ``undeclare_parameter``
call in the node modules; only node_main may make them. And every parameter a node holds once
built, its own, the packaged ones and those its command line gave, has a description (and a
range where its spec has one), read back through the runtime's ``describe_parameters``.
"""
from __future__ import annotations

import ast
import math
from pathlib import Path
from typing import Any, Callable

import pytest

from rcbf_ros.parameters.rules import find_config
from rcbf_ros.ros.node_main import declare_specs, OTHER_DESCRIPTION, RUNTIME_PARAMETERS

ROOT = Path(__file__).resolve().parents[2]
UNICYCLE = str(find_config('unicycle'))
DECLARING = ('declare_parameter', 'declare_parameters', 'has_parameter', 'undeclare_parameter')
ONE_WAY = 'rcbf_ros/ros/node_main.py'
NOT_YET: tuple[str, ...] = ()
"""Node modules left out of the oracle while they move onto declare_specs (drop each from here
once it is on declare_specs)."""


def _node_modules() -> list[Path]:
    return sorted([*ROOT.glob('rcbf_ros/ros/*.py'), *ROOT.glob('sim_nodes/*.py')])


def _declaring_calls(path: Path) -> list[str]:
    return [f'line {node.lineno}: {node.func.attr}'
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path)))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr in DECLARING]


@pytest.mark.parametrize('path', _node_modules(), ids=lambda p: str(p.relative_to(ROOT)))
def test_only_node_main_declares_parameters(path):
    relative = str(path.relative_to(ROOT))
    if relative == ONE_WAY or relative in NOT_YET:
        return
    assert _declaring_calls(path) == [], f'{relative}: declare through node_main.declare_specs'


def test_the_oracle_sees_the_one_way(tmp_path):
    assert _declaring_calls(ROOT / ONE_WAY)
    sample = tmp_path / 'sample.py'
    sample.write_text('if not self.has_parameter(n):\n    self.declare_parameter(n, 1)\n')
    assert _declaring_calls(sample) == ['line 1: has_parameter', 'line 2: declare_parameter']
    for relative in NOT_YET:
        assert (ROOT / relative).is_file(), f'{relative} is gone: drop it from NOT_YET'


def _cases(tmp_path: Path) -> list[tuple[str, Callable[[], Any], list[str]]]:
    from rcbf_ros.ros.learner_node import LearnerNode
    from rcbf_ros.ros.policy_node import PolicyNode
    from rcbf_ros.ros.recorder_node import RecorderNode
    from rcbf_ros.ros.replay_node import ReplayNode
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    from rcbf_ros.ros.scene_node import SceneNode
    from sim_nodes.nominal_controller_node import NominalControllerNode
    from sim_nodes.simulator_node import SimulatorNode
    from sim_nodes.unicycle_lidar_node import UnicycleLidarNode
    return [
        ('simulator', SimulatorNode, []),
        ('simulator', SimulatorNode, ['-p', 'system:=pvtol', '-p', 'rate_hz:=20.0',
                                      '-p', 'goal:=[1.0, 2.0]', '-p', 'stray:=3']),
        ('simulator', SimulatorNode, ['--params-file', UNICYCLE]),
        ('nominal_controller', NominalControllerNode, ['-p', 'system:=car_following']),
        ('nominal_controller', NominalControllerNode, ['--params-file', UNICYCLE]),
        ('learner', LearnerNode, ['--params-file', UNICYCLE, '-p',
                                  f'out_dir:={tmp_path / "learner"}']),
        ('policy', PolicyNode, []),  # no policy file: it refuses after declaring
        ('recorder', RecorderNode, ['-p', f'output:={tmp_path / "bag"}']),
        ('replay', ReplayNode, []),  # no bag: it refuses after declaring
        ('scene_markers', SceneNode, ['--params-file', UNICYCLE, '-p', 'rate_hz:=5']),
        ('unicycle_lidar', UnicycleLidarNode, ['--params-file', UNICYCLE]),
        ('safety_filter', SafetyFilterNode, ['--params-file', UNICYCLE, '-p', 'k_c:=3.0']),
    ]


def _built(monkeypatch, ros_domain_id: int, make: Callable[[], Any], args: list[str]
           ) -> dict[str, Any]:
    """name -> descriptor (``describe_parameters``) of every parameter the node holds once
    built; a node that refuses to start (no policy file, no bag) is described as it stood."""
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.node import Node
    nodes: list[Any] = []
    original = Node.__init__

    def remember(self: Any, *a: Any, **k: Any) -> None:
        nodes.append(self)
        original(self, *a, **k)
    monkeypatch.setattr(Node, '__init__', remember)
    rclpy.init(args=['node', '--ros-args', *args], domain_id=ros_domain_id)
    try:
        try:
            made = make()
        except (ValueError, OSError):
            made = None
        node = nodes[0]
        names = sorted(node.get_parameters_by_prefix(''))
        described = dict(zip(names, node.describe_parameters(names)))
        if made is not None and hasattr(made, 'close'):
            made.close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
        monkeypatch.undo()
    return described


def test_every_parameter_of_every_node_has_a_description(monkeypatch, ros_domain_id, tmp_path):
    for name, make, args in _cases(tmp_path):
        described = _built(monkeypatch, ros_domain_id, make, args)
        assert described, name
        bare = [key for key, descriptor in described.items()
                if key not in RUNTIME_PARAMETERS and not descriptor.description]
        assert bare == [], f'{name} {args}: declared without a description: {bare}'


def test_every_node_but_the_filter_declares_every_parameter_read_only(
        monkeypatch, ros_domain_id, tmp_path):
    """They read their parameters once, at start: a set must be refused, not reported done
    and ignored (the filter reads some at runtime and checks them: its own tests)."""
    for name, make, args in _cases(tmp_path):
        if name == 'safety_filter':
            continue
        described = _built(monkeypatch, ros_domain_id, make, args)
        settable = [key for key, descriptor in described.items()
                    if key not in RUNTIME_PARAMETERS and not descriptor.read_only]
        assert settable == [], f'{name} {args}: settable, read only at start: {settable}'


def test_an_override_gets_its_spec_and_a_stray_one_says_it_is_not_read(
        monkeypatch, ros_domain_id, tmp_path):
    from sim_nodes.simulator_node import NODE_PARAMETERS, SimulatorNode
    described = _built(monkeypatch, ros_domain_id, SimulatorNode,
                       ['-p', 'system:=pvtol', '-p', 'rate_hz:=20.0', '-p', 'stray:=3'])
    rate = next(spec for spec in NODE_PARAMETERS if spec.name == 'rate_hz')
    assert described['rate_hz'].description == rate.description
    assert described['rate_hz'].floating_point_range[0].from_value == rate.range[0]
    assert described['max_episodes'].integer_range[0].from_value == 0
    assert 'the simulated system' in described['system'].description
    assert described['stray'].description == OTHER_DESCRIPTION
    scene = _built(monkeypatch, ros_domain_id, _scene, ['--params-file', UNICYCLE])
    assert 'obstacle' in scene['obstacles.x'].description  # described as the filter's


def _scene() -> Any:
    from rcbf_ros.ros.scene_node import SceneNode
    return SceneNode()


def test_an_override_outside_its_range_is_refused_in_one_line_as_before(ros_domain_id):
    """Left as the override declared it, for the node's reader to refuse with its own line."""
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from sim_nodes.simulator_node import SimulatorNode
    rclpy.init(args=['node', '--ros-args', '-p', 'rate_hz:=-2.0'], domain_id=ros_domain_id)
    try:
        with pytest.raises(ValueError, match=r'^rate_hz: must be >= 0\.001, got -2\.0$'):
            SimulatorNode()
    finally:
        rclpy.try_shutdown()


def test_declare_specs_declares_a_string_list_by_type_and_a_pattern_only_when_given(
        ros_domain_id):
    from rcbf_ros.node_logic.interface import ParameterSpec
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.node import Node
    rclpy.init(args=['node', '--ros-args', '-p', 'bands.a.index:=1'], domain_id=ros_domain_id)
    try:
        node = Node('declarations', automatically_declare_parameters_from_overrides=True)
        declare_specs(node, (ParameterSpec('topics', [], 'string[]', 'topics'),
                             ParameterSpec('bands.<name>.index', None, 'integer', 'an index',
                                           minimum=0)))
        assert node.get_parameters_by_prefix('')['topics'].value is None  # by type: not set
        assert node.describe_parameter('topics').type == 9  # STRING_ARRAY
        assert not node.has_parameter('bands.<name>.index')
        assert node.describe_parameter('bands.a.index').description == 'an index'
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_declare_specs_marks_read_only_types_overrides_dynamically_and_describes_others(
        ros_domain_id):
    from rcbf_ros.node_logic.interface import ParameterSpec
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.node import Node, Parameter
    rclpy.init(args=['node', '--ros-args', '-p', 'fixed:=1', '-p', 'gain:=2.5', '-p',
                     'family.x:=1', '-p', 'other:=3'], domain_id=ros_domain_id)
    try:
        node = Node('declarations', automatically_declare_parameters_from_overrides=True)
        declare_specs(node, (ParameterSpec('fixed', 0, 'integer', 'fixed at start'),
                             ParameterSpec('gain', 1.0, 'double', 'a gain', minimum=0.0),
                             ParameterSpec('unset', 5, 'integer', 'from its default')),
                      dynamic_overrides=True, read_only=lambda name: name != 'gain',
                      others=lambda name: 'a family' if name.startswith('family.') else None)
        described = {name: node.describe_parameter(name)
                     for name in ('fixed', 'gain', 'unset', 'family.x', 'other')}
        assert [(d.read_only, d.dynamic_typing, d.description)
                for d in described.values()] == [
            (True, True, 'fixed at start'), (False, True, 'a gain'),
            (True, False, 'from its default'), (True, True, 'a family'), (False, False, '')]
        assert described['gain'].floating_point_range[0].from_value == 0.0
        assert node.get_parameter('gain').value == 2.5  # the override's value, kept
        results = node.set_parameters([Parameter('gain', value='any type'),
                                       Parameter('fixed', value=2)])
        assert [r.successful for r in results] == [True, False]
        assert 'read-only' in results[1].reason
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_the_filter_node_declares_as_it_did_through_declare_specs(monkeypatch, ros_domain_id):
    """Read-only where fixed at start, every filter key typed dynamically and described by its
    spec, a family key no spec names described as read-only text, a stray key left bare."""
    from rcbf_ros.node_logic import safety_filter as logic
    from rcbf_ros.node_logic.safety_filter_interface import INTERFACE
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    described = _built(monkeypatch, ros_domain_id, SafetyFilterNode,  # refuses bands.stray
                       ['--params-file', UNICYCLE, '-p', 'k_c:=2.0', '-p', 'bands.stray:=1',
                        '-p', 'stray:=3'])
    for name in ('system', 'qos.depth', 'state_type', 'k_c', 'alpha', 'walls.nx'):
        spec = INTERFACE.spec(name)
        descriptor = described[name]
        assert (descriptor.description, descriptor.read_only, descriptor.dynamic_typing) == (
            spec.description, logic.is_read_only(name), True), name
    assert described['system'].read_only and not described['k_c'].read_only
    assert described['k_c'].floating_point_range[0].from_value == 0.0
    assert described['bands.stray'].description == logic.READ_ONLY_DESCRIPTION
    assert described['stray'].description == ''


@pytest.mark.parametrize('override, refusal', [
    ('qos.depth:=-5', 'qos.depth: -5 is outside its declared range 1 to 2147483647'),
    ('k_c:=-1.0', 'k_c: -1.0 is outside its declared range 0.0 to inf'),
])
def test_the_filter_node_refuses_an_override_outside_its_range_in_its_own_words(
        override, refusal, ros_domain_id):
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    rclpy.init(args=['node', '--ros-args', '-p', 'system:=unicycle', '-p', override],
               domain_id=ros_domain_id)
    try:
        with pytest.raises(ValueError) as refused:
            SafetyFilterNode()
        assert str(refused.value) == refusal
    finally:
        rclpy.try_shutdown()


_SOURCE = ['-p', 'observation_sources:=[front]', '-p', 'front.type:=scan',
           '-p', 'front.topic:=scan', '-p', 'footprint.radius:=0.2']


def test_every_key_of_a_source_is_declared_with_its_value_in_force(ros_domain_id):
    """A source key left out of the params file is declared too (read-only, described, with
    the default in force), so that ``ros2 param get`` shows it and a set is refused as
    read-only rather than as undeclared."""
    from rcbf_ros.core.config import SourceParameters
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    rclpy.init(args=['node', '--ros-args', '--params-file', UNICYCLE, *_SOURCE,
                     '-p', 'front.timeout_s:=2.0'], domain_id=ros_domain_id)
    try:
        node = SafetyFilterNode()
        defaults = SourceParameters()
        expected = {'type': 'scan', 'topic': 'scan', 'timeout_s': 2.0,
                    'min_height': defaults.min_height, 'max_height': defaults.max_height,
                    'voxel_size': defaults.voxel_size, 'best_effort': defaults.best_effort}
        for key, value in expected.items():
            name = f'front.{key}'
            assert node.get_parameter(name).value == value, name
            descriptor = node.describe_parameter(name)
            assert descriptor.read_only and descriptor.description, name
        from rcbf_ros.ros.runtime import Parameter
        result = node.set_parameters([Parameter('front.voxel_size', value=0.5)])[0]
        assert not result.successful and 'read-only' in result.reason
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize('args, words', [
    (['-p', 'front.topic:=cmd_safe'], "front.topic: 'cmd_safe' resolves to /cmd_safe"),
    (['-p', 'front.topic:=/diagnostics'], 'own diagnostics topic'),
    (['-r', '__ns:=/robot', '-p', 'front.topic:=/robot/state'], 'own state topic'),
    (['-r', 'lidar:=filter_info', '-p', 'front.topic:=lidar'], 'own filter_info topic'),
    (['-p', 'observation_sources:=[front,back]', '-p', 'back.type:=scan',
      '-p', 'back.topic:=/scan'], "back.topic: '/scan' resolves to /scan, the topic of "
                                  'front.topic too'),
    (['-p', 'front.topic:=rosout'], "front.topic: 'rosout' resolves to /rosout, the node's own "
                                    '/rosout topic'),
    (['-p', 'front.topic:=/tf_static'], "the node's own /tf_static topic"),
    (['-p', 'front.topic:=parameter_events'], "the node's own /parameter_events topic"),
    (['-p', 'front.topic:=/safety_filter/get_parameters'], 'own ~/get_parameters service'),
    (['-p', 'front.topic:=~/set_parameters_atomically'], 'own ~/set_parameters_atomically'),
    (['-p', 'state_type:=odometry', '-p', 'state_frame_id:=map'],
     "state_frame_id: 'map' is not odom_frame_id 'odom'"),
])
def test_the_filter_node_refuses_a_source_topic_that_clashes(args, words, ros_domain_id):
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    rclpy.init(args=['node', '--ros-args', '--params-file', UNICYCLE, *_SOURCE, *args],
               domain_id=ros_domain_id)
    try:
        with pytest.raises(ValueError) as refused:
            SafetyFilterNode()
        assert words in str(refused.value) and '\n' not in str(refused.value)
    finally:
        rclpy.try_shutdown()


def _timing_kind(name: str) -> str | None:
    """'rate' for a rate a timer runs at (``rate_hz``, ``*_rate_hz``, a replay ``rate``),
    'seconds' for a period, timeout, wait or step (``*_s``, ``dt``), else None."""
    leaf = name.rsplit('.', 1)[-1]
    if leaf.endswith('_hz') or leaf == 'rate':
        return 'rate'
    if leaf.endswith('_s') or leaf == 'dt':
        return 'seconds'
    return None


def test_every_rate_and_period_of_every_node_is_bounded_where_it_is_declared():
    """A rate or a period without both ends reaches a timer as an overflow (1 / 1e-300 s) or
    a node that never wakes: every one is declared inside the shared limits."""
    from rcbf_ros.cli.interface_doc import node_interfaces
    from rcbf_ros.node_logic.safety_filter import DURATION_LIMIT_S
    from rcbf_ros.parameters.reader import RATE_LIMITS_HZ
    seen, unbounded = [], []
    for interface in node_interfaces():
        for spec in interface.parameters:
            kind = _timing_kind(spec.name)
            if kind is None or spec.type != 'double':
                continue
            seen.append(f'{interface.node} {spec.name}')
            low, high = spec.range or (-math.inf, math.inf)
            limits = RATE_LIMITS_HZ if kind == 'rate' else (0.0, DURATION_LIMIT_S)
            if not limits[0] <= low <= high <= limits[1]:
                unbounded.append(f'{interface.node} {spec.name} {spec.range}')
    assert unbounded == []
    for expected in ('scene_markers rate_hz', 'unicycle_lidar scan_rate_hz',
                     'recorder flush_period_s', 'simulator action_timeout_s', 'replay rate',
                     'simulator dt', 'learner dt'):
        assert expected in seen


@pytest.mark.parametrize('cls, key', [
    ('rcbf_ros.node_logic.scene:SceneSettings', 'rate_hz'),
    ('sim_nodes.unicycle_lidar_node:LidarRobotSettings', 'scan_rate_hz'),
    ('sim_nodes.unicycle_lidar_node:LidarRobotSettings', 'rate_hz'),
    ('sim_nodes.simulator_node:SimulatorSettings', 'rate_hz'),
    ('sim_nodes.simulator_node:SimulatorSettings', 'action_timeout_s'),
    ('rcbf_ros.ros.recorder_node:RecorderConfig', 'flush_period_s'),
    ('rcbf_ros.ros.recorder_node:RecorderConfig', 'discovery_period_s'),
])
@pytest.mark.parametrize('value', [1e-300, 1e-10, 2e9, 1e308])
def test_a_rate_or_period_out_of_its_range_is_refused_naming_its_key(cls, key, value):
    import importlib

    from rcbf_ros.parameters.reader import ParameterError, read_parameters
    module, name = cls.split(':')
    settings = getattr(importlib.import_module(module), name)
    values = {'output': 'bag'} if name == 'RecorderConfig' else {}
    with pytest.raises(ParameterError, match=rf'^{key}: must be [<>]= '):
        read_parameters(settings, {**values, key: value})


@pytest.mark.parametrize('value', [0, 1023, 2 ** 62])
def test_a_recorder_chunk_size_out_of_its_range_is_refused_naming_it(value):
    from rcbf_ros.parameters.reader import ParameterError, read_parameters
    from rcbf_ros.ros.recorder_node import RecorderConfig
    with pytest.raises(ParameterError, match=r'^chunk_size: must be [<>]= '):
        read_parameters(RecorderConfig, {'output': 'bag', 'chunk_size': value})

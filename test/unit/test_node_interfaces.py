"""Every node's interface: ``--help`` / ``-h`` without starting anything, the parameter specs
against what the node really declares, and the README's tables against the generated ones."""
from __future__ import annotations

import enum
import importlib
from pathlib import Path
import subprocess
import sys
import types
from typing import Any, Callable
from unittest import mock

import pytest

from rcbf_ros.cli import interface_doc
from rcbf_ros.node_logic import safety_filter_interface
from rcbf_ros.node_logic.interface import help_text, NodeInterface, resolve, wants_help
from rcbf_ros.ros import node_main
from rcbf_ros.ros.dds.time_source import USE_SIM_TIME

REPO = Path(__file__).resolve().parents[2]
UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
MODULES = [module for module, _ in interface_doc.NODES]


def _console_scripts() -> dict[str, str]:
    """console script -> module of every node in setup.py (a script of node_main's: the node
    module its function hands to :func:`node_main.main_of`)."""
    text = (REPO / 'setup.py').read_text()
    scripts = {}
    for line in text.splitlines():
        line = line.strip().strip("',")
        if ' = ' in line and ':main' in line:
            name, target = line.split(' = ')
            scripts[name] = target.split(':')[0]
        elif ' = rcbf_ros.ros.node_main:' in line:
            name, target = line.split(' = ')
            scripts[name] = _node_module_of(getattr(node_main, target.split(':')[1]))
    return {name: module for name, module in scripts.items() if module in MODULES}


def _node_module_of(entry: Callable[..., int]) -> str:
    """The node module a console-script function of node_main runs."""
    seen: list[str] = []
    with mock.patch.object(node_main, 'main_of', lambda module, args=None: seen.append(module)):
        entry(['script'])
    return seen[0]


def test_every_node_console_script_has_an_interface():
    assert sorted(_console_scripts().values()) == sorted(MODULES)


def test_help_words_are_found_outside_ros_args_only():
    assert wants_help(['node', '--help']) and wants_help(['node', '-h'])
    assert wants_help(['node', '--ros-args', '-p', 'a:=1', '--', '-h'])
    assert not wants_help(['node', '--ros-args', '-p', 'a:=1'])
    assert not wants_help(['--help'])                       # argv[0] is the program
    assert not wants_help(['node', '--ros-args', '-r', '-h:=x'])


@pytest.fixture
def no_participant(monkeypatch):
    """Any attempt to join DDS fails the test."""
    from rcbf_ros.ros.dds import context

    def refuse(*_args: Any, **_kwargs: Any) -> None:
        raise AssertionError('a DDS participant was created')
    monkeypatch.setattr(context, '_create_participant', refuse)
    monkeypatch.setattr(context.Context, 'init', refuse)


@pytest.mark.parametrize('module', MODULES)
@pytest.mark.parametrize('flag', ['--help', '-h'])
def test_help_lists_every_parameter_and_starts_nothing(module, flag, no_participant, capsys):
    node = importlib.import_module(module)
    argv = [module.rsplit('.', 1)[-1], flag]
    assert node.main(argv) == 0
    out, err = capsys.readouterr()
    assert err == ''
    interface = resolve(getattr(node, dict(interface_doc.NODES)[module]), argv)
    assert out == help_text(interface)
    for spec in interface.parameters:
        assert f'\n  {spec.name}  ({spec.type}, default ' in out, spec.name
    for topic in interface.topics:
        assert f' {topic.name} ' in out, topic.name


MIDDLEWARE = ('rcbf_ros.ros.runtime', 'cyclonedds', 'rcbf_ros.ros.safety_filter_node')
"""Modules the filter's ``--help`` must not import (the node class and what it derives from)."""
SHOW_MIDDLEWARE = (f'import sys; print(sorted(m for m in {MIDDLEWARE!r} if m in sys.modules), '
                   'file=sys.stderr)')
"""Python that prints which of :data:`MIDDLEWARE` the process imported, on stderr."""


@pytest.mark.parametrize('launch', [
    ['-c', 'import sys; from rcbf_ros.ros.node_main import safety_filter; code = '
           f'safety_filter(); {SHOW_MIDDLEWARE}; sys.exit(code)'],  # the console script
    ['-c', 'import sys; from rcbf_ros.ros.node_main import run_module; code = '
           f'run_module(sys.argv[1:]); {SHOW_MIDDLEWARE}; sys.exit(code)',
     'rcbf_ros.ros.safety_filter_node'],  # python -m rcbf_ros.ros.node_main (the launcher)
], ids=['console_script', 'node_main_module'])
def test_help_of_the_filter_process_exits_0_without_the_middleware(launch):
    result = subprocess.run([sys.executable, *launch, '--help'],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert (result.returncode, result.stderr) == (0, '[]\n'), result.stderr
    assert result.stdout.startswith('usage: safety_filter ')
    assert '\n  state_type  (string, default array)\n' in result.stdout
    assert result.stdout == help_text(safety_filter_interface.INTERFACE)


@pytest.mark.parametrize('argv', [
    ['safety_filter', '--help'], ['safety_filter', '-h'],
    ['safety_filter', '--ros-args', '-p', 'system:=pvtol', '--', '--help'],
    ['safety_filter', '--ros-args', '--params-file', UNICYCLE, '--', '-h'],
])
def test_the_filter_help_without_the_node_is_the_node_modules_own(argv, no_participant,
                                                                    capsys):
    from rcbf_ros.ros import safety_filter_node
    assert safety_filter_node.INTERFACE is safety_filter_interface.INTERFACE
    assert safety_filter_node.main(argv) == 0
    own = capsys.readouterr()
    assert node_main.safety_filter(argv) == 0
    assert capsys.readouterr() == own


def test_main_of_runs_the_node_modules_main_unless_the_help_is_light(monkeypatch, capsys):
    calls: list[Any] = []
    for name in ('fake_light_node', 'fake_node'):
        module = types.ModuleType(name)
        module.main = lambda args=None, name=name: calls.append((name, args)) or 7
        monkeypatch.setitem(sys.modules, name, module)
    light = types.ModuleType('fake_light_interface')
    light.INTERFACE = safety_filter_interface.INTERFACE
    monkeypatch.setitem(sys.modules, 'fake_light_interface', light)
    monkeypatch.setitem(node_main.LIGHT_INTERFACES, 'fake_light_node', 'fake_light_interface')
    run = ['node', '--ros-args', '-r', '-h:=x']  # -h inside --ros-args: not a help request
    assert node_main.main_of('fake_light_node', run) == 7
    assert node_main.main_of('fake_node', ['node', '--help']) == 7  # its own help
    assert calls == [('fake_light_node', run), ('fake_node', ['node', '--help'])]
    assert capsys.readouterr().out == ''
    assert node_main.main_of('fake_light_node', ['node', '--help']) == 0
    assert capsys.readouterr().out == help_text(safety_filter_interface.INTERFACE)
    assert len(calls) == 2


# --- the specs are what the nodes declare -------------------------------------------------------

def _declared(monkeypatch, ros_domain_id: int, make: Callable[[], Any],
              args: list[str]) -> dict[str, Any]:
    """name -> default of every parameter a node declares while it is built (it may then
    refuse to start, e.g. without a policy file: the declarations are what counts)."""
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.dds.node import Node
    declared: dict[str, Any] = {}
    original = Node.declare_parameter

    def record(self: Any, name: str, value: Any = None, *rest: Any, **kwargs: Any) -> Any:
        declared[name] = value
        return original(self, name, value, *rest, **kwargs)
    monkeypatch.setattr(Node, 'declare_parameter', record)
    original_many = Node.declare_parameters

    def record_many(self: Any, namespace: str, parameters: Any, *rest: Any, **kwargs: Any) -> Any:
        # rclpy declares a node's overrides in one call (automatically_declare_...)
        for name, value, *_ in parameters:
            declared[f'{namespace}.{name}' if namespace else name] = value
        return original_many(self, namespace, parameters, *rest, **kwargs)
    monkeypatch.setattr(Node, 'declare_parameters', record_many)
    rclpy.init(args=['node', '--ros-args', *args], domain_id=ros_domain_id)
    node = None
    try:
        node = make()
    except (ValueError, OSError):
        pass
    finally:
        if node is not None:
            if hasattr(node, 'close'):
                node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return declared


def _cases(tmp_path: Path) -> list[tuple[str, Callable[[], Any], list[str]]]:
    from rcbf_ros.ros.learner_node import LearnerNode
    from rcbf_ros.ros.policy_node import PolicyNode
    from rcbf_ros.ros.recorder_node import RecorderNode
    from rcbf_ros.ros.replay_node import ReplayNode
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    from rcbf_ros.ros.scene_node import SceneNode
    from sim_nodes.nominal_controller_node import NominalControllerNode
    from sim_nodes.simulator_node import SimulatorNode
    return [
        ('rcbf_ros.ros.safety_filter_node', SafetyFilterNode,
         ['--params-file', UNICYCLE, '-r', '__node:=safety_filter']),
        ('sim_nodes.simulator_node', SimulatorNode, []),
        ('sim_nodes.nominal_controller_node', NominalControllerNode, []),
        ('rcbf_ros.ros.learner_node', LearnerNode, ['-p', f'out_dir:={tmp_path / "learner"}']),
        ('rcbf_ros.ros.policy_node', PolicyNode, []),
        ('rcbf_ros.ros.recorder_node', RecorderNode, ['-p', f'output:={tmp_path / "bag"}']),
        ('rcbf_ros.ros.replay_node', ReplayNode, []),
        ('rcbf_ros.ros.scene_node', SceneNode,
         ['--params-file', UNICYCLE, '-r', '__node:=scene_markers']),
    ]


def test_every_declared_parameter_has_its_spec_and_every_spec_is_declared(
        monkeypatch, ros_domain_id, tmp_path):
    for module, make, args in _cases(tmp_path):
        node = importlib.import_module(module)
        interface: NodeInterface = resolve(getattr(node, dict(interface_doc.NODES)[module]),
                                           [module])
        declared = _declared(monkeypatch, ros_domain_id, make, args)
        monkeypatch.undo()
        assert declared, module
        overridden = {word.split(':=')[0] for word in args if ':=' in word}
        for name, value in declared.items():
            if name == USE_SIM_TIME:  # every node's, declared by the runtime as rclpy does
                continue
            spec = interface.spec(name)
            assert spec is not None, f'{module}: {name} is declared but has no spec'
            if isinstance(value, enum.Enum):  # declared by type (Parameter.Type), no value
                continue
            if spec.default is not None and name not in overridden:
                assert value == spec.default, (module, name, value, spec.default)
        always = module == 'rcbf_ros.ros.safety_filter_node'  # declares its filter keys unset
        for spec in interface.parameters:
            if spec.pattern or (spec.default is None and not always):
                continue  # declared when given (a params file, -p)
            assert spec.name in declared, f'{module}: {spec.name} has a spec, is not declared'


# --- docs/INTERFACE.md ----------------------------------------------------------------------

def test_the_interface_doc_section_is_the_generated_one():
    assert interface_doc.main(['--check', str(REPO / interface_doc.INTERFACE_DOC)]) == 0, (
        f'run rcbf_ros interface-doc --write {interface_doc.INTERFACE_DOC}')


def test_the_readme_links_the_interface_doc_and_holds_no_copy():
    readme = (REPO / 'README.md').read_text()
    assert f']({interface_doc.INTERFACE_DOC})' in readme
    assert interface_doc.END not in readme and 'BEGIN interface' not in readme


def test_a_stale_readme_section_is_reported(tmp_path, capsys):
    readme = tmp_path / 'README.md'
    readme.write_text(f'intro\n{interface_doc.BEGIN}\nold table\n{interface_doc.END}\nrest\n')
    assert interface_doc.main(['--check', str(readme)]) == 1
    assert 'out of date' in capsys.readouterr().err
    assert interface_doc.main(['--write', str(readme)]) == 0
    assert interface_doc.main(['--check', str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith('intro\n') and text.endswith(f'{interface_doc.END}\nrest\n')

"""Parameters given to a node that it does not read are named in a WARN as it starts, with the
nearest name it reads; a params section of no node of the package is named too
(:mod:`rcbf_ros.parameters.unknown`, :func:`rcbf_ros.ros.node_main.unknown_parameters`)."""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from hypothesis import given
from hypothesis import strategies as st
import pytest

from rcbf_ros.cli.interface_doc import NODES
from rcbf_ros.node_logic.safety_filter_interface import INTERFACE as FILTER
from rcbf_ros.parameters.unknown import NODE_NAMES, unknown_parameter_lines
from rcbf_ros.ros.node_main import unknown_parameters, warn_unknown_parameters

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / 'config').glob('*.yaml'))


def _interface(module: str, name: str) -> Any:
    return getattr(importlib.import_module(module), name)


def _lines(node: str, tmp_path: Path, text: str | None = None, *extra: str,
           interface: Any = FILTER) -> list[str]:
    argv = ['node', '--ros-args']
    if text is not None:
        path = tmp_path / 'params.yaml'
        path.write_text(text)
        argv += ['--params-file', str(path)]
    return unknown_parameters(node, f'/{node}', [*argv, *extra], interface)


def test_the_package_names_every_node_it_documents():
    names = {_interface(module, name).node if not callable(_interface(module, name))
             else _interface(module, name)([module]).node for module, name in NODES}
    assert names == set(NODE_NAMES)


@pytest.mark.parametrize('config', CONFIGS, ids=lambda path: path.name)
def test_the_packaged_configs_give_no_node_an_unknown_parameter(config):
    for module, name in NODES:
        interface = _interface(module, name)
        argv = ['node', '--ros-args', '--params-file', str(config)]
        node = (interface if not callable(interface) else interface(argv)).node
        assert unknown_parameters(node, f'/{node}', argv, interface) == [], (config, node)


FILE = '/**:\n  ros__parameters:\n    system: unicycle\n{extra}'


@pytest.mark.parametrize('extra, shown', [
    ('    input_limit:\n      min: [-0.1]\n      max: [0.1]\n',
     "'input_limit.min' (did you mean 'input_limits.min'?), 'input_limit.max' (did you mean "
     "'input_limits.max'?)"),
    ('    control_period: 0.05\n    latency: 0.1\n',
     "'control_period' (did you mean 'control_period_s'?), 'latency' (did you mean "
     "'latency_s'?)"),
    ('    alpha: {x: 1}\n', "'alpha.x' ('alpha' takes a value, not a map)"),
    ('    zzzz_qqqq: 1\n', "'zzzz_qqqq'"),
])
def test_a_typo_is_named_with_the_name_meant(extra, shown, tmp_path):
    words = 'parameters' if shown.count(", '") else 'parameter'
    assert _lines('safety_filter', tmp_path, FILE.format(extra=extra)) == [
        f'unknown {words} ignored (this node reads no such key): {shown}']


def test_an_override_on_the_command_line_is_named_too(tmp_path):
    assert _lines('safety_filter', tmp_path, None, '-p', 'alpah:=3.0') == [
        "unknown parameter ignored (this node reads no such key): 'alpah' (did you mean "
        "'alpha'?)"]


def test_a_section_of_no_node_of_the_package_is_named_with_the_nearest(tmp_path):
    text = FILE.format(extra='') + '/safety_filer:\n  ros__parameters:\n    alpha: 1.0\n'
    assert _lines('safety_filter', tmp_path, text) == [
        "params section '/safety_filer' names no node of rcbf_ros (did you mean "
        "'/safety_filter'?); its keys reach no node"]
    other = FILE.format(extra='') + '/ns/simulator:\n  ros__parameters:\n    dt: 0.1\n'
    assert _lines('safety_filter', tmp_path, other) == []


def test_a_shared_key_passes_under_every_node_but_not_in_another_nodes_section(tmp_path):
    from sim_nodes.simulator_node import simulator_interface
    shared = FILE.format(extra='    k_c: 2.0\n')
    assert _lines('simulator', tmp_path, shared, interface=simulator_interface) == []
    own = '/simulator:\n  ros__parameters:\n    k_c: 2.0\n'
    assert _lines('simulator', tmp_path, own, interface=simulator_interface) == [
        "unknown parameter ignored (this node reads no such key): 'k_c'"]


KNOWN = [spec.name for spec in FILTER.parameters if not spec.pattern]


@given(st.lists(st.one_of(st.sampled_from(KNOWN),
                          st.from_regex(r'zq[a-z_]{0,8}(\.[a-z_]{1,6})?', fullmatch=True)),
                min_size=1, max_size=8))
def test_exactly_the_names_no_spec_takes_are_named(names):
    """Oracle: the filter's specs. Every name no spec takes appears in the line, no name a spec
    takes does."""
    lines = unknown_parameter_lines(
        sections={'/safety_filter': dict.fromkeys(names, 1)}, node_name='safety_filter',
        fully_qualified='/safety_filter', own=lambda n: FILTER.spec(n) is not None,
        shared=lambda n: False, own_names=KNOWN, shared_names=[])
    unknown = sorted({name for name in names if FILTER.spec(name) is None})
    assert bool(lines) == bool(unknown)
    for name in names:
        assert (f"'{name}'" in ''.join(lines)) == (name in unknown)


class _Logger:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warning(self, text: str) -> None:
        self.warnings.append(text)


class _Node:
    def __init__(self) -> None:
        self.logger = _Logger()

    def get_name(self) -> str:
        return 'safety_filter'

    def get_fully_qualified_name(self) -> str:
        return '/safety_filter'

    def get_logger(self) -> _Logger:
        return self.logger


def test_the_node_logs_each_line_as_a_warning_and_a_failure_never_stops_it():
    node = _Node()
    warn_unknown_parameters(node, ['n', '--ros-args', '-p', 'alpah:=3.0'], FILTER)
    assert len(node.logger.warnings) == 1 and "'alpah'" in node.logger.warnings[0]

    def broken(argv: Any) -> Any:
        raise RuntimeError('no interface')
    node = _Node()
    warn_unknown_parameters(node, ['n', '--ros-args', '-p', 'alpah:=3.0'], broken)
    assert node.logger.warnings == [
        'parameters given not checked against those read: RuntimeError: no interface']


def test_no_launch_gives_a_node_an_unknown_parameter():
    from rcbf_ros.launch.table import argument_values, LAUNCHES, resolve_entry, ros_arguments
    from rcbf_ros.parameters.rules import find_config
    attributes = dict(NODES)
    for name, setup in LAUNCHES.items():
        values = argument_values(setup, {})
        for entry in setup.nodes:
            entry = resolve_entry(entry, values)
            argv = ['node', *ros_arguments(entry, params_file=str(find_config(setup.config)))]
            interface = _interface(entry.module, attributes[entry.module])
            assert unknown_parameters(entry.name, f'/{entry.name}', argv, interface) == [], (
                name, entry.name)


def test_a_key_given_twice_is_reported_with_both_lines(tmp_path):
    lines = _lines('safety_filter', tmp_path,
                   '/**:\n  ros__parameters:\n    alpha: 2.0\n    alpha: 0.5\n')
    assert len(lines) == 1
    assert "line 4: the key 'alpha' is given twice in one mapping (lines 3 and 4" in lines[0]
    assert lines[0].endswith('(read as ROS 2 reads it: the later value of the same type)')


def test_a_signal_while_the_warnings_are_worked_out_still_closes_the_node():
    """The node is built before its unknown parameters are looked at: a Ctrl-C meanwhile stops
    it as one during the spin does (on_exit runs: a recorder closes its bag)."""
    from rcbf_ros.ros import node_main

    class Node:
        destroyed = False

        def destroy_node(self):
            self.destroyed = True

    class Rclpy:
        @staticmethod
        def try_shutdown():
            pass

    def interrupted(node):
        raise KeyboardInterrupt

    closed, node = [], Node()
    status = node_main._run('n', lambda: node, built=interrupted, run=lambda n: None,
                            on_exit=closed.append, setup_errors=(), setup_message='',
                            shutdown_errors=(), rclpy=Rclpy)
    assert status == 0 and closed == [node] and node.destroyed

"""Setting parameters on the Cyclone runtime follows rclpy 7.1's rules, without ROS installed.

The scenario is test/ros2/parameter_semantics.py (the ros2 tier runs it on real rclpy and
compares); here its steps are checked one by one against what rclpy's node.py does
(``set_parameters``, ``set_parameters_atomically``, ``_set_parameters_atomically_common``,
``_apply_descriptor``, ``list_parameters``, ``undeclare_parameter``), plus the calls the
scenario does not make.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest
from runtime_node import runtime_node

from rcbf_ros.messages.classes import get_message
from rcbf_ros.ros.dds.node import (
    DEPTH_RECURSIVE,
    Parameter,
    parameter_descriptor,
    ParameterNotDeclaredException,
)

SCRIPT = Path(__file__).resolve().parents[1] / 'ros2' / 'parameter_semantics.py'


def _scenario() -> Any:
    spec = importlib.util.spec_from_file_location('parameter_semantics', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope='module')
def steps() -> dict[str, dict[str, Any]]:
    """The scenario's steps by name (its node joins ROS_DOMAIN_ID, else domain 0)."""
    return {step['step']: step for step in _scenario().run('cyclone')}


@pytest.fixture
def node(ros_domain_id):
    with runtime_node('n', domain_id=ros_domain_id) as instance:
        yield instance


def test_set_parameters_runs_every_parameter_through_the_callbacks_on_its_own(steps):
    step = steps['set one by one']
    reasons = [reason for _, reason in step['outcome']]
    assert [ok for ok, _ in step['outcome']] == [
        True, False, False, False, True, True, False, False, True, False, False, True, True,
        False]
    assert reasons[1] == 'b: must be >= 0'  # the callback's reason
    assert reasons[2].startswith('The parameter value for a is not a valid step.')
    assert reasons[3] == 'Parameter a out of range. Min: 0, Max: 10, value: 12'
    assert reasons[7] == 'Parameter b out of range Min: -2.0, Max: 1.0, value: -3.0'
    assert reasons[9] == 'Trying to set a read-only parameter: ro.'
    assert reasons[10] == "Wrong parameter type, expected 'Type.INTEGER' got 'Type.STRING'"
    assert reasons[13] == 'Static parameter cannot be undeclared'
    # newest on-set callback first; post-set only after a success; descriptors before both
    assert step['calls'][:5] == ['on_record:a', 'on_b:a', 'post:a', 'on_record:b', 'on_b:b']
    assert step['values']['a'] == 10 and step['values']['b'] == 1.0000001  # edges are in
    assert 'dyn' not in step['values']  # NOT_SET undeclared the dynamically typed one


def test_set_parameters_atomically_is_all_or_nothing(steps):
    refused = steps['atomic refused by a callback']
    assert refused['outcome'] == [False, 'b: must be >= 0']
    assert refused['calls'] == ['on_record:a,b', 'on_b:a,b']
    assert refused['values']['a'] == 10
    assert steps['atomic refused by a descriptor']['calls'] == []
    accepted = steps['atomic accepted']
    assert accepted['outcome'] == [True, '']  # the callback's reason is dropped on success
    assert accepted['calls'] == ['on_record:a,b', 'on_b:a,b', 'post:a,b']
    assert (accepted['values']['a'], accepted['values']['b']) == (6, 1.0)
    # rclpy 7.1.1 names the undeclared parameters after the first one only
    assert steps['atomic with undeclared']['outcome'] == {
        'raises': 'ParameterNotDeclaredException',
        'message': 'Invalid access to undeclared parameter(s): []'}
    assert steps['atomic with undeclared']['values']['a'] == 8
    assert steps['atomic with three undeclared']['outcome'] == {
        'raises': 'ParameterNotDeclaredException',
        'message': "Invalid access to undeclared parameter(s): ['nope2', 'nope3']"}


def test_an_undeclared_name_stops_set_parameters_after_the_ones_before(steps):
    step = steps['set undeclared']
    assert step['outcome'] == {'raises': 'ParameterNotDeclaredException',
                               'message': 'Invalid access to undeclared parameter(s): []'}
    assert step['values']['a'] == 8 and step['calls'] == ['on_record:a', 'on_b:a', 'post:a']
    assert steps['set not a Parameter']['outcome'] == {'raises': 'TypeError'}


def test_declarations_go_through_the_on_set_and_post_set_callbacks(steps):
    assert steps['declare with callbacks']['calls'] == ['on_record:c', 'on_b:c', 'post:c']
    refused = steps['declare refused by a callback']
    assert refused['outcome'] == {'raises': 'InvalidParameterValueException'}
    assert 'b2' not in refused['values']
    many = steps['declare many, one refused']
    assert many['values']['d1'] == 1 and 'b3' not in many['values'] and 'd2' not in many['values']
    assert steps['declare one declared before']['outcome'] == {
        'raises': 'ParameterAlreadyDeclaredException'}
    assert 'd3' not in steps['declare one declared before']['values']


def test_pre_set_callbacks_replace_the_list(steps):
    step = steps['set through pre-set callbacks']
    assert step['calls'] == ['pre_add:a', 'pre_double:a', 'on_record:c,a', 'on_b:c,a', 'post:c,a']
    assert step['values']['a'] == 4 and step['values']['c'] == 9.5
    empty = steps['pre-set callbacks return nothing']
    assert empty['outcome'][0][0] is False
    assert empty['outcome'][0][1].startswith('parameter list cannot be empty')


def test_removing_callbacks(steps):
    assert steps['remove a callback twice']['outcome'] == {'raises': 'ValueError'}
    assert steps['remove on-set callback twice']['outcome'] == {'raises': 'ValueError'}
    assert steps['set once the refusing callback is gone']['calls'] == ['on_record:b', 'post:b']
    assert steps['undeclare read-only']['outcome'] == {'raises': 'ParameterImmutableException'}
    assert 'c' not in steps['undeclare']['values']
    assert steps['undeclare undeclared']['outcome'] == {
        'raises': 'ParameterNotDeclaredException',
        'message': 'Invalid access to undeclared parameter(s): c'}


def test_every_declaration_and_set_is_announced_as_rclpy_announces_it(steps):
    """One ParameterEvent per successful declaration or set, from the node itself (not only
    through the parameter services): new when the parameter had no value, changed when it had,
    deleted when a NOT_SET value undeclared it; none for a refused set or an undeclare."""
    def names(step: str, kind: str) -> list[list[str]]:
        return [[entry[0] for entry in event[kind]] for event in steps[step]['events']]
    first = steps['declare the first parameters']['events']
    assert [event['new'][0][0] for event in first] == ['a', 'b', 'ro', 'dyn', 'x.y.z', 'x.w',
                                                       'unset']
    assert first[-1]['new'] == [['unset', 0, None]]  # declared without a value: NOT_SET
    assert {event['node'] for event in first} == {'/parameter_semantics'}
    # the six accepted sets of the fourteen, in order; the last undeclared `dyn`
    assert names('set one by one', 'changed') == [['a'], ['a'], ['b'], ['b'], ['dyn'], []]
    assert names('set one by one', 'deleted') == [[], [], [], [], [], ['dyn']]
    assert steps['atomic refused by a callback']['events'] == []
    assert names('atomic accepted', 'changed') == [['a', 'b']]
    assert names('declare many, one refused', 'new') == [['d1']]
    assert steps['undeclare']['events'] == []


def test_list_parameters_by_prefix_and_depth(steps):
    def listed(key: str) -> tuple[list[str], list[str]]:
        outcome = steps[key]['outcome']
        return outcome['names'], outcome['prefixes']
    assert listed('list [] 1') == (['a', 'b', 'ro', 'unset', 'd1'], [])
    assert listed('list [] 2') == (['a', 'b', 'ro', 'x.w', 'unset', 'd1'], ['x'])
    assert listed("list ['x'] 1") == (['x.w'], ['x'])
    assert listed("list ['x'] 0") == (['x.y.z', 'x.w', 'x.y.q', 'x.v.q.r'],
                                      ['x.y', 'x', 'x.v.q'])
    assert listed("list ['x.y'] 1") == (['x.y.z', 'x.y.q'], ['x.y'])
    assert listed("list ['a'] 0") == (['a'], [])
    assert steps['list negative depth']['outcome'] == {'raises': 'ValueError'}
    assert steps['list prefixes not a list']['outcome'] == {'raises': 'TypeError'}


def test_list_parameters_returns_the_rcl_interfaces_message(node):
    node.declare_parameter('p.q', 1)
    result = node.list_parameters([], DEPTH_RECURSIVE)
    assert type(result) is get_message('rcl_interfaces/msg/ListParametersResult')
    assert list(result.names) == ['use_sim_time', 'p.q']  # use_sim_time: every node's, as rclpy
    assert list(result.prefixes) == ['p']


def test_the_same_list_object_reaches_the_on_set_and_post_set_callbacks(node):
    node.declare_parameter('k', 1.0)
    seen: list[Any] = []
    node.add_on_set_parameters_callback(
        lambda ps: seen.append(ps) or get_message('rcl_interfaces/msg/SetParametersResult')(
            successful=True))
    node.add_post_set_parameters_callback(seen.append)
    node.set_parameters_atomically([Parameter('k', value=2.0)])
    assert len(seen) == 2 and seen[0] is seen[1]


def test_allowed_undeclared_parameters_are_set_dynamically_typed(ros_domain_id):
    with runtime_node('u', domain_id=ros_domain_id, allow_undeclared_parameters=True) as node:
        assert node.set_parameters([Parameter('free', value=1)])[0].successful
        assert node.set_parameters([Parameter('free', value='text')])[0].successful
        assert node.describe_parameter('free').dynamic_typing


def test_a_read_only_parameter_is_declared_with_its_override_and_never_set(ros_domain_id):
    with runtime_node('r', domain_id=ros_domain_id,
                      args=['--ros-args', '-p', 'ro:=5']) as node:
        node.declare_parameter('ro', 1, parameter_descriptor(read_only=True))
        assert node.get_parameter('ro').value == 5
        result = node.set_parameters([Parameter('ro', value=6)])[0]
        assert not result.successful and 'read-only' in result.reason
        with pytest.raises(ParameterNotDeclaredException):
            node.set_parameters_atomically([Parameter('missing', value=1)])

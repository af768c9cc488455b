"""The safety_filter node's parameters and obstacles change at runtime, whole or not at all.

One process, no peers: the node's callbacks are called directly (as in
test_safety_filter_callbacks.py) and its parameters set through rclpy's calls. A change builds a
complete new filter with the start's validation; a refused one (the reason names the key)
leaves the filter object and every parameter as they were; an accepted one swaps the filter
once, after the parameters are stored. The ``obstacles`` topic goes through the same path.
"""
from __future__ import annotations

import math
from typing import Any

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_safety_filter_callbacks import _cdr, EVERY_DIAGNOSTIC, FilterHarness, UNICYCLE

from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.node_logic import safety_filter as filter_logic
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Parameter

STATE = [-0.85, 0.0, 0.0]  # facing the obstacle at the origin, 0.25 m from its edge


@pytest.fixture
def harness(ros_domain_id):
    rclpy.init(args=['--ros-args', '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC],
               domain_id=ros_domain_id)
    instance = FilterHarness()
    yield instance
    instance.node.destroy_node()
    rclpy.try_shutdown()


def _obstacles(values: list[float], dims: list[tuple[str, int, int]] = ()) -> bytes:
    msg = get_message('std_msgs/msg/Float64MultiArray')(data=values)
    dim_type = get_message('std_msgs/msg/MultiArrayDimension')
    msg.layout.dim = [dim_type(label=label, size=size, stride=stride)
                      for label, size, stride in dims]
    return serialize_message(msg)


def _constraints(values: dict[str, str]) -> np.ndarray:
    return np.array([float(v) for k, v in sorted(values.items())
                     if k.startswith('constraint.')])


def test_a_valid_gain_is_applied_and_the_rows_follow_it(harness, capsys):
    node = harness.node
    node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))
    _, (level, _, before) = harness.propose(_cdr({'u': [0.1, 0.0]}))
    result = node.set_parameters([Parameter('k_c', value=0.0)])[0]
    assert result.successful and result.reason == ''
    assert node.config.problem.k_c == 0.0 and node.get_parameter('k_c').value == 0.0
    _, (level, _, after) = harness.propose(_cdr({'u': [0.1, 0.0]}))
    assert level == filter_logic.OK
    # the robust margin k_c |dh/dx| std is gone from every obstacle row
    assert np.all(_constraints(after) > _constraints(before))
    log = capsys.readouterr().err
    assert '[INFO]' in log and 'filter updated: k_c: 2.0 -> 0.0' in log


def test_an_invalid_value_is_refused_with_the_key_and_nothing_changes(harness, capsys):
    node = harness.node
    old_filter, old_k_c = node.filter, node.get_parameter('k_c').value
    result = node.set_parameters([Parameter('k_c', value=-1.0)])[0]
    assert not result.successful
    # the declared range refuses it before any callback runs, in rclpy's words
    assert result.reason == 'Parameter k_c out of range Min: 0.0, Max: inf, value: -1.0'
    assert node.filter is old_filter and node.get_parameter('k_c').value == old_k_c
    assert ('[WARN]' in (log := capsys.readouterr().err) and 'parameter change refused: k_c: '
            '-1.0 is outside its declared range 0.0 to inf' in log), log
    for name, value in (('alpha', 0.0), ('obstacles.margin', -0.1), ('slack_tolerance', -1.0),
                        ('input_bounds.state', math.nan), ('osqp.max_iter', 0),
                        ('obstacles.radius', [0.6, -0.6, 0.6, 0.6, 0.6]),
                        # values beyond what float64, OSQP or the clock take, or whose rows
                        # overflow: each would kill the node or make every answer the fail-safe
                        ('obstacles.margin', 1e308), ('log_throttle_s', 1e308),
                        ('osqp.max_iter', 2 ** 63 - 1), ('alpha', 1e300), ('k_c', 1e300),
                        ('diagnostics.min_period_s', 1e308), ('obstacles.heading_index', 0),
                        ('obstacles.x', [1e200, -1.5, -1.5, 1.5, 1.5]),
                        ('obstacles.radius', [1e154] * 5), ('slack_weight', 1e308),
                        # values that would publish commands breaking the rows as OK answers,
                        # or put every ordinary proposal out of bounds
                        ('slack_tolerance', 1.0), ('obstacles.lookahead', 10.0),
                        ('input_bounds.command', 0.5), ('input_limits.max', [1e308, 2.5])):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        # the key itself leads, or the key it contradicts names it (input_limits.min: ...
        # lies beyond input_bounds.command = 0.5)
        assert not result.successful and (result.reason.startswith(
            (f'{name}:', f'Parameter {name} out of range')) or f' {name} = ' in result.reason
        ), (name, result.reason)
        assert node.filter is old_filter


def test_the_parameters_fixed_at_start_are_read_only(harness, capsys):
    node = harness.node
    for name, value in (('system', 'pvtol'), ('command_type', 'twist'), ('qos.depth', 1),
                        ('state_type', 'odometry'), ('twist_fields', ['linear.x'])):
        assert node.describe_parameter(name).read_only, name
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful
        assert result.reason == f'Trying to set a read-only parameter: {name}.'
        warning = capsys.readouterr().err
        assert '[WARN]' in warning and f'refused: {name} is read-only' in warning
    assert node.get_parameter('system').value == 'unicycle'  # the override kept its value
    assert not node.describe_parameter('k_c').read_only


def test_several_keys_set_atomically_are_one_swap(harness, capsys):
    node = harness.node
    swaps = []
    node.add_post_set_parameters_callback(lambda ps: swaps.append(node.filter))
    old_filter = node.filter
    # one by one, the second obstacle list would not match the first: refused
    result = node.set_parameters([Parameter('obstacles.x', value=[3.0])])[0]
    assert not result.successful and result.reason.startswith('obstacles.y')
    result = node.set_parameters_atomically([
        Parameter('obstacles.x', value=[3.0]), Parameter('obstacles.y', value=[0.0]),
        Parameter('obstacles.radius', value=[0.5]), Parameter('alpha', value=1.0)])
    assert result.successful
    # one post-set call for the four keys; a newer post-set callback runs before the node's
    assert len(swaps) == 1 and swaps[0] is old_filter and node.filter is not old_filter
    assert node.filter.barrier_names == ['obstacle_0']
    assert node.config.problem.alpha == 1.0
    assert capsys.readouterr().err.count('filter updated') == 1


def test_a_parameter_the_filter_does_not_read_changes_nothing(harness):
    node = harness.node
    node.declare_parameter('some_other_node_key', 1)
    old_filter = node.filter
    assert node.set_parameters([Parameter('some_other_node_key', value=2)])[0].successful
    assert node.filter is old_filter


def test_node_settings_change_too(harness):
    node = harness.node
    assert node.set_parameters([Parameter('diagnostics.name', value='front_filter'),
                                Parameter('log_throttle_s', value=5.0)])[1].successful
    assert node.settings.diagnostics_name == 'front_filter'
    assert node._throttle.period_ns == 5 * 10**9
    node._on_state(_cdr({'state': STATE}))
    harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert node._diag_pub  # published with the new name
    assert harness.diagnostics[-1][0] == filter_logic.OK


def test_an_obstacles_message_moves_the_obstacles(harness, capsys):
    node = harness.node
    node._on_state(_cdr({'state': STATE}))
    u, (_, message, _) = harness.propose(_cdr({'u': [2.5, 0.0]}))
    assert u[0] < 2.5  # braking for the obstacle at the origin
    node._on_obstacles(_obstacles([5.0, 5.0, 0.5, -5.0, 5.0, 0.5], [('obstacles', 2, 6),
                                                                    ('xyr', 3, 3)]))
    assert node.get_parameter('obstacles.x').value == [5.0, -5.0]
    assert node.get_parameter('obstacles.radius').value == [0.5, 0.5]
    assert node.filter.barrier_names == ['obstacle_0', 'obstacle_1']
    u, _ = harness.propose(_cdr({'u': [2.5, 0.0]}))
    np.testing.assert_allclose(u, [2.5, 0.0])  # nothing in the way any more
    node._on_obstacles(_obstacles([-0.1, 0.0, 0.6]))  # right ahead of the robot
    u, _ = harness.propose(_cdr({'u': [2.5, 0.0]}))
    assert u[0] < 2.5
    log = capsys.readouterr().err
    assert 'filter updated from the obstacles topic: obstacles.radius' in log


@pytest.mark.parametrize('values, dims, field', [
    ([1.0, 2.0, 0.5, 3.0], [], 'data'),
    ([1.0, 2.0, -0.5], [], 'obstacles.radius'),
    ([1.0, math.nan, 0.5], [], 'obstacles.y'),
    ([1.0, 2.0, 0.5], [('obstacles', 3, 3), ('xyr', 1, 1)], 'layout.dim'),
    ([], [], 'barriers'),
])
def test_a_bad_obstacles_message_is_refused_and_the_old_obstacles_stay(
        harness, capsys, values, dims, field):
    node = harness.node
    old_filter, old_x = node.filter, node.get_parameter('obstacles.x').value
    node._on_obstacles(_obstacles(values, dims))
    assert node.filter is old_filter and node.get_parameter('obstacles.x').value == old_x
    error = [line for line in capsys.readouterr().err.splitlines() if '[ERROR]' in line]
    assert len(error) == 1 and 'obstacles message refused' in error[0] and field in error[0]


def test_an_undecodable_obstacles_message_is_refused(harness, capsys):
    node = harness.node
    old_filter = node.filter
    node._on_obstacles(_obstacles([1.0, 2.0, 0.5])[:10])
    assert node.filter is old_filter
    assert 'obstacles message refused, the obstacles are unchanged: undecodable sample' in \
        capsys.readouterr().err


# Any sequence of parameter sets leaves the node with the filter of an accepted parameter set.
_VALUES = {
    'k_c': st.sampled_from([0.0, 1.0, 2.5, -1.0, math.nan]),
    'alpha': st.sampled_from([0.5, 2.0, 0.0, -3.0]),
    'obstacles.margin': st.sampled_from([0.0, 0.2, -0.1]),
    'slack_tolerance': st.sampled_from([1e-4, 1e-3, -1.0]),
    'obstacles.x': st.sampled_from([[0.0, -1.5, -1.5, 1.5, 1.5], [0.5, 0.0, 0.0, 0.0, 0.0],
                                    [1.0]]),
}
_SETS = st.lists(st.tuples(
    st.booleans(),
    st.lists(st.sampled_from(sorted(_VALUES)), min_size=1, max_size=3, unique=True).flatmap(
        lambda keys: st.tuples(*[st.tuples(st.just(k), _VALUES[k]) for k in keys]))),
    min_size=1, max_size=6)


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(operations=_SETS)
def test_any_sequence_of_sets_leaves_a_filter_of_accepted_parameters(harness, operations):
    node = harness.node
    model = dict(node._active.params)

    def accepted(changes: dict[str, Any]) -> bool:
        nonlocal model
        candidate = filter_logic.merged_parameters(current=model, changes=changes)
        try:
            filter_logic.build_active_filter(params=candidate)
        except ValueError:
            return False
        model = candidate
        return True

    for atomically, items in operations:
        parameters = [Parameter(name, value=value) for name, value in items]
        if atomically:
            result = node.set_parameters_atomically(parameters)
            assert result.successful == accepted(dict(items))
        else:
            for parameter, result in zip(parameters, node.set_parameters(parameters)):
                assert result.successful == accepted({parameter.name: parameter.value})
        assert node._active.params == model
        assert node._parameter_values() == model
    fresh = filter_logic.build_active_filter(params=model).safety_filter
    for state in ([-0.85, 0.0, 0.0], [1.0, -0.7, 2.0]):
        ours = node.filter.filter(np.array(state), np.array([2.5, 0.3]))
        theirs = fresh.filter(np.array(state), np.array([2.5, 0.3]))
        np.testing.assert_allclose(ours.u_safe, theirs.u_safe, atol=1e-6)  # warm starts

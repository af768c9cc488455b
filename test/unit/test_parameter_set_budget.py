"""The executor time the safety filter's parameter sets may take.

Each set of a filter key builds a whole filter on the node's one executor thread (5 ms; 175 ms
with 20,000 obstacles): a set_parameters request of 100 entries alternating one gain held the
answers back for half a second, one of 10,000 entries for about a minute. The builds are now
charged to a budget (rcbf_ros.node_logic.time_budget), and a set that comes while it is spent
is refused, saying so, with the filter and the parameter unchanged. The clock is the test's
own: no test is timed.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from rcbf_ros.ros import safety_filter_node
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.parameter_service import parameter_msg
from rcbf_ros.ros.dds.services import get_service
from rcbf_ros.ros.runtime import Parameter

REPO = Path(__file__).resolve().parents[2]
MS = 1_000_000
SET = get_service('rcl_interfaces/srv/SetParameters')


class FakeClock:
    def __init__(self) -> None:
        self.ns = 10**12

    def __call__(self) -> int:
        return self.ns


@pytest.fixture
def node(ros_domain_id: int):
    rclpy.init(args=['--ros-args', '--params-file', str(REPO / 'config' / 'unicycle.yaml')],
               domain_id=ros_domain_id)
    instance = safety_filter_node.SafetyFilterNode()
    yield instance
    instance.destroy_node()
    rclpy.try_shutdown()


def test_a_request_of_many_sets_builds_within_the_share_and_refuses_the_rest(node) -> None:
    """100 entries each changing alpha, each build taking 100 ms: the builds stop once the burst
    is spent, every later entry is refused naming the key and the budget (one WARN for all),
    the filter in force is the one of the last entry built, and once the budget has filled
    again a set is built."""
    clock = FakeClock()
    node._build_budget.clock = node._build_budget.work_clock = clock
    built: list[float] = []
    build = node._build

    def slow_build(params, *args, **kwargs):
        built.append(params['alpha'])
        clock.ns += 100 * MS
        return build(params, *args, **kwargs)
    node._build = slow_build
    warnings: list[str] = []
    node.get_logger().warning = warnings.append
    values = [3.0 + 0.01 * k for k in range(100)]  # each one a change
    request = SET.Request(parameters=[parameter_msg(Parameter('alpha', value=v))
                                      for v in values])
    results = node._parameter_service._set_parameters(request, SET.Response()).results
    burst = safety_filter_node.BUILD_TIME_BURST_S
    assert 1 <= len(built) <= burst / 0.1 + 1
    assert [r.successful for r in results] == [True] * len(built) + [False] * (100 - len(built))
    assert all(r.reason.startswith('alpha: not set') for r in results[len(built):])
    assert node.get_parameter('alpha').value == values[len(built) - 1]
    assert node.config.problem is not None and node._active.params['alpha'] == values[
        len(built) - 1]
    assert sum('not set' in w for w in warnings) == 1, warnings
    clock.ns += int((burst + 0.1) / safety_filter_node.BUILD_TIME_SHARE * 1e9) + 1
    assert node.set_parameters([Parameter('alpha', value=5.0)])[0].successful
    assert built[-1] == 5.0 and node._active.params['alpha'] == 5.0


def test_a_set_that_changes_nothing_costs_no_budget(node) -> None:
    """Setting the values in force builds nothing (a params file loaded again)."""
    clock = FakeClock()
    node._build_budget.clock = node._build_budget.work_clock = clock
    alpha = node.get_parameter('alpha').value
    node._build_budget.admit()
    node._build_budget.charge(clock.ns - 10**9)  # spent: in debt by most of a second
    assert all(r.successful for r in node.set_parameters([Parameter('alpha', value=alpha)]))
    assert not node.set_parameters([Parameter('alpha', value=alpha + 1.0)])[0].successful


def test_an_obstacles_message_built_on_the_executor_is_never_refused_for_the_budget(node):
    """An obstacles message's set, built again on the executor because the parameters changed
    while its worker built it, is paced by the worker: taken with the budget spent."""
    clock = FakeClock()
    node._build_budget.clock = node._build_budget.work_clock = clock
    node._build_budget.admit()
    node._build_budget.charge(clock.ns - 10**9)
    assert not node.set_parameters([Parameter('alpha', value=7.0)])[0].successful
    node._change_source = 'obstacles'
    try:
        result = node.set_parameters_atomically([
            Parameter('obstacles.x', value=[1.0]), Parameter('obstacles.y', value=[2.0]),
            Parameter('obstacles.radius', value=[0.3])])
    finally:
        node._change_source = ''
    assert result.successful, result.reason
    assert node._active.params['obstacles.x'] == [1.0]

"""The ``obstacles`` subscription's filter is built in the worker thread, swapped in on the
executor: until the executor takes the build, the filter in force answers; of several quick
messages the newest ends in force; a parameter set between the build and the swap is kept
(the set is built again over it); answers more than ``control_period_s`` apart are counted and
said. One process, no peers; the executor is ``spin_once`` on the node."""
from __future__ import annotations

import numpy as np
from test_safety_filter_callbacks import _cdr
from test_safety_filter_runtime_changes import _obstacles, harness  # noqa: F401

from rcbf_ros.messages.conversions import msg_to_sections
from rcbf_ros.node_logic import safety_filter as filter_logic
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Parameter
from rcbf_ros.ros.safety_filter_node import LATE_ANSWERS

WAIT_S = 60.0
FAR = [-3.0, 0.0, 0.0]


def _rows(count: int, x0: float = 5.0) -> list[float]:
    """``count`` circles of radius 0.2 in a row from x = ``x0``, far from the robot."""
    return np.column_stack([x0 + np.arange(count), np.full(count, 8.0),
                            np.full(count, 0.2)]).ravel().tolist()


def _barriers_answered(filter_harness) -> int:
    """How many barrier values the latest answer's ``filter_info`` carries."""
    return len(msg_to_sections(filter_harness.infos[-1])['h'])


def _swap_in(node, old) -> None:
    """Run the executor until the filter in force is no longer ``old``."""
    assert node._obstacle_builds.wait_idle(WAIT_S)
    for _ in range(200):
        if node.filter is not old:
            return
        rclpy.spin_once(node, timeout_sec=0.05)
    raise AssertionError('the built filter was never swapped in')


def test_the_filter_in_force_answers_until_the_executor_swaps_the_build_in(harness):  # noqa: F811
    node = harness.node
    old = node.filter
    node._take_obstacles(_obstacles(_rows(300)))
    assert node._obstacle_builds.wait_idle(WAIT_S)   # built, not yet taken by the executor
    assert node.filter is old and len(node.get_parameter('obstacles.x').value) == 5
    node._on_state(_cdr({'state': FAR}))
    harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert _barriers_answered(harness) == 5          # answered by the filter in force
    _swap_in(node, old)
    assert node.filter.barrier_names[-1] == 'obstacle_299'
    assert node.get_parameter('obstacles.x').value == _rows(300)[0::3]
    harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert _barriers_answered(harness) == 300


def test_of_several_quick_messages_the_newest_ends_in_force(harness):  # noqa: F811
    node = harness.node
    old = node.filter
    for count in (400, 300, 200, 7):
        node._take_obstacles(_obstacles(_rows(count)))
    _swap_in(node, old)
    for _ in range(20):   # a build of an older message may be swapped in first
        if len(node.filter.barrier_names) == 7:
            break
        assert node._obstacle_builds.wait_idle(WAIT_S)
        rclpy.spin_once(node, timeout_sec=0.05)
    assert node.get_parameter('obstacles.x').value == _rows(7)[0::3]
    assert len(node.filter.barrier_names) == 7
    assert node._obstacle_builds.take() == [] and not node._obstacle_builds.busy


def test_a_parameter_set_during_the_build_is_kept(harness):  # noqa: F811
    node = harness.node
    old = node.filter
    node._take_obstacles(_obstacles(_rows(100)))
    assert node._obstacle_builds.wait_idle(WAIT_S)   # built over k_c as it was
    assert node.set_parameters([Parameter('k_c', value=0.0)])[0].successful
    changed = node.filter
    assert changed is not old and changed.problem.k_c == 0.0
    _swap_in(node, changed)
    assert node.config.problem.k_c == 0.0 and node.get_parameter('k_c').value == 0.0
    assert len(node.filter.barrier_names) == 100


def test_a_refused_message_leaves_the_filter_and_says_why(harness, capsys):  # noqa: F811
    node = harness.node
    old = node.filter
    node._take_obstacles(_obstacles([1.0, 2.0, -0.5]))
    assert node._obstacle_builds.wait_idle(WAIT_S)
    for _ in range(5):
        rclpy.spin_once(node, timeout_sec=0.05)
    assert node.filter is old
    errors = [line for line in capsys.readouterr().err.splitlines() if '[ERROR]' in line]
    assert len(errors) == 1 and 'obstacles message refused' in errors[0]
    assert 'obstacles.radius' in errors[0]


def test_an_answer_later_than_the_period_is_counted_and_said(harness, capsys):  # noqa: F811
    node = harness.node
    assert node.set_parameters([Parameter('control_period_s', value=0.05)])[0].successful
    node._on_state(_cdr({'state': FAR}))
    harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert node.late_answers == 0
    node._last_published_ns -= 200_000_000       # the previous answer 0.2 s ago, as if blocked
    node._on_state(_cdr({'state': FAR}))
    harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert node.late_answers == 1
    assert harness.diagnostics[-1][2][LATE_ANSWERS] == '1'
    warnings = [line for line in capsys.readouterr().err.splitlines() if 'late answer' in line]
    assert len(warnings) == 1 and 'over control_period_s = 0.05' in warnings[0]


def test_overrun_only_past_the_period():
    assert filter_logic.answer_overrun_s(control_period_s=0.0, previous_ns=0,
                                         now_ns=10**10) is None
    assert filter_logic.answer_overrun_s(control_period_s=0.05, previous_ns=None,
                                         now_ns=10**10) is None
    assert filter_logic.answer_overrun_s(control_period_s=0.05, previous_ns=0,
                                         now_ns=50_000_000) is None
    assert abs(filter_logic.answer_overrun_s(control_period_s=0.05, previous_ns=0,
                                             now_ns=80_000_000) - 0.03) < 1e-12

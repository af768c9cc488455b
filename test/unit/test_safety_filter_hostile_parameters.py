"""No parameter value, obstacles message or params file kills the safety filter or switches it off.

Hypothesis draws sets over every declared parameter with extreme values (+-1e308, subnormals,
NaN, +-inf, the int64 ends, 2^31, long lists, long strings, wrong types), one at a time and
atomically, and ``obstacles`` messages of any size and value. After each one the node must
still answer, the set must have been applied whole or refused whole (a refusal is one line),
the stored parameters must be those of the filter in force, every answer must keep the
invariant (the rows hold at the command within the slack tolerance in force, or the fail-safe
with a reason), and a filter that accepted a change must still be able to evaluate its rows at
the robot's state (no ``input_refused`` at an ordinary proposal). Params files at start: one
line and exit status 2, or a filter that runs.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
import subprocess
import sys
from typing import Any

from hypothesis import example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_safety_filter_callbacks import _cdr, EVERY_DIAGNOSTIC, FilterHarness, UNICYCLE
from test_safety_invariant import row_values
import yaml

from rcbf_ros.core.config import OBSTACLE_LIMIT
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Parameter
from rcbf_ros.ros.dds.parameters import ParameterNotDeclaredException

STATE = [-0.85, 0.0, 0.0]  # facing the obstacle at the origin, 0.25 m from its edge
PROPOSAL = [1.0, 0.2]

HOSTILE_NUMBERS = (1e308, -1e308, 5e-324, -5e-324, 0.0, -0.0, math.nan, math.inf, -math.inf,
                   1e154, 1e200, -1e-300, 1e15, 1e16, 0.5, 2.0, 2 ** 63 - 1, -2 ** 63, 2 ** 31,
                   2 ** 31 - 1, -1, 0, 1, 2, 3, 7)
"""Values at and beyond every edge a key may have, of both numeric types."""

_floats = st.one_of(st.sampled_from([v for v in HOSTILE_NUMBERS if isinstance(v, float)]),
                    st.floats(allow_nan=True, allow_infinity=True))
_ints = st.one_of(st.sampled_from([v for v in HOSTILE_NUMBERS if isinstance(v, int)]),
                  st.integers(-2 ** 63, 2 ** 63 - 1))
VALUES = st.one_of(
    st.sampled_from(HOSTILE_NUMBERS), _floats, _ints, st.booleans(),
    st.sampled_from(['', 'pvtol', 'x' * 10_000, 'true']),
    st.lists(st.sampled_from(HOSTILE_NUMBERS[:9]), min_size=1, max_size=6),
    st.lists(_floats, max_size=8), st.lists(_ints, min_size=1, max_size=8),
    st.lists(st.sampled_from(['a', 'linear.x', '']), min_size=1, max_size=3),
    st.sampled_from([[0.6] * 600, [1e308] * 5, [0.1] * 5000, [2 ** 63 - 1] * 2]),
)
"""What a set may carry (any ROS parameter type, homogeneous lists)."""

OPEN_NAMES = ('bands.extra.index', 'system_params.with_operator', 'not_a_parameter')
"""Names the node did not declare at start."""


@pytest.fixture
def harness(ros_domain_id):
    rclpy.init(args=['--ros-args', '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC],
               domain_id=ros_domain_id)
    instance = FilterHarness()
    yield instance
    instance.node.destroy_node()
    rclpy.try_shutdown()


def _same(a: Any, b: Any) -> bool:
    """Parameter values equal, NaN equal to NaN, lists element by element."""
    if isinstance(a, (list, tuple, np.ndarray)) and isinstance(b, (list, tuple, np.ndarray)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _assert_in_force(node: Any) -> None:
    """The filter in force is the filter of the stored parameters that feed it (NaN equal to
    NaN: a key of a family that is not configured, such as ``gaps.delta`` without ``gaps.a``,
    is read only when the family is; ``use_sim_time`` is the runtime's)."""
    from rcbf_ros.node_logic.safety_filter import feeds_the_filter
    active, stored = ({k: v for k, v in params.items() if feeds_the_filter(k)}
                      for params in (node._active.params, node._parameter_values()))
    assert set(active) == set(stored)
    assert all(_same(active[k], stored[k]) for k in active), {
        k: (active[k], stored[k]) for k in active if not _same(active[k], stored[k])}


def _values(node: Any) -> dict[str, Any]:
    return {name: p.value for name, p in node.get_parameters_by_prefix('').items()}


def _parameter(name: str, value: Any) -> Parameter | None:
    """The Parameter a ROS client would send (None: no ROS type holds the value)."""
    try:
        return Parameter(name, value=value)
    except Exception:
        return None


def _check_answer(harness: FilterHarness) -> None:
    """A state and a proposal in; the answer keeps the invariant of the filter in force, and a
    filter the node holds can evaluate its rows there."""
    node = harness.node
    node._on_state(_cdr({'state': STATE}))
    active = node._active
    command, diagnostic = harness.answer(_cdr({'u': PROPOSAL}))  # diagnostics may be throttled
    info = harness.infos[-1]
    status = int(_section(info, 'status'))
    assert status != STATUS_CODES['input_refused'], diagnostic
    if _section(info, 'fail_safe'):
        np.testing.assert_array_equal(command, active.safety_filter.fail_safe_action)
        assert status >= 10, status  # a reason, not a solver status
        return
    system = active.config.problem.system
    if system.u_min is not None:
        assert np.all(command >= np.array(system.u_min) - 1e-12)
        assert np.all(command <= np.array(system.u_max) + 1e-12)
    mean = active.static_mean if active.static_mean.size else None
    std = active.static_std if active.static_std.size else None
    u_rows = (np.clip(PROPOSAL, system.u_min, system.u_max) if system.u_min is not None
              else np.array(PROPOSAL))
    values = row_values(active.config.problem, np.array(STATE), u_rows, command, mean, std)
    scale = 1.0 + np.abs(values).max(initial=0.0)
    assert np.all(values >= -active.settings.slack_tolerance - 1e-9 * scale), values


def _section(info: Any, label: str) -> float:
    """One value of a filter_info message's section ``label``."""
    offset = 0
    for dim in info.layout.dim:
        if dim.label == label:
            return float(info.data[offset])
        offset += dim.size
    raise KeyError(label)


_PROPERTY = settings(max_examples=150, deadline=None, derandomize=True,
                     suppress_health_check=[HealthCheck.function_scoped_fixture,
                                            HealthCheck.too_slow, HealthCheck.data_too_large])


def test_no_parameter_set_kills_the_filter_or_switches_it_off(harness):
    node = harness.node
    names = sorted(_values(node)) + list(OPEN_NAMES)
    _check_answer(harness)

    @_PROPERTY
    @example(atomically=False, items=[('obstacles.margin', 1e308)])
    @example(atomically=False, items=[('obstacles.radius', [1e308] * 5)])
    @example(atomically=True, items=[('obstacles.x', [1e200, -1.5, -1.5, 1.5, 1.5])])
    @example(atomically=False, items=[('log_throttle_s', 1e308)])
    @example(atomically=False, items=[('diagnostics.min_period_s', 1e308)])
    @example(atomically=False, items=[('osqp.max_iter', 2 ** 63 - 1)])
    @example(atomically=False, items=[('obstacles.heading_index', 0)])
    @example(atomically=False, items=[('alpha', 1e308)])
    @example(atomically=True, items=[('k_c', 1e300), ('alpha', 5e-324)])
    @example(atomically=True, items=[('slack_tolerance', 1e308), ('slack_weight', 1e-300)])
    @example(atomically=False, items=[('obstacles.lookahead', 10.0)])
    @example(atomically=False, items=[('input_bounds.command', 5e-324)])
    @example(atomically=True, items=[('walls.nx', [1e-300]), ('walls.ny', [0.0]),
                                     ('walls.offset', [1.0])])
    @given(atomically=st.booleans(),
           items=st.lists(st.tuples(st.sampled_from(names), VALUES), min_size=1, max_size=4,
                          unique_by=lambda item: item[0]))
    def check(atomically: bool, items: list[tuple[str, Any]]) -> None:
        parameters = [p for p in (_parameter(n, v) for n, v in items) if p is not None]
        if not parameters:
            return
        before = _values(node)
        if any(p.name not in before for p in parameters):
            # rclpy's local calls raise for an undeclared name (the parameter service answers
            # "not declared"); nothing changes either way
            with pytest.raises(ParameterNotDeclaredException):
                (node.set_parameters_atomically if atomically else node.set_parameters)(
                    [p for p in parameters if p.name not in before])
            assert all(_same(v, before[k]) for k, v in _values(node).items())
            parameters = [p for p in parameters if p.name in before]
            if not parameters:
                return
        if atomically:
            results = [node.set_parameters_atomically(parameters)] * len(parameters)
        else:
            results = node.set_parameters(parameters)
        after = _values(node)
        for parameter, result in zip(parameters, results):
            assert '\n' not in result.reason and len(result.reason) <= 1000, result.reason
            if result.successful:
                assert _same(after[parameter.name], parameter.value), parameter.name
            else:
                assert result.reason, parameter.name
                assert _same(after[parameter.name], before[parameter.name]), parameter.name
        if atomically and not results[0].successful:
            assert all(_same(after[k], before[k]) for k in before)
        _assert_in_force(node)
        _check_answer(harness)

    check()


@st.composite
def _obstacle_messages(draw: st.DrawFn) -> tuple[bytes, np.ndarray]:
    rows = draw(st.sampled_from([0, 1, 2, 5, 512, 1000, OBSTACLE_LIMIT, OBSTACLE_LIMIT + 1,
                                 100_000]))
    value = draw(_floats)
    data = np.tile(np.array([0.0, 1.5, 0.4]), rows)
    if rows and draw(st.booleans()):
        data[draw(st.integers(0, data.size - 1))] = value
    if draw(st.booleans()):
        data = data[:-1] if data.size else np.array([value])
    msg = get_message('std_msgs/msg/Float64MultiArray')(data=data.tolist())
    if draw(st.booleans()):
        dim = get_message('std_msgs/msg/MultiArrayDimension')
        msg.layout.dim = [dim(label='rows', size=draw(st.sampled_from([rows, 2 ** 32 - 1])),
                              stride=3 * rows), dim(label='xyr', size=3, stride=3)]
    return serialize_message(msg), data


def test_no_obstacles_message_kills_the_filter_or_switches_it_off(harness):
    node = harness.node
    _check_answer(harness)

    @_PROPERTY
    @given(message=_obstacle_messages())
    def check(message: tuple[bytes, np.ndarray]) -> None:
        data, sent = message
        keys = ('obstacles.x', 'obstacles.y', 'obstacles.radius')
        before = [list(node.get_parameter(k).value) for k in keys]
        node._on_obstacles(data)
        after = [list(node.get_parameter(k).value) for k in keys]
        # the whole set of the message, or the old set untouched
        if not all(_same(a, b) for a, b in zip(after, before)):
            for column, values in enumerate(after):
                assert _same(values, sent[column::3].tolist())
        assert len(after[0]) <= OBSTACLE_LIMIT
        _assert_in_force(node)
        _check_answer(harness)

    check()


HOSTILE_FILES = [
    ({'obstacles': {'margin': 1e308}}, 'obstacles.margin'),
    ({'obstacles': {'radius': [1e308] * 5}}, 'obstacles.radius'),
    ({'obstacles': {'x': [1e200, -1.5, -1.5, 1.5, 1.5]}}, 'obstacles.x'),
    ({'log_throttle_s': 1e308}, 'log_throttle_s'),
    ({'diagnostics': {'min_period_s': 1e308}}, 'diagnostics.min_period_s'),
    ({'osqp': {'max_iter': 2 ** 63 - 1}}, 'osqp.max_iter'),
    ({'obstacles': {'heading_index': 0}}, 'obstacles.heading_index'),
    # more obstacles than a filter takes: a params file that size is refused first
    ({'obstacles': {'x': [0.5] * (OBSTACLE_LIMIT + 1)}}, 'byte limit of a params file'),
    ({'alpha': 1e300}, 'alpha'),
    ({'slack_weight': 1e308}, 'slack_weight'),
    ({'input_bounds': {'state': 1e300}}, 'input_bounds.state'),
    ({'state_frame_id': 'map\x00'}, 'state_frame_id: contains the control character U+0000'),
    ({'diagnostics': {'name': 'a\x1b[31mb'}}, 'diagnostics.name: contains the control'),
]


@pytest.mark.parametrize('values, key', HOSTILE_FILES, ids=[k for _, k in HOSTILE_FILES])
def test_a_hostile_params_file_is_one_line_and_exit_2(tmp_path: Path, ros_domain_id: int,
                                                       values: dict, key: str) -> None:
    path = tmp_path / 'hostile.yaml'
    path.write_text(yaml.safe_dump({'/safety_filter': {'ros__parameters': values}}))
    process = subprocess.run(
        [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
         '--params-file', UNICYCLE, '--params-file', str(path)],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, 'ROS_DOMAIN_ID': str(ros_domain_id)})
    assert process.returncode == 2, process.stderr[-2000:]
    assert 'Traceback' not in process.stderr
    last = process.stderr.strip().splitlines()[-1]
    assert last.startswith('safety_filter: ') and key in last, process.stderr[-2000:]


@pytest.mark.parametrize('name, value', [
    ('diagnostics.name', 'a\x00b'), ('diagnostics.hardware_id', 'evil\x1b[31m'),
    ('state_frame_id', 'map\x00'), ('diagnostics.name', 'tab\there')])
def test_a_string_with_a_control_character_is_refused_at_runtime_naming_it(harness, name,
                                                                           value):
    node = harness.node
    before = _values(node)
    (result,) = node.set_parameters([Parameter(name, value=value)])
    assert not result.successful
    assert result.reason.startswith(f'{name}: contains the control character U+'), result.reason
    assert _values(node) == before
    _assert_in_force(node)


def test_every_declared_parameter_describes_itself_with_its_range(harness):
    from rcbf_ros.ros.safety_filter_node import INTERFACE
    node = harness.node
    names = sorted(_values(node))
    # alpha and obstacles.* come from the params file (declared from the overrides first)
    assert {'alpha', 'obstacles.x', 'k_c', 'osqp.max_iter', 'system'} <= set(names)
    for name in names:
        spec = INTERFACE.spec(name)
        if spec is None:  # the runtime's own (use_sim_time)
            continue
        descriptor = node.describe_parameter(name)
        assert descriptor.description == spec.description, name
        bounds = spec.range
        ranges = list(descriptor.floating_point_range) + list(descriptor.integer_range)
        if bounds is None:
            assert not ranges, name
        else:
            assert [(r.from_value, r.to_value) for r in ranges] == [bounds], name
    k_c = node.describe_parameter('k_c').floating_point_range[0]
    assert (k_c.from_value, k_c.to_value) == (0.0, math.inf)
    max_iter = node.describe_parameter('osqp.max_iter').integer_range[0]
    assert (max_iter.from_value, max_iter.to_value) == (1, 2 ** 31 - 1)
    alpha = node.describe_parameter('alpha').floating_point_range[0]
    assert alpha.from_value == 5e-324 and alpha.to_value == math.inf
    assert node.describe_parameter('system').read_only


def test_a_failing_publication_still_sends_the_fail_safe_command(harness, capsys):
    node = harness.node
    node._on_state(_cdr({'state': STATE}))
    sent: list[Any] = []
    publish = node._cmd_pub.publish

    def first_fails(msg: Any) -> None:  # the answer's command cannot go out, the next can
        sent.append(msg)
        if len(sent) == 1:
            raise RuntimeError('publisher gone')
        publish(msg)
    node._cmd_pub.publish = first_fails
    before = len(harness.commands)
    node._on_proposal(_cdr({'u': PROPOSAL}))  # never raises
    assert len(harness.commands) == before + 1  # the fail-safe instead of the answer
    np.testing.assert_array_equal(harness.commands[-1].data, node.fail_safe_action)
    assert 'fail-safe: internal error: RuntimeError: publisher gone' in capsys.readouterr().err


def test_a_failing_detail_costs_the_details_never_a_second_command(harness, capsys):
    node = harness.node
    node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))  # far from every obstacle: passed as is

    def broken(msg: Any) -> None:
        raise RuntimeError('info publisher gone')
    node._info_pub.publish = broken
    before = len(harness.commands)
    for _ in range(50):
        node._on_proposal(_cdr({'u': PROPOSAL}))  # never raises
    assert len(harness.commands) == before + 50  # one command per proposal, the answer's
    np.testing.assert_array_equal(harness.commands[-1].data, PROPOSAL)
    log = capsys.readouterr().err
    assert log.count('answer details not published') == 1, log  # throttled


@pytest.mark.parametrize('broken', ['info_cdr', 'diagnostics_cdr'])
def test_a_detail_that_cannot_be_made_costs_the_details_never_the_command(harness, capsys,
                                                                          monkeypatch, broken):
    """filter_info or the diagnostics cannot be made: every proposal still gets its own
    command (not the fail-safe), filter_info goes out when it was made, one throttled line."""
    from rcbf_ros.node_logic import filter_edge
    node = harness.node
    node._on_state(_cdr({'state': [-3.0, 0.0, 0.0]}))  # far from every obstacle: passed as is

    def fails(*_args: Any, **_kwargs: Any) -> bytes:
        raise RuntimeError('encoder gone')
    monkeypatch.setattr(filter_edge, broken, fails)
    commands, infos = len(harness.commands), len(harness.infos)
    for _ in range(20):
        node._on_proposal(_cdr({'u': PROPOSAL}))  # never raises
    assert len(harness.commands) == commands + 20
    np.testing.assert_array_equal(harness.commands[-1].data, PROPOSAL)
    assert len(harness.infos) == infos + (0 if broken == 'info_cdr' else 20)
    log = capsys.readouterr().err
    assert log.count('answer details not published: internal error: RuntimeError: encoder '
                     'gone') == 1, log


def test_an_unforeseen_error_while_a_set_is_checked_refuses_it_in_one_line(harness, monkeypatch):
    from rcbf_ros.node_logic import safety_filter as logic
    node = harness.node
    old = node.filter

    def broken(**kwargs: Any) -> Any:
        raise RuntimeError('a defect\nover two lines')
    monkeypatch.setattr(logic, 'build_active_filter', broken)
    result = node.set_parameters([Parameter('k_c', value=1.0)])[0]
    assert not result.successful
    assert result.reason == 'k_c: RuntimeError: a defect over two lines'
    assert node.filter is old and node.get_parameter('k_c').value == 2.0
    _check_answer(harness)


def test_an_obstacles_message_of_10000_rows_is_installed_and_answered(harness):
    node = harness.node
    rng = np.random.default_rng(0)
    rows = np.column_stack([rng.uniform(20.0, 120.0, 10_000), rng.uniform(-50.0, 50.0, 10_000),
                            rng.uniform(0.05, 0.5, 10_000)])
    rows[0] = [0.0, 0.0, 0.6]  # the obstacle STATE faces
    msg = get_message('std_msgs/msg/Float64MultiArray')(data=rows.ravel().tolist())
    node._on_obstacles(serialize_message(msg))
    assert _same(list(node.get_parameter('obstacles.radius').value), rows[:, 2].tolist())
    assert node._active.safety_filter.assembly == 'vectorised'
    _assert_in_force(node)
    _check_answer(harness)  # every one of the 10,000 rows met at the answer
    info = harness.infos[-1]
    assert not _section(info, 'fail_safe')
    assert np.any(np.abs(harness.answer(_cdr({'u': PROPOSAL}))[0] - PROPOSAL) > 1e-6)

"""The parameter services answer within a bound (rcbf_ros.ros.dds.parameter_service).

rclpy answers a name as often as a request gives it: a 5 kB request naming a parameter of
20,000 values 300 times had the node build a 48 MB answer on its one executor thread, and a
request of a few hundred kB would take gigabytes (the filter stores an ``obstacles`` message's
rows as such parameters). A request of more than MAX_REQUEST_NAMES names, or whose get answer
would carry more than MAX_ANSWER_VALUES values, is answered with nothing (as one naming an
undeclared parameter is) and said in a throttled WARN.
"""
from __future__ import annotations

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.ros.dds import parameter_service
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Node
from rcbf_ros.ros.dds.services import get_service

GET = get_service('rcl_interfaces/srv/GetParameters')
DESCRIBE = get_service('rcl_interfaces/srv/DescribeParameters')
TYPES = get_service('rcl_interfaces/srv/GetParameterTypes')
ROWS = 20_000


@pytest.fixture
def node():
    rclpy.init(args=[], domain_id=0)
    instance = Node('bounds')
    instance.declare_parameter('rows', [0.5] * ROWS)
    instance.declare_parameter('gain', 2.0)
    instance.declare_parameter('label', 'x' * 100)
    warnings: list[str] = []
    instance.get_logger().warning = warnings.append
    instance.warnings = warnings
    yield instance
    instance.destroy_node()
    rclpy.try_shutdown()


SIZES = {'rows': ROWS, 'gain': 1, 'label': 100}


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(counts=st.dictionaries(st.sampled_from(sorted(SIZES)), st.integers(0, 80)))
def test_a_get_is_answered_whole_within_the_bound_or_not_at_all(node, counts) -> None:
    """Any multiset of declared names: every name answered in order when the values fit the
    bound, else nothing."""
    names = [name for name, count in sorted(counts.items()) for _ in range(count)]
    values = node._parameter_service._get_parameters(GET.Request(names=names),
                                                     GET.Response()).values
    size = sum(SIZES[name] for name in names)
    if size <= parameter_service.MAX_ANSWER_VALUES:
        assert len(values) == len(names)
        for name, value in zip(names, values):
            if name == 'rows':
                assert len(value.double_array_value) == ROWS
            elif name == 'gain':
                assert value.double_value == 2.0
            else:
                assert value.string_value == 'x' * 100
    else:
        assert list(values) == []


def test_an_answer_past_the_bound_is_nothing_and_said_once(node, monkeypatch) -> None:
    """A 5 kB request for 300 copies of a 20,000-value parameter (48 MB answered before): an
    empty answer, built before any value message, and one WARN for a burst of them."""
    built: list[object] = []
    monkeypatch.setattr(parameter_service, 'parameter_value_msg',
                        lambda parameter: built.append(parameter) or object())
    monkeypatch.setattr(parameter_service.time, 'monotonic_ns', lambda: 10**12)  # one instant
    for _ in range(5):
        response = node._parameter_service._get_parameters(
            GET.Request(names=['rows'] * 300), GET.Response())
        assert list(response.values) == []
    assert built == []
    assert len(node.warnings) == 1, node.warnings
    assert 'get_parameters' in node.warnings[0] and '6000000 values' in node.warnings[0]


@pytest.mark.parametrize(('service', 'srv', 'field'), [
    ('_describe_parameters', DESCRIBE, 'descriptors'), ('_get_parameter_types', TYPES, 'types'),
    ('_get_parameters', GET, 'values')])
def test_a_request_of_too_many_names_is_answered_with_nothing(node, service, srv, field):
    callback = getattr(node._parameter_service, service)
    limit = parameter_service.MAX_REQUEST_NAMES
    assert len(getattr(callback(srv.Request(names=['gain'] * limit), srv.Response()),
                       field)) == limit
    assert list(getattr(callback(srv.Request(names=['gain'] * (limit + 1)), srv.Response()),
                        field)) == []


SET = get_service('rcl_interfaces/srv/SetParameters')
SET_ATOMICALLY = get_service('rcl_interfaces/srv/SetParametersAtomically')


@pytest.mark.parametrize('atomically', [False, True])
def test_a_set_request_of_too_many_parameters_sets_none(node, atomically) -> None:
    """More than MAX_SET_ENTRIES parameters in one set request: none set, each refused with the
    reason (one result for an atomic set); at the bound, every one set."""
    from rcbf_ros.ros.dds.parameter_service import parameter_msg
    from rcbf_ros.ros.dds.parameters import Parameter

    limit = parameter_service.MAX_SET_ENTRIES
    service = node._parameter_service
    for count, value in ((limit + 1, 3.0), (limit, 4.0)):
        entries = [parameter_msg(Parameter('gain', value=value))] * count
        if atomically:
            results = [service._set_parameters_atomically(
                SET_ATOMICALLY.Request(parameters=entries), SET_ATOMICALLY.Response()).result]
        else:
            results = list(service._set_parameters(SET.Request(parameters=entries),
                                                   SET.Response()).results)
            assert len(results) == count
        refused = count > limit
        assert all(r.successful is not refused for r in results)
        assert all(('more than' in r.reason) is refused for r in results)
        assert node.get_parameter('gain').value == (2.0 if refused else 4.0)

"""rcl_interfaces' parameter services of a node, answered as rclpy's ParameterService does.

Every node serves, under its own name (``<node>/get_parameters`` resolved in its namespace,
remaps applied), ``describe_parameters``, ``get_parameters``, ``get_parameter_types``,
``list_parameters``, ``set_parameters`` and ``set_parameters_atomically`` with QoS
``qos_profile_parameters``, so that ``ros2 param`` and rclpy's parameter clients reach it.

Semantics (rclpy 7.1 ``parameter_service.py``): a get / describe / get-types request naming one
undeclared (or, for get, uninitialized) parameter gets an empty list back; ``set_parameters``
sets each parameter atomically on its own, an undeclared one failing with the exception's text
as its reason; ``set_parameters_atomically`` sets all or none. Setting goes through the node's
``set_parameters_atomically``, so its checks (types, read-only, set-parameter callbacks) apply.
Unlike rclpy, the answers are bounded (:data:`MAX_REQUEST_NAMES`, :data:`MAX_ANSWER_VALUES`,
:data:`MAX_SET_ENTRIES`): a request past them is answered as a refused one, with a WARN.

Successful sets, through these services or from inside the node, are announced on
``/parameter_events`` by the node itself (:meth:`NodeParameters._set_parameters_common`), as
rclpy announces every declaration and set.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Iterable
import weakref

import numpy as np

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.parameters import (
    Parameter,
    ParameterNotDeclaredException,
    ParameterUninitializedException,
    set_parameters_result,
)
from rcbf_ros.ros.dds.qos import QoSProfile
from rcbf_ros.ros.dds.services import get_service, qos_profile_parameters

qos_profile_parameter_events = QoSProfile(depth=1000)
"""rclpy's QoS of ``/parameter_events``: reliable, volatile, keep-last 1000."""

PARAMETER_SERVICES = ('describe_parameters', 'get_parameters', 'get_parameter_types',
                      'list_parameters', 'set_parameters', 'set_parameters_atomically')
"""The services every node offers, in the order rclpy creates them."""

_VALUE_FIELDS = {
    Parameter.Type.BOOL: 'bool_value', Parameter.Type.INTEGER: 'integer_value',
    Parameter.Type.DOUBLE: 'double_value', Parameter.Type.STRING: 'string_value',
    Parameter.Type.BYTE_ARRAY: 'byte_array_value',
    Parameter.Type.BOOL_ARRAY: 'bool_array_value',
    Parameter.Type.INTEGER_ARRAY: 'integer_array_value',
    Parameter.Type.DOUBLE_ARRAY: 'double_array_value',
    Parameter.Type.STRING_ARRAY: 'string_array_value',
}


def parameter_value_msg(parameter: Parameter) -> Any:
    """The ``rcl_interfaces/msg/ParameterValue`` of a parameter (rclpy's
    ``Parameter.get_parameter_value``)."""
    value_msg = messages.get_message('rcl_interfaces/msg/ParameterValue')(
        type=parameter.type_.value)
    field = _VALUE_FIELDS.get(parameter.type_)
    if field is not None:
        value = parameter.value
        if parameter.type_ is Parameter.Type.BYTE_ARRAY:
            value = b''.join(value)
        setattr(value_msg, field, value)
    return value_msg


def parameter_msg(parameter: Parameter) -> Any:
    """The ``rcl_interfaces/msg/Parameter`` of a parameter (rclpy's ``to_parameter_msg``)."""
    return messages.get_message('rcl_interfaces/msg/Parameter')(
        name=parameter.name, value=parameter_value_msg(parameter))


def parameter_from_msg(msg: Any) -> Parameter:
    """The parameter a ``rcl_interfaces/msg/Parameter`` stands for (rclpy's
    ``Parameter.from_parameter_msg``; arrays as Python lists, bytes as 1-byte ``bytes``).

    Raises:
        ValueError: the message's type is not a ParameterType.
    """
    type_ = Parameter.Type(msg.value.type)
    field = _VALUE_FIELDS.get(type_)
    value = None if field is None else getattr(msg.value, field)
    if type_ is Parameter.Type.BYTE_ARRAY:
        value = [bytes([int(b) & 0xFF]) for b in value]
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, list):
        value = list(value)
    return Parameter(msg.name, type_, value)


MAX_REQUEST_NAMES = 10_000
"""The most names a get, describe or get-types request may give (a node declares some hundred
parameters; rclpy answers a name as often as it is given)."""
MAX_ANSWER_VALUES = 1_000_000
"""The most values a get answer may carry (array items, string characters, one for a scalar):
a request giving a name of 20,000 values a few thousand times would have the node build and
send gigabytes on its one executor thread (300 names of ``obstacles.x``, a 5 kB request,
made a 48 MB answer)."""
MAX_SET_ENTRIES = 1_000
"""The most parameters a set_parameters or set_parameters_atomically request may give (a node
declares some hundred; each entry of a set_parameters request is one set, and a set may build
a whole safety filter)."""
REFUSAL_WARNING_PERIOD_S = 1.0
"""At most one WARN per service per this many seconds for requests refused by the bounds."""


def _value_size(parameter: Parameter) -> int:
    """How many values ``parameter`` puts into an answer (:data:`MAX_ANSWER_VALUES`)."""
    value = parameter.value
    if isinstance(value, (str, bytes)):
        return max(1, len(value))
    if isinstance(value, (list, tuple)):  # an array parameter holds one type
        if value and isinstance(value[0], str):
            return max(1, sum(map(len, value)))
        return max(1, len(value))
    return 1


def _type_number(kind: Any) -> int:
    """The ParameterType number of what ``get_parameter_type`` gives: a number, or, for an
    undeclared parameter (where allowed), ``Parameter.Type.NOT_SET``."""
    return int(getattr(kind, 'value', kind))


def _each_or_none(names: Iterable[str], answer: Callable[[str], Any], *,
                  refusals: tuple[type[Exception], ...] = (ParameterNotDeclaredException,)
                  ) -> list[Any]:
    """``answer(name)`` of every name, or none at all if one raises one of ``refusals`` (as
    rclpy's parameter service answers a request naming an undeclared parameter)."""
    try:
        return [answer(name) for name in names]
    except refusals:
        return []


class ParameterService:
    """The six parameter services of ``node`` and its ``/parameter_events`` publisher."""

    def __init__(self, node: Any) -> None:
        self._node_ref = weakref.ref(node)
        self._refusal_ns: dict[str, int] = {}
        """Per service, when a refused request was last said (:meth:`_refused`)."""
        self._refusals: dict[str, int] = {}
        """Per service, requests refused since then."""
        name = node.get_name()
        callbacks = {
            'describe_parameters': ('DescribeParameters', self._describe_parameters),
            'get_parameters': ('GetParameters', self._get_parameters),
            'get_parameter_types': ('GetParameterTypes', self._get_parameter_types),
            'list_parameters': ('ListParameters', self._list_parameters),
            'set_parameters': ('SetParameters', self._set_parameters),
            'set_parameters_atomically': ('SetParametersAtomically',
                                          self._set_parameters_atomically),
        }
        self.services = [
            node.create_service(get_service(f'rcl_interfaces/srv/{srv_type}'),
                                f'{name}/{service}', callback,
                                qos_profile=qos_profile_parameters)
            for service, (srv_type, callback) in ((s, callbacks[s]) for s in PARAMETER_SERVICES)]

    def _node(self) -> Any:
        node = self._node_ref()
        if node is None:
            raise ReferenceError('the node of this parameter service is gone')
        return node

    # callbacks --------------------------------------------------------------------------------
    def _too_many_names(self, service: str, names: Any) -> bool:
        """Whether a request gives more than :data:`MAX_REQUEST_NAMES` names (then it is
        answered as one naming an undeclared parameter is, with nothing, and said)."""
        if len(names) <= MAX_REQUEST_NAMES:
            return False
        self._refused(service, f'{len(names)} names, more than {MAX_REQUEST_NAMES}')
        return True

    def _refused(self, service: str, why: str) -> None:
        """One WARN (at most one per :data:`REFUSAL_WARNING_PERIOD_S` per service) saying a
        request was answered with nothing, and why."""
        now = time.monotonic_ns()
        last = self._refusal_ns.get(service)
        self._refusals[service] = self._refusals.get(service, 0) + 1
        if last is not None and now - last < REFUSAL_WARNING_PERIOD_S * 1e9:
            return
        self._refusal_ns[service] = now
        count = self._refusals.pop(service)
        self._node().get_logger().warning(
            f'{service}: {count} request(s) answered with nothing; last: {why}')

    def _describe_parameters(self, request: Any, response: Any) -> Any:
        if self._too_many_names('describe_parameters', request.names):
            response.descriptors = []
            return response
        response.descriptors = _each_or_none(request.names, self._node().describe_parameter)
        return response

    def _get_parameters(self, request: Any, response: Any) -> Any:
        node = self._node()
        response.values = []
        if self._too_many_names('get_parameters', request.names):
            return response
        parameters = _each_or_none(
            request.names, node.get_parameter,
            refusals=(ParameterNotDeclaredException, ParameterUninitializedException))
        sizes: dict[int, int] = {}  # a name given again costs nothing more to weigh
        size = sum(sizes.setdefault(id(parameter), _value_size(parameter))
                   for parameter in parameters)
        if size > MAX_ANSWER_VALUES:  # counted before any message is built
            self._refused('get_parameters', f'the answer would carry {size} values, more '
                                            f'than {MAX_ANSWER_VALUES}')
            return response
        response.values = [parameter_value_msg(parameter) for parameter in parameters]
        return response

    def _get_parameter_types(self, request: Any, response: Any) -> Any:
        node = self._node()
        if self._too_many_names('get_parameter_types', request.names):
            response.types = []
            return response
        response.types = _each_or_none(
            request.names, lambda name: _type_number(node.get_parameter_type(name)))
        return response

    def _list_parameters(self, request: Any, response: Any) -> Any:
        node = self._node()
        try:
            response.result = node.list_parameters(list(request.prefixes), int(request.depth))
        except (TypeError, ValueError):
            response.result = messages.get_message('rcl_interfaces/msg/ListParametersResult')()
        return response

    def _too_many_entries(self, service: str, parameters: Any) -> str:
        """Why a set request is refused whole: more than :data:`MAX_SET_ENTRIES` parameters
        ('' when it is not; said in the throttled WARN)."""
        if len(parameters) <= MAX_SET_ENTRIES:
            return ''
        why = f'{len(parameters)} parameters, more than {MAX_SET_ENTRIES} in one request'
        self._refused(service, why)
        return f'not set: {why}'

    def _set_parameters(self, request: Any, response: Any) -> Any:
        why = self._too_many_entries('set_parameters', request.parameters)
        if why:
            response.results = [set_parameters_result(False, why)] * len(request.parameters)
            return response
        response.results = [self._set_atomically([parameter_from_msg(p)])
                            for p in request.parameters]
        return response

    def _set_parameters_atomically(self, request: Any, response: Any) -> Any:
        why = self._too_many_entries('set_parameters_atomically', request.parameters)
        if why:
            response.result = set_parameters_result(False, why)
            return response
        response.result = self._set_atomically([parameter_from_msg(p)
                                                for p in request.parameters])
        return response

    def _set_atomically(self, parameters: list[Parameter]) -> Any:
        try:
            return self._node().set_parameters_atomically(parameters)
        except ParameterNotDeclaredException as exc:
            return set_parameters_result(False, str(exc))

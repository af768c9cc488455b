"""One scenario of setting parameters, run on real rclpy or on the Cyclone runtime.

``python parameter_semantics.py rclpy|cyclone`` prints one JSON list: every step's outcome
(SetParametersResult flags and reasons, the exception type a call raised, the values after it,
the callbacks called and in which order, the parameter events the node published). The ros2
tier runs it under a real Jazzy and on ours
and compares the two lists; the unit tests import :func:`run` and check the semantics one by
one. The steps cover per-parameter and atomic sets, the three kinds of callbacks (each list
newest first; a refusal stops the on-set ones), descriptors (read-only, types, integer and
floating-point ranges), undeclared names, declarations with callbacks in place, removing
callbacks and ``list_parameters``.
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any, Callable


def middleware(which: str) -> dict[str, Any]:
    """The classes and calls the scenario needs, from rclpy or from our runtime."""
    if which == 'rclpy':
        from rcl_interfaces.msg import (
            FloatingPointRange,
            IntegerRange,
            ParameterDescriptor,
            SetParametersResult,
        )
        import rclpy
        from rclpy.context import Context
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        context = Context()
        rclpy.init(args=[], context=context)
        return {'node': lambda name: Node(name, context=context), 'Parameter': Parameter,
                'Descriptor': ParameterDescriptor, 'IntegerRange': IntegerRange,
                'FloatingPointRange': FloatingPointRange, 'Result': SetParametersResult,
                'shutdown': lambda: rclpy.shutdown(context=context)}
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.dds import rclpy_compat
    from rcbf_ros.ros.dds.node import Node, Parameter
    rclpy_compat.init(args=[], domain_id=int(os.environ.get('ROS_DOMAIN_ID', '0')))
    return {'node': Node, 'Parameter': Parameter,
            'Descriptor': get_message('rcl_interfaces/msg/ParameterDescriptor'),
            'IntegerRange': get_message('rcl_interfaces/msg/IntegerRange'),
            'FloatingPointRange': get_message('rcl_interfaces/msg/FloatingPointRange'),
            'Result': get_message('rcl_interfaces/msg/SetParametersResult'),
            'shutdown': rclpy_compat.try_shutdown}


VALUE_FIELDS = {1: 'bool_value', 2: 'integer_value', 3: 'double_value', 4: 'string_value',
                5: 'byte_array_value', 6: 'bool_array_value', 7: 'integer_array_value',
                8: 'double_array_value', 9: 'string_array_value'}
"""rcl_interfaces/msg/ParameterType number -> the ParameterValue field holding it."""

RCLPY_OWN = ('use_sim_time', 'start_type_description_service')
"""Parameters rclpy declares on every node (simulated time, the type description service),
which the Cyclone runtime has no use for."""


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)) or type(value).__name__ in ('array', 'ndarray'):
        return [_plain(v) for v in value]
    return value


def run(which: str) -> list[dict[str, Any]]:
    """Every step of the scenario and its outcome, in order."""
    m = middleware(which)
    P, T = m['Parameter'], m['Parameter'].Type
    node = m['node']('parameter_semantics')
    calls: list[str] = []
    steps: list[dict[str, Any]] = []
    events: list[Any] = []

    class EventCapture:
        """Stands in for the node's ``/parameter_events`` publisher (the same attribute on
        rclpy's Node and on ours): what the node publishes, without DDS timing."""

        def publish(self, msg: Any) -> None:
            events.append(msg)

    node._parameter_event_publisher = EventCapture()

    def event_entries(parameters: Any) -> list[Any]:
        return [[p.name, p.value.type, _plain(getattr(p.value, VALUE_FIELDS[p.value.type]))
                 if p.value.type in VALUE_FIELDS else None] for p in parameters]

    def result(successful: bool, reason: str = '') -> Any:
        return m['Result'](successful=successful, reason=reason)

    def refuse_negative_b(parameters: list[Any]) -> Any:
        calls.append('on_b:' + ','.join(p.name for p in parameters))
        for p in parameters:
            if p.name.startswith('b') and p.value < 0:
                return result(False, f'{p.name}: must be >= 0')
        return result(True, 'a reason rclpy drops on success')

    def record_on(parameters: list[Any]) -> Any:
        calls.append('on_record:' + ','.join(p.name for p in parameters))
        return result(True)

    def post(parameters: list[Any]) -> None:
        calls.append('post:' + ','.join(p.name for p in parameters))

    def values() -> dict[str, Any]:
        return {name: _plain(p.value) for name, p in node.get_parameters_by_prefix('').items()
                if name not in RCLPY_OWN}

    def step(name: str, call: Callable[[], Any]) -> None:
        calls.clear()
        events.clear()
        try:
            out = call()
        except Exception as exc:  # noqa: BLE001 - the exception type is the outcome here
            outcome: Any = {'raises': type(exc).__name__}
            if type(exc).__name__ == 'ParameterNotDeclaredException':  # clients read its text
                outcome['message'] = str(exc)
        else:
            if isinstance(out, list):
                outcome = [[r.successful, r.reason] for r in out]
            elif hasattr(out, 'successful'):
                outcome = [out.successful, out.reason]
            elif hasattr(out, 'names'):
                outcome = {'names': [n for n in out.names if n not in RCLPY_OWN],
                           'prefixes': list(out.prefixes)}
            else:
                outcome = None
        steps.append({'step': name, 'outcome': outcome, 'calls': list(calls),
                      'values': values(),
                      'events': [{'node': e.node, 'new': event_entries(e.new_parameters),
                                  'changed': event_entries(e.changed_parameters),
                                  'deleted': event_entries(e.deleted_parameters)}
                                 for e in events]})

    d = m['Descriptor']

    def first_declarations() -> None:
        node.declare_parameter('a', 2, d(integer_range=[m['IntegerRange'](
            from_value=0, to_value=10, step=2)]))
        node.declare_parameter('b', 0.5, d(floating_point_range=[m['FloatingPointRange'](
            from_value=1.0, to_value=-2.0, step=0.25)]))
        node.declare_parameter('ro', 'fixed', d(read_only=True))
        node.declare_parameter('dyn', 1, d(dynamic_typing=True))
        node.declare_parameter('x.y.z', 1.0)
        node.declare_parameter('x.w', [1.0, 2.0])
        node.declare_parameter('unset', m['Parameter'].Type.INTEGER)

    step('declare the first parameters', first_declarations)
    node.add_on_set_parameters_callback(refuse_negative_b)
    node.add_on_set_parameters_callback(record_on)
    node.add_post_set_parameters_callback(post)

    step('set one by one', lambda: node.set_parameters([
        P('a', value=4), P('b', value=-1.0), P('a', value=3), P('a', value=12),
        P('a', value=10), P('b', value=0.25 + 1e-9), P('b', value=0.3), P('b', value=-3.0),
        P('b', value=1.0 + 1e-7), P('ro', value='x'),
        P('a', value='text'), P('dyn', value='now a string'), P('dyn', T.NOT_SET),
        P('x.y.z', T.NOT_SET)]))
    step('atomic refused by a callback', lambda: node.set_parameters_atomically(
        [P('a', value=6), P('b', value=-1.0)]))
    step('atomic refused by a descriptor', lambda: node.set_parameters_atomically(
        [P('a', value=6), P('b', value=2.0)]))
    step('atomic accepted', lambda: node.set_parameters_atomically(
        [P('a', value=6), P('b', value=1.0)]))
    step('set undeclared', lambda: node.set_parameters([P('a', value=8), P('nope', value=1)]))
    step('atomic with undeclared', lambda: node.set_parameters_atomically(
        [P('a', value=0), P('nope', value=1)]))
    step('atomic with three undeclared', lambda: node.set_parameters_atomically(
        [P('nope', value=1), P('a', value=0), P('nope2', value=1), P('nope3', value=1)]))
    step('set not a Parameter', lambda: node.set_parameters_atomically([('a', 1)]))
    step('declare with callbacks', lambda: node.declare_parameter('c', 1.5))
    step('declare refused by a callback', lambda: node.declare_parameter('b2', -1.0))
    step('declare many, one refused', lambda: node.declare_parameters(
        '', [('d1', 1), ('b3', -2.0), ('d2', 2)]))
    step('declare one declared before', lambda: node.declare_parameters(
        '', [('d3', 1), ('a', 2)]))

    def pre_double(parameters: list[Any]) -> list[Any]:
        calls.append('pre_double:' + ','.join(p.name for p in parameters))
        return [P(p.name, value=p.value * 2) for p in parameters if p.name == 'a']

    def pre_add(parameters: list[Any]) -> list[Any]:
        calls.append('pre_add:' + ','.join(p.name for p in parameters))
        return [P('c', value=9.5)] if any(p.name == 'a' for p in parameters) else []

    step('add pre-set callbacks', lambda: (node.add_pre_set_parameters_callback(pre_double),
                                           node.add_pre_set_parameters_callback(pre_add)))
    step('set through pre-set callbacks', lambda: node.set_parameters([P('a', value=2)]))
    step('pre-set callbacks return nothing', lambda: node.set_parameters(
        [P('ro', value='y')]))
    step('remove pre-set callbacks', lambda: (
        node.remove_pre_set_parameters_callback(pre_add),
        node.remove_pre_set_parameters_callback(pre_double)))
    step('remove a callback twice', lambda: node.remove_pre_set_parameters_callback(pre_add))
    step('remove on-set callback', lambda: node.remove_on_set_parameters_callback(
        refuse_negative_b))
    step('set once the refusing callback is gone', lambda: node.set_parameters(
        [P('b', value=0.0)]))
    step('remove post-set callback', lambda: node.remove_post_set_parameters_callback(post))
    step('remove on-set callback twice', lambda: node.remove_on_set_parameters_callback(
        refuse_negative_b))
    step('undeclare read-only', lambda: node.undeclare_parameter('ro'))
    step('undeclare', lambda: node.undeclare_parameter('c'))
    step('undeclare undeclared', lambda: node.undeclare_parameter('c'))
    node.declare_parameter('x.y.q', 'q')
    node.declare_parameter('x.v.q.r', 'r')
    for prefixes, depth in (([], 0), ([], 1), ([], 2), (['x'], 0), (['x'], 1), (['x'], 2),
                            (['x.y'], 1), (['x', 'a'], 1), (['a'], 0), (['nothing'], 0)):
        step(f'list {prefixes} {depth}', lambda p=prefixes, n=depth: node.list_parameters(p, n))
    step('list negative depth', lambda: node.list_parameters([], -1))
    step('list prefixes not a list', lambda: node.list_parameters('x', 0))
    node.destroy_node()
    m['shutdown']()
    return steps


if __name__ == '__main__':
    print(json.dumps(run(sys.argv[1])))

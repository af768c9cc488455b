"""Run by the ros2 tier under a real Jazzy: what rclpy makes of each command line.

Reads a JSON list of ``{"argv": [...], "name": ..., "namespace": ...}`` from the file named by
argv[1]; prints a JSON list of ``{"overrides": {name: value}}`` (rclpy's parameter overrides of
a node of that name, NOT_SET as null) or ``{"error": "<type>: <message>"}``.
"""
import json
import sys

import rclpy
from rclpy.context import Context


def overrides(case):
    context = Context()
    try:
        rclpy.init(args=case['argv'], context=context)
    except Exception as exc:  # noqa: BLE001 - rcl refusing the arguments is a result here
        return {'error': f'{type(exc).__name__}: {exc}'}
    try:
        node = rclpy.create_node(case['name'], namespace=case.get('namespace', ''),
                                 context=context)
        try:
            return {'overrides': {name: parameter.value for name, parameter
                                  in node._parameter_overrides.items()}}
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


with open(sys.argv[1], encoding='utf-8') as stream:
    cases = json.load(stream)
print(json.dumps([overrides(case) for case in cases]))

"""Run by the ros2 tier under a real Jazzy: rclpy's serialized default message of each type.

Reads type names (one a line) from the file named by argv[1]; prints a JSON object
``{type name: hex of serialize_message(Type())}`` for every type this install has (others
are left out). Uses nothing of rcbf_ros.
"""
import json
import sys

from rclpy.serialization import serialize_message
from rosidl_runtime_py.utilities import get_message

found = {}
with open(sys.argv[1], encoding='utf-8') as stream:
    for name in stream.read().split():
        try:
            message_type = get_message(name)
        except (AttributeError, ModuleNotFoundError, ValueError):
            continue
        found[name] = serialize_message(message_type()).hex()
print(json.dumps(found))

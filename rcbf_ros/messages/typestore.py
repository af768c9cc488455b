"""The one ROS 2 Jazzy type store: message type names, definitions and RIHS01 type hashes.

Every message type is described once, by rosbags' ``ROS2_JAZZY`` type store (std_msgs,
geometry_msgs, sensor_msgs, nav_msgs, diagnostic_msgs, rcl_interfaces, ...: field definitions,
CDR serializers, RIHS01 hashes). The bag tools and the runtime share this one store, so the
schema text, the type hash and the CDR bytes agree with what a Jazzy node sends. Pure library:
no DDS, no file I/O.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Typestore

PRIMITIVE_DTYPES: dict[str, Any] = {
    'bool': np.bool_, 'byte': np.uint8, 'char': np.uint8, 'octet': np.uint8,
    'int8': np.int8, 'uint8': np.uint8, 'int16': np.int16, 'uint16': np.uint16,
    'int32': np.int32, 'uint32': np.uint32, 'int64': np.int64, 'uint64': np.uint64,
    'float32': np.float32, 'float64': np.float64,
}
"""Numpy scalar type of each primitive (non-string) ROS field type, as rosbags holds primitive
arrays and sequences (CDR is little endian on the wire here)."""


@lru_cache(maxsize=1)
def jazzy_typestore() -> Typestore:
    """The rosbags type store of ROS 2 Jazzy (one per process; building it takes ~100 ms)."""
    return get_typestore(Stores.ROS2_JAZZY)


def zero_value(base: str) -> Any:
    """The zero of a primitive ROS field type: '' for strings, False, 0 or 0.0."""
    if base == 'string':
        return ''
    if base == 'bool':
        return False
    return 0.0 if base.startswith('float') else 0


def normalize_type_name(type_name: str) -> str:
    """``'std_msgs/Float64'`` or ``'std_msgs/msg/Float64'`` -> ``'std_msgs/msg/Float64'``.

    Raises:
        ValueError: ``type_name`` is not of the form ``pkg/Type`` or ``pkg/msg/Type``.
    """
    parts = type_name.split('/')
    if len(parts) == 2 and all(parts):
        return f'{parts[0]}/msg/{parts[1]}'
    if len(parts) == 3 and all(parts):
        return type_name
    raise ValueError(f'type_name {type_name!r} is not of the form pkg/msg/Type')


def require_known_type(type_name: str, typestore: Typestore | None = None) -> str:
    """Normalised ``type_name`` if the type store knows it, else a ValueError naming it."""
    store = typestore or jazzy_typestore()
    name = normalize_type_name(type_name)
    if name not in store.fielddefs:
        raise ValueError(
            f'type_name {type_name!r} is not in the ROS 2 Jazzy type store '
            '(register it with rosbags or pass message_definition and type_hash)')
    return name


def message_definition_text(type_name: str, typestore: Typestore | None = None) -> str:
    """The full concatenated ``ros2msg`` definition that rosbag2 stores as an MCAP schema.

    Layout (as rosbag2's local message definition source writes it): the root type's ``.msg``
    text, then for each dependency, depth first and each once, a line of 80 ``=``, a line
    ``MSG: pkg/Type`` and that type's text. The text comes from rosbags' normalised definitions
    (comments are not kept; fields, constants and bounds are).
    """
    store = typestore or jazzy_typestore()
    text, _ = store.generate_msgdef(require_known_type(type_name, store), ros_version=2)
    return text


def type_hash_rihs01(type_name: str, typestore: Typestore | None = None) -> str:
    """The ROS 2 type description hash ``RIHS01_<64 hex>`` of ``type_name``.

    Raises:
        ValueError: the type store does not know ``type_name``.
    """
    store = typestore or jazzy_typestore()
    return store.hash_rihs01(require_known_type(type_name, store))

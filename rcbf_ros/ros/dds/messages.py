"""The runtime's messages: the shared message layer plus what is specific to Cyclone DDS.

Message classes, CDR and RIHS01 hashes come from :mod:`rcbf_ros.messages` (rosbags' Jazzy type
store, shared with the bag tools) and are re-exported here, so that the runtime reads one
module. What only DDS needs is here:

- the Cyclone DDS ``IdlStruct`` mirror (``@final``, XCDR1) of a message type, named
  ``pkg::msg::dds_::Type_`` as ROS 2's rmw names it (:func:`idl_struct`); it fixes the DDS topic
  type, while the bytes themselves come from rosbags' serializer (the tests check that both
  produce identical CDR);
- ROS <-> DDS type names (:func:`dds_type_name`, :func:`ros_type_name`);
- the payload a publisher sends: the CDR stream zero-padded to a multiple of 4 bytes
  (:func:`dds_payload`).
"""
from __future__ import annotations

import functools
from typing import Any

from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as idl_types
from rosbags.typesys.store import Nodetype

from rcbf_ros.messages.cdr import DeserializationError, deserialize_message, serialize_message
from rcbf_ros.messages.classes import get_message, Message, message_type_name
from rcbf_ros.messages.typestore import jazzy_typestore as typestore
from rcbf_ros.messages.typestore import normalize_type_name
from rcbf_ros.messages.typestore import type_hash_rihs01 as type_hash

__all__ = [
    # shared with the bag tools (rcbf_ros.messages), under the names the runtime uses
    'DeserializationError', 'Message', 'deserialize_message', 'get_message', 'message_type_name',
    'serialize_message', 'type_hash', 'typestore',
    # DDS only
    'dds_payload', 'dds_type_name', 'idl_struct', 'ros_type_name',
]

_IDL_PRIMITIVES: dict[str, Any] = {
    'bool': bool, 'byte': idl_types.byte, 'char': idl_types.uint8, 'int8': idl_types.int8,
    'uint8': idl_types.uint8, 'int16': idl_types.int16, 'uint16': idl_types.uint16,
    'int32': idl_types.int32, 'uint32': idl_types.uint32, 'int64': idl_types.int64,
    'uint64': idl_types.uint64, 'float32': idl_types.float32, 'float64': idl_types.float64,
}


def dds_type_name(type_name: str) -> str:
    """ROS -> DDS type name: ``'std_msgs/msg/Float64'`` -> ``'std_msgs::msg::dds_::Float64_'``."""
    pkg, sub, name = normalize_type_name(type_name).split('/')
    return f'{pkg}::{sub}::dds_::{name}_'


def ros_type_name(dds_name: str) -> str:
    """DDS type name -> ROS type name (inverse of :func:`dds_type_name`); others unchanged."""
    parts = dds_name.split('::')
    if len(parts) == 4 and parts[2] == 'dds_' and parts[3].endswith('_'):
        return f'{parts[0]}/{parts[1]}/{parts[3][:-1]}'
    return dds_name


def dds_payload(cdr: bytes) -> bytes:
    """The serialized payload DDS sends for a CDR stream: zero-padded to a multiple of 4.

    DDSI carries payloads in multiples of 4 bytes and reads that many from the sample whatever
    its length (Cyclone's Python serdata holds exactly the bytes written, so up to 3 bytes
    beyond them would go out: whatever the heap held). The padding is zeros, as rmw_cyclonedds
    writes it, and its length goes into the two low bits of the encapsulation options (XTypes
    1.3, 7.6.3.1.2, as Cyclone's own serializer sets them) so that a receiver can tell where
    the message ends; ROS 2's deserializers ignore the options.
    """
    pad = -len(cdr) % 4
    if pad == 0:
        return cdr
    if len(cdr) < 4:  # not a CDR stream at all: still never send bytes beyond the sample
        return cdr + bytes(pad)
    return cdr[:3] + bytes([(cdr[3] & 0xFC) | pad]) + cdr[4:] + bytes(pad)


@functools.cache
def idl_struct(type_name: str) -> type[IdlStruct]:
    """The Cyclone ``IdlStruct`` (``@final``, XCDR1) mirroring a ROS message type."""
    type_name = normalize_type_name(type_name)
    _, fields = typestore().fielddefs[type_name]
    members: dict[str, Any] = {}
    for name, desc in fields:
        members[name] = _idl_member(desc)
    return make_idl_struct(type_name.rsplit('/', 1)[1] + '_', dds_type_name(type_name), members)


def _idl_member(desc: tuple) -> Any:
    kind, detail = desc
    if kind == Nodetype.BASE:
        base, bound = detail
        if base == 'string':
            return idl_types.bounded_str[bound] if bound else str
        return _IDL_PRIMITIVES[base]
    if kind == Nodetype.NAME:
        return idl_struct(detail)
    sub, length = detail
    inner = _idl_member(sub)
    if kind == Nodetype.ARRAY:
        return idl_types.array[inner, length]
    return idl_types.sequence[inner, length] if length else idl_types.sequence[inner]

"""Message definitions, type hashes and CDR (de)serialisation for bags, from rosbags' type store.

Pure library: no DDS, no file I/O. The type store is rosbags' ``ROS2_JAZZY`` store (std_msgs,
geometry_msgs, sensor_msgs, nav_msgs, diagnostic_msgs, ...), the same one the middleware runtime
uses, so the schema text, the RIHS01 hash and the CDR bytes agree with what a Jazzy node sends.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any, Mapping

import numpy as np
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

# rosbags' numpy dtypes for primitive sequences / arrays (CDR is little endian on the wire here).
_PRIMITIVE_DTYPES: dict[str, str] = {
    'bool': 'bool', 'byte': 'uint8', 'char': 'uint8', 'octet': 'uint8',
    'int8': 'int8', 'uint8': 'uint8', 'int16': 'int16', 'uint16': 'uint16',
    'int32': 'int32', 'uint32': 'uint32', 'int64': 'int64', 'uint64': 'uint64',
    'float32': 'float32', 'float64': 'float64',
}


@lru_cache(maxsize=1)
def jazzy_typestore() -> Typestore:
    """The rosbags type store of ROS 2 Jazzy (cached; building it takes ~100 ms)."""
    return get_typestore(Stores.ROS2_JAZZY)


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
    """The ROS 2 type description hash ``RIHS01_<64 hex>`` of ``type_name``."""
    store = typestore or jazzy_typestore()
    return store.hash_rihs01(require_known_type(type_name, store))


def serialize_message(message: Any, type_name: str, typestore: Typestore | None = None) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of ``message``.

    Args:
        message: a rosbags message object of the type, a ``dict`` of field values (nested dicts
            for nested messages, lists or numpy arrays for sequences; missing fields take the
            type's default), or any object with the fields as attributes (an rclpy message or
            one of the runtime's message classes).
        type_name: ``pkg/msg/Type``.
    """
    store = typestore or jazzy_typestore()
    name = require_known_type(type_name, store)
    return bytes(store.serialize_cdr(to_rosbags_message(message, name, store), name))


def deserialize_message(data: bytes | memoryview, type_name: str,
                        typestore: Typestore | None = None) -> Any:
    """The rosbags message object decoded from CDR ``data`` of type ``type_name``."""
    store = typestore or jazzy_typestore()
    return store.deserialize_cdr(data, require_known_type(type_name, store))


def to_rosbags_message(message: Any, type_name: str, typestore: Typestore | None = None,
                       *, field_path: str = '') -> Any:
    """Convert ``message`` (rosbags object, dict, or attribute-bearing object) to rosbags' class.

    Raises:
        ValueError: a field has a value that cannot be converted; the message names the field.
    """
    store = typestore or jazzy_typestore()
    cls = store.types[type_name]
    if isinstance(message, cls):
        return message
    _, fields = store.fielddefs[type_name]
    values: dict[str, Any] = {}
    for field_name, desc in fields:
        path = f'{field_path}.{field_name}' if field_path else field_name
        if isinstance(message, Mapping):
            raw = message.get(field_name, None)
        else:
            raw = getattr(message, field_name, None)
        try:
            values[field_name] = _convert_field(raw, desc, store, path)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, _FieldError):
                raise
            raise _FieldError(f'field {path!r} of {type_name}: {exc}') from exc
    if isinstance(message, Mapping):
        unknown = set(message) - {name for name, _ in fields}
        if unknown:
            raise ValueError(f'{type_name} has no field(s) {sorted(unknown)} '
                             f'(at {field_path or "top level"})')
    return cls(**values)


class _FieldError(ValueError):
    """A conversion error already carrying the field path."""


def _convert_field(raw: Any, desc: tuple[Any, Any], store: Typestore, path: str) -> Any:
    """One field value in rosbags' representation (``raw is None`` -> the type default)."""
    kind, detail = desc
    if kind == Nodetype.BASE:
        base, _ = detail
        if base == 'string':
            return '' if raw is None else str(raw)
        if raw is None:
            return False if base == 'bool' else 0 if 'int' in base or base in (
                'byte', 'char', 'octet') else 0.0
        if base == 'bool':
            return bool(raw)
        if base.startswith('float'):
            return float(raw)
        return int(raw)
    if kind == Nodetype.NAME:
        sub = detail
        if raw is None:
            return to_rosbags_message({}, sub, store, field_path=path)
        return to_rosbags_message(raw, sub, store, field_path=path)
    (sub_kind, sub_detail), length = detail
    items = [] if raw is None else raw
    if sub_kind == Nodetype.BASE:
        base = sub_detail[0]
        if base == 'string':
            out = [str(item) for item in items]
        else:
            out = np.asarray(items, dtype=_PRIMITIVE_DTYPES[base]).reshape(-1)
    else:
        out = [to_rosbags_message(item, sub_detail, store, field_path=f'{path}[{i}]')
               for i, item in enumerate(items)]
    if kind == Nodetype.ARRAY:
        if raw is None:
            if sub_kind == Nodetype.BASE and sub_detail[0] != 'string':
                return np.zeros(length, dtype=_PRIMITIVE_DTYPES[sub_detail[0]])
            if sub_kind == Nodetype.BASE:
                return [''] * length
            return [to_rosbags_message({}, sub_detail, store, field_path=path)
                    for _ in range(length)]
        if len(out) != length:
            raise _FieldError(f'field {path!r} needs exactly {length} elements, got {len(out)}')
    elif length and len(out) > length:
        raise _FieldError(f'field {path!r} takes at most {length} elements, got {len(out)}')
    return out

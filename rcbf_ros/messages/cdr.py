"""CDR (de)serialisation of ROS 2 messages with rosbags' Jazzy serializers.

Serialized messages are the CDR stream with its 4-byte encapsulation header (``00 01 00 00``
for little-endian XCDR1), as ``rclpy.serialization.serialize_message`` gives them and rosbag2
stores them. Two readers: :func:`deserialize_message` gives the message classes of
:mod:`.classes` and one error for bad bytes (what a subscriber needs); the bag tools'
:func:`deserialize_rosbags_message` gives rosbags' own message objects. One writer,
:func:`serialize_message`, takes a message instance, or with the type name also a ``dict`` of
field values (missing fields take the type's zero) or any object with the fields as attributes.
"""
from __future__ import annotations

import struct
from typing import Any, Mapping

import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys.store import Nodetype, Typestore

from rcbf_ros.messages.classes import Message, rosbags_converter
from rcbf_ros.messages.typestore import (
    jazzy_typestore,
    normalize_type_name,
    PRIMITIVE_DTYPES,
    require_known_type,
    zero_value,
)


def serialize_message(message: Any, type_name: str | None = None,
                      typestore: Typestore | None = None) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of ``message``.

    Args:
        message: without ``type_name``, an instance of a :mod:`.classes` message class (which
            names its type), like rclpy's ``serialize_message(msg)``; with ``type_name``, also
            a rosbags message object, a ``dict`` of field values (nested dicts for nested
            messages, lists or numpy arrays for sequences; missing fields take the type's
            default), or any object with the fields as attributes (an rclpy message).
        type_name: ``pkg/msg/Type`` (or ``pkg/Type``).
        typestore: the type store to use (default: :func:`.typestore.jazzy_typestore`).

    Raises:
        TypeError: no ``type_name`` and ``message`` is not a message instance.
        ValueError: an unknown ``type_name``, or a field value that cannot be converted (the
            message names the field).
    """
    if type_name is None:
        own_type = getattr(message, '_type_name', None)
        if not own_type:
            raise TypeError(f'cannot serialize {type(message).__name__}: not a message instance')
        return bytes(jazzy_typestore().serialize_cdr(message, own_type, little_endian=True))
    store = typestore or jazzy_typestore()
    name = require_known_type(type_name, store)
    return bytes(store.serialize_cdr(to_rosbags_message(message, name, store), name))


class DeserializationError(ValueError):
    """CDR bytes that are not a sample of the message type they were taken as.

    The one error :func:`deserialize_message` raises for bad bytes, whatever the decoder met
    (truncation, a sequence or string length beyond the buffer, a string that is not UTF-8, an
    unsupported encapsulation), so that a subscriber can drop exactly the undecodable samples.
    """


_CDR_ENCAPSULATIONS = {b'\x00\x00': False, b'\x00\x01': True}  # plain CDR: big / little endian
# What rosbags' generated decoders raise on bytes that do not fit the type: its own checks of
# string and sequence lengths (SerdeError), struct and numpy reads past the end, strict UTF-8.
_DECODE_ERRORS = (SerdeError, struct.error, ValueError, IndexError, OverflowError)


def deserialize_message(data: bytes | memoryview, message_type: type[Message] | str) -> Message:
    """Inverse of :func:`serialize_message` (``message_type`` is a class or a type name).

    Bytes after a complete message are ignored, as rmw's CDR deserializers do (a writer may
    pad; DDS has already checked the sample's structure on receipt).

    Raises:
        DeserializationError: ``data`` is not a plain-CDR sample of the type; the message names
            the type and what did not fit.
        ValueError: ``message_type`` is not a known type (the caller's error).
    """
    type_name = message_type if isinstance(message_type, str) else message_type._type_name
    type_name = normalize_type_name(type_name)
    convert = rosbags_converter(type_name)
    view = memoryview(data).cast('B')
    little_endian = _CDR_ENCAPSULATIONS.get(bytes(view[:2]))
    if len(view) < 4 or little_endian is None:
        raise DeserializationError(f'{type_name}: not a plain CDR sample (encapsulation header '
                                   f'{bytes(view[:4]).hex() or "missing"}, expected 00000000 '
                                   'or 00010000 and a body)')
    store = jazzy_typestore()
    msgdef = store.get_msgdef(type_name)
    decode = msgdef.deserialize_cdr_le if little_endian else msgdef.deserialize_cdr_be
    try:
        decoded, _end = decode(view[4:], 0, msgdef.cls, store)
    except _DECODE_ERRORS as exc:
        raise DeserializationError(f'{type_name}: {_one_line(exc)}') from exc
    return convert(decoded)


def _one_line(exc: BaseException) -> str:
    """The exception's text on one line, at most 200 characters (it goes into logs)."""
    text = ' '.join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + '...'


def deserialize_rosbags_message(data: bytes | memoryview, type_name: str,
                                typestore: Typestore | None = None) -> Any:
    """The rosbags message object decoded from CDR ``data`` of type ``type_name`` (rosbags'
    own checks and errors; the bag tools read recorded messages with it)."""
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
        if raw is None:
            return zero_value(base)
        if base == 'string':
            return str(raw)
        if base == 'bool':
            return bool(raw)
        if base.startswith('float'):
            return float(raw)
        return int(raw)
    if kind == Nodetype.NAME:
        return to_rosbags_message({} if raw is None else raw, detail, store, field_path=path)
    (sub_kind, sub_detail), length = detail
    items = [] if raw is None else raw
    if sub_kind == Nodetype.BASE:
        base = sub_detail[0]
        if base == 'string':
            out = [str(item) for item in items]
        else:
            out = np.asarray(items, dtype=PRIMITIVE_DTYPES[base]).reshape(-1)
    else:
        out = [to_rosbags_message(item, sub_detail, store, field_path=f'{path}[{i}]')
               for i, item in enumerate(items)]
    if kind == Nodetype.ARRAY:
        if raw is None:
            if sub_kind == Nodetype.BASE and sub_detail[0] != 'string':
                return np.zeros(length, dtype=PRIMITIVE_DTYPES[sub_detail[0]])
            if sub_kind == Nodetype.BASE:
                return [''] * length
            return [to_rosbags_message({}, sub_detail, store, field_path=path)
                    for _ in range(length)]
        if len(out) != length:
            raise _FieldError(f'field {path!r} needs exactly {length} elements, got {len(out)}')
    elif length and len(out) > length:
        raise _FieldError(f'field {path!r} takes at most {length} elements, got {len(out)}')
    return out

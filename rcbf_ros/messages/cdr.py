"""CDR (de)serialisation of ROS 2 messages with rosbags' Jazzy serializers.

Serialized messages are the CDR stream with its 4-byte encapsulation header (``00 01 00 00``
for little-endian XCDR1), as ``rclpy.serialization.serialize_message`` gives them and rosbag2
stores them. Two readers: :func:`deserialize_message` gives the message classes of
:mod:`.classes` and one error for bad bytes (what a subscriber needs); the bag tools'
:func:`deserialize_rosbags_message` gives rosbags' own message objects. One writer,
:func:`serialize_message`, takes a message instance, or with the type name also a ``dict`` of
field values (missing fields take the type's zero) or any object with the fields as attributes.

``std_msgs/Float64MultiArray``, the type of every vector this package sends, takes a shorter
way through both (the same bytes and the same message, see :func:`serialize_message` and
:func:`deserialize_message`). :func:`float64_multiarray_head` and
:func:`float64_multiarray_fields` are the one writer and the one reader of those bytes: the
message path, :mod:`.conversions`' sections and the filter's fixed layouts (the heads
:class:`rcbf_ros.node_logic.filter_edge.Float64ArrayLayout` keeps) all go through them.
"""
from __future__ import annotations

import functools
import struct
from typing import Any, Mapping

import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys.store import Nodetype, Typestore

from rcbf_ros.messages.classes import get_message, Message, rosbags_converter
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
        if own_type == FLOAT64_MULTIARRAY:
            data = _float64_multiarray_cdr(message)
            if data is not None:
                return data
        return _serialized_by_rosbags(message, own_type)
    store = typestore or jazzy_typestore()
    name = require_known_type(type_name, store)
    return bytes(store.serialize_cdr(to_rosbags_message(message, name, store), name))


def _serialized_by_rosbags(message: Message, type_name: str) -> bytes:
    """rosbags' serializer on a message instance of ours (the general way)."""
    return bytes(jazzy_typestore().serialize_cdr(message, type_name, little_endian=True))


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
    if type_name == FLOAT64_MULTIARRAY:
        message = _float64_multiarray_message(data)
        if message is not None:
            return message
    return _decoded_by_rosbags(data, type_name)


def _decoded_by_rosbags(data: bytes | memoryview, type_name: str) -> Message:
    """rosbags' decoder into our classes (the general way; see :func:`deserialize_message`)."""
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


FLOAT64_MULTIARRAY = 'std_msgs/msg/Float64MultiArray'
CDR_LE_HEADER = b'\x00\x01\x00\x00'
"""The encapsulation header of plain little-endian CDR (XCDR1) as writers send it; a reader
looks at its first two bytes only (the options bytes that follow are the writer's)."""
_UINT32 = struct.Struct('<I')
_TWO_UINT32 = struct.Struct('<II')

Float64Dims = tuple[tuple[str, int, int], ...]
"""``layout.dim`` of a Float64MultiArray as (label, size, stride) per dimension."""


def _float64_multiarray_cdr(message: Any) -> bytes | None:
    """The serialized bytes of a Float64MultiArray instance: the bytes before its values (those
    of :func:`float64_multiarray_head`) and the values, or None when it is not the plain case
    (data not a float64 array, fields of other types): the serializer then says what is
    wrong with it."""
    data = message.data
    if (type(data) is not np.ndarray or data.dtype != np.float64 or data.ndim != 1
            or not data.flags.c_contiguous):
        return None
    layout = message.layout
    try:
        key = tuple((dim.label, dim.size, dim.stride) for dim in layout.dim)
        if not all(type(label) is str and type(size) is int and type(stride) is int
                   for label, size, stride in key) or type(layout.data_offset) is not int:
            return None
        head = float64_multiarray_head(key, layout.data_offset, data.size)
    except Exception:  # noqa: BLE001 - any odd field: the serializer reports it
        return None
    return head + data.astype('<f8', copy=False).tobytes()


@functools.lru_cache(maxsize=256)
def float64_multiarray_head(dims: Float64Dims, data_offset: int, count: int) -> bytes:
    """Everything of a serialized Float64MultiArray before its ``count`` values: the
    encapsulation header, ``layout`` (``dims``, ``data_offset``) and the length of ``data``
    (then the padding to the values' 8-byte alignment, when there are values), as the
    serializer writes them.

    CDR aligns every primitive to its size, counted from the start of the body (after the
    4-byte header); strings are a uint32 length that counts their terminating NUL, then the
    UTF-8 bytes and the NUL.

    Raises:
        TypeError: a label that is not a str (as the message's field refuses it).
        struct.error: a size, stride, offset or count that is not a uint32.
    """
    body = bytearray(_UINT32.pack(len(dims)))
    for label, size, stride in dims:
        if not isinstance(label, str):
            raise TypeError(f"field 'label' of std_msgs/msg/MultiArrayDimension must be str, "
                            f'got {type(label).__name__}')
        text = label.encode('utf-8')
        body += _UINT32.pack(len(text) + 1) + text + b'\x00'
        body += bytes(-len(body) % 4)
        body += _TWO_UINT32.pack(size, stride)
    body += _TWO_UINT32.pack(data_offset, count)  # data_offset, then the length of data
    if count:
        body += bytes(-len(body) % 8)
    return CDR_LE_HEADER + bytes(body)


def float64_multiarray_fields(data: bytes | memoryview
                              ) -> tuple[list[tuple[str, int, int]], int, np.ndarray] | None:
    """(``layout.dim`` as (label, size, stride), ``layout.data_offset``, ``data``) of a plain
    little-endian CDR Float64MultiArray sample, read without building a message (``data``: a
    read-only float64 view of the sample); None for anything but the plain case (big endian,
    a sequence or string running past the end, a label that is not NUL-terminated UTF-8
    without NULs): the decoder then reads it, or says what is wrong. Bytes after a complete
    message are ignored, as the decoder ignores them.

    The one reader of these bytes: :func:`deserialize_message` builds its message from it and
    :func:`rcbf_ros.messages.conversions.sections_from_cdr` its sections.
    """
    view = memoryview(data).cast('B') if not isinstance(data, bytes) else data
    if len(view) < 16 or view[:2] != CDR_LE_HEADER[:2]:
        return None
    end = len(view)
    (count,), pos = _UINT32.unpack_from(view, 4), 8
    if count > (end - pos) // 12:  # every dimension takes at least 12 bytes
        return None
    base = 4  # CDR aligns from the start of the body, after the encapsulation header
    dims = []
    for _ in range(count):
        pos += -(pos - base) % 4
        if pos + 4 > end:
            return None
        (length,), pos = _UINT32.unpack_from(view, pos), pos + 4
        if length < 1 or pos + length > end or view[pos + length - 1] != 0:
            return None
        raw = bytes(view[pos:pos + length - 1])
        if b'\x00' in raw:
            return None
        try:
            label = raw.decode('utf-8')
        except UnicodeDecodeError:
            return None
        pos += length
        pos += -(pos - base) % 4
        if pos + 8 > end:
            return None
        (size, stride), pos = _TWO_UINT32.unpack_from(view, pos), pos + 8
        dims.append((label, size, stride))
    pos += -(pos - base) % 4
    if pos + 8 > end:
        return None
    (data_offset, length), pos = _TWO_UINT32.unpack_from(view, pos), pos + 8
    if length:
        pos += -(pos - base) % 8
    if pos + 8 * length > end:
        return None
    return dims, data_offset, np.frombuffer(view, dtype=np.float64, count=length, offset=pos)


@functools.cache
def _float64_multiarray_classes() -> tuple[type[Message], type[Message], type[Message]]:
    """The message classes of Float64MultiArray, MultiArrayLayout and MultiArrayDimension."""
    return (get_message(FLOAT64_MULTIARRAY), get_message('std_msgs/msg/MultiArrayLayout'),
            get_message('std_msgs/msg/MultiArrayDimension'))


def _float64_multiarray_message(data: bytes | memoryview) -> Message | None:
    """The Float64MultiArray of a plain little-endian CDR sample, as the decoder builds it
    (ints, str labels, ``data`` a read-only float64 view of the sample), or None for anything
    but the plain case (see :func:`float64_multiarray_fields`)."""
    fields = float64_multiarray_fields(data)
    if fields is None:
        return None
    raw_dims, data_offset, values = fields
    array_class, layout_class, dim_class = _float64_multiarray_classes()
    setter = object.__setattr__
    dims = []
    for label, size, stride in raw_dims:
        dim = dim_class.__new__(dim_class)
        setter(dim, 'label', label)
        setter(dim, 'size', size)
        setter(dim, 'stride', stride)
        dims.append(dim)
    layout = layout_class.__new__(layout_class)
    setter(layout, 'dim', dims)
    setter(layout, 'data_offset', data_offset)
    message = array_class.__new__(array_class)
    setter(message, 'layout', layout)
    setter(message, 'data', values)
    return message


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

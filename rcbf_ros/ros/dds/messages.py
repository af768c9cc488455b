"""ROS 2 message classes, CDR and DDS type mirrors generated from rosbags' Jazzy type store.

Every message type is described once, by rosbags' ``ROS2_JAZZY`` type store (field definitions,
CDR serializer, RIHS01 hash). From that description this module generates, cached per type:

- a user-facing message class that behaves like rclpy's generated classes: ``Twist()`` builds
  all-default fields, nested attribute access, scalar fields type-checked on assignment (as
  rclpy does: a ``float64`` field rejects ``int``), primitive arrays and sequences stored as
  numpy arrays of the field's dtype (lists, tuples, numpy arrays and ``bytes`` accepted);
- the Cyclone DDS ``IdlStruct`` mirror (``@final``, XCDR1) named ``pkg::msg::dds_::Type_`` as
  ROS 2's rmw names it; it fixes the DDS topic type, while the bytes themselves come from
  rosbags' serializer (the tests check that both produce identical CDR).

Serialized messages are the CDR stream with its 4-byte encapsulation header (``00 01 00 00``
for little-endian XCDR1), as ``rclpy.serialization.serialize_message`` gives them; a publisher
sends them zero-padded to a multiple of 4 bytes (:func:`dds_payload`).
"""
from __future__ import annotations

import functools
import struct
from typing import Any, Callable

from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as idl_types
import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Nodetype

_NUMPY_DTYPES: dict[str, Any] = {
    'bool': np.bool_, 'byte': np.uint8, 'char': np.uint8, 'int8': np.int8, 'uint8': np.uint8,
    'int16': np.int16, 'uint16': np.uint16, 'int32': np.int32, 'uint32': np.uint32,
    'int64': np.int64, 'uint64': np.uint64, 'float32': np.float32, 'float64': np.float64,
}
_INT_RANGES: dict[str, tuple[int, int]] = {
    'byte': (0, 255), 'char': (0, 255), 'int8': (-2**7, 2**7 - 1), 'uint8': (0, 2**8 - 1),
    'int16': (-2**15, 2**15 - 1), 'uint16': (0, 2**16 - 1), 'int32': (-2**31, 2**31 - 1),
    'uint32': (0, 2**32 - 1), 'int64': (-2**63, 2**63 - 1), 'uint64': (0, 2**64 - 1),
}
_IDL_PRIMITIVES: dict[str, Any] = {
    'bool': bool, 'byte': idl_types.byte, 'char': idl_types.uint8, 'int8': idl_types.int8,
    'uint8': idl_types.uint8, 'int16': idl_types.int16, 'uint16': idl_types.uint16,
    'int32': idl_types.int32, 'uint32': idl_types.uint32, 'int64': idl_types.int64,
    'uint64': idl_types.uint64, 'float32': idl_types.float32, 'float64': idl_types.float64,
}


DECLARED_DEFAULTS: dict[tuple[str, str], Any] = {
    ('geometry_msgs/msg/Quaternion', 'w'): 1.0,
    ('sensor_msgs/msg/NavSatStatus', 'status'): -2,
}
"""The non-zero default values that Jazzy's .msg files declare (``float64 w 1``), which
rclpy's generated classes start with and rosbags' type store does not keep; every other field
starts at zero, False, '' or empty."""


@functools.cache
def typestore() -> Any:
    """The rosbags ROS 2 Jazzy type store (one per process)."""
    return get_typestore(Stores.ROS2_JAZZY)


def normalize_type_name(type_name: str) -> str:
    """``'std_msgs/Float64'`` or ``'std_msgs/msg/Float64'`` -> ``'std_msgs/msg/Float64'``."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f'message type name {type_name!r} is not of the form pkg/msg/Type')
    return '/'.join(parts)


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


def type_hash(type_name: str) -> str:
    """The RIHS01 type hash string of a message type (``'RIHS01_<64 hex>'``)."""
    return typestore().hash_rihs01(normalize_type_name(type_name))


class Message:
    """Base of the generated message classes (rclpy-like behaviour, see the module docstring)."""

    __slots__ = ()
    _type_name: str = ''
    _field_names: tuple[str, ...] = ()
    _coerce: dict[str, Callable[[Any], Any]] = {}
    _defaults: dict[str, Callable[[], Any]] = {}
    _field_types: dict[str, str] = {}

    def __init__(self, **kwargs: Any) -> None:
        unknown = set(kwargs) - set(self._field_names)
        if unknown:
            raise TypeError(f'{self._type_name} has no field(s) {sorted(unknown)}; '
                            f'fields are {list(self._field_names)}')
        for name in self._field_names:
            if name in kwargs:
                setattr(self, name, kwargs[name])
            else:
                object.__setattr__(self, name, self._defaults[name]())

    def __setattr__(self, name: str, value: Any) -> None:
        coerce = self._coerce.get(name)
        if coerce is None:
            raise AttributeError(f'{self._type_name} has no field {name!r}')
        object.__setattr__(self, name, coerce(value))

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in self._field_names:
            mine, theirs = getattr(self, name), getattr(other, name)
            if isinstance(mine, np.ndarray):
                if not np.array_equal(mine, theirs):
                    return False
            elif mine != theirs:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        inner = ', '.join(f'{n}={getattr(self, n)!r}' for n in self._field_names)
        return f'{self._type_name.replace("/msg/", ".msg.").replace("/", ".")}({inner})'

    @classmethod
    def get_fields_and_field_types(cls) -> dict[str, str]:
        """Field name -> ROS type string, like rclpy's classmethod of the same name."""
        return dict(cls._field_types)


def _scalar_coercer(type_name: str, field: str, base: str, bound: int) -> Callable[[Any], Any]:
    where = f'field {field!r} of {type_name}'
    if base == 'string':
        def coerce_string(value: Any) -> str:
            if not isinstance(value, str):
                raise TypeError(f'{where} must be str, got {type(value).__name__}')
            if bound and len(value) > bound:
                raise ValueError(f'{where} is bounded to {bound} characters')
            return value
        return coerce_string
    if base == 'bool':
        def coerce_bool(value: Any) -> bool:
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError(f'{where} must be bool, got {type(value).__name__}')
            return bool(value)
        return coerce_bool
    if base in ('float32', 'float64'):
        def coerce_float(value: Any) -> float:
            if not isinstance(value, (float, np.floating)):
                raise TypeError(f'{where} must be float, got {type(value).__name__}')
            return float(value)
        return coerce_float
    low, high = _INT_RANGES[base]

    def coerce_int(value: Any) -> int:
        if base == 'byte' and isinstance(value, bytes) and len(value) == 1:
            return value[0]  # rclpy represents ``byte`` fields as 1-byte bytes
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise TypeError(f'{where} must be int, got {type(value).__name__}')
        if not low <= value <= high:
            raise ValueError(f'{where} ({base}) out of range: {value}')
        return int(value)
    return coerce_int


def _primitive_array_coercer(type_name: str, field: str, base: str, length: int,
                             fixed: bool) -> Callable[[Any], np.ndarray]:
    dtype = _NUMPY_DTYPES[base]
    where = f'field {field!r} of {type_name}'

    def coerce_array(value: Any) -> np.ndarray:
        if isinstance(value, (bytes, bytearray, memoryview)) and dtype is np.uint8:
            array = np.frombuffer(bytes(value), dtype=np.uint8).copy()
        elif isinstance(value, str):
            raise TypeError(f'{where} must be a sequence of {base}, got str')
        else:
            try:
                array = np.array(value, dtype=dtype)
            except (TypeError, ValueError) as exc:
                raise TypeError(f'{where} must be a sequence of {base}: {exc}') from exc
        if array.ndim != 1:
            raise ValueError(f'{where} must be one-dimensional, got shape {array.shape}')
        if fixed and array.shape[0] != length:
            raise ValueError(f'{where} must have exactly {length} elements, got {array.shape[0]}')
        if not fixed and length and array.shape[0] > length:
            raise ValueError(f'{where} is bounded to {length} elements, got {array.shape[0]}')
        return array
    return coerce_array


def _list_coercer(type_name: str, field: str, item_coerce: Callable[[Any], Any], length: int,
                  fixed: bool) -> Callable[[Any], list]:
    where = f'field {field!r} of {type_name}'

    def coerce_list(value: Any) -> list:
        if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
            raise TypeError(f'{where} must be a list, got {type(value).__name__}')
        items = [item_coerce(item) for item in value]
        if fixed and len(items) != length:
            raise ValueError(f'{where} must have exactly {length} elements, got {len(items)}')
        if not fixed and length and len(items) > length:
            raise ValueError(f'{where} is bounded to {length} elements, got {len(items)}')
        return items
    return coerce_list


def _instance_coercer(type_name: str, field: str, cls: type) -> Callable[[Any], Any]:
    def coerce_instance(value: Any) -> Any:
        if not isinstance(value, cls):
            raise TypeError(f'field {field!r} of {type_name} must be {cls._type_name}, '
                            f'got {type(value).__name__}')
        return value
    return coerce_instance


def _describe(desc: tuple) -> str:
    """rosbags field description -> ROS type string (for ``get_fields_and_field_types``)."""
    kind, detail = desc
    if kind == Nodetype.BASE:
        base, bound = detail
        return f'{base}<={bound}' if bound else base
    if kind == Nodetype.NAME:
        return detail
    sub, length = detail
    inner = _describe(sub)
    if kind == Nodetype.ARRAY:
        return f'{inner}[{length}]'
    return f'sequence<{inner}, {length}>' if length else f'sequence<{inner}>'


def get_message(type_name: str) -> type[Message]:
    """The message class of a ROS type, e.g. ``get_message('geometry_msgs/msg/Twist')``.

    ``'pkg/Type'`` and ``'pkg/msg/Type'`` give the same class.

    Raises:
        ValueError: the type is not in rosbags' ROS 2 Jazzy type store.
    """
    return _message_class(normalize_type_name(type_name))


@functools.cache
def _message_class(type_name: str) -> type[Message]:
    store = typestore()
    if type_name not in store.fielddefs:
        raise ValueError(f'unknown message type {type_name!r} (not in the ROS 2 Jazzy type '
                         'store of rosbags)')
    constants, fields = store.fielddefs[type_name]
    coerce: dict[str, Callable[[Any], Any]] = {}
    defaults: dict[str, Callable[[], Any]] = {}
    field_types: dict[str, str] = {}
    for name, desc in fields:
        kind, detail = desc
        field_types[name] = _describe(desc)
        if kind == Nodetype.BASE:
            base, bound = detail
            coerce[name] = _scalar_coercer(type_name, name, base, bound)
            zero: Any = '' if base == 'string' else False if base == 'bool' else (
                0.0 if base.startswith('float') else 0)
            zero = DECLARED_DEFAULTS.get((type_name, name), zero)
            defaults[name] = functools.partial(lambda z: z, zero)
        elif kind == Nodetype.NAME:
            sub_cls = get_message(detail)
            coerce[name] = _instance_coercer(type_name, name, sub_cls)
            defaults[name] = sub_cls
        else:
            (sub_kind, sub_detail), length = detail
            fixed = kind == Nodetype.ARRAY
            if sub_kind == Nodetype.BASE and sub_detail[0] != 'string':
                dtype = _NUMPY_DTYPES[sub_detail[0]]
                coerce[name] = _primitive_array_coercer(type_name, name, sub_detail[0], length,
                                                        fixed)
                defaults[name] = functools.partial(np.zeros, length if fixed else 0, dtype)
            else:
                if sub_kind == Nodetype.BASE:
                    item = _scalar_coercer(type_name, f'{name}[]', 'string', sub_detail[1])
                    make_item: Callable[[], Any] = str
                else:
                    item_cls = get_message(sub_detail)
                    item = _instance_coercer(type_name, f'{name}[]', item_cls)
                    make_item = item_cls
                coerce[name] = _list_coercer(type_name, name, item, length, fixed)
                defaults[name] = functools.partial(
                    lambda make, n: [make() for _ in range(n)], make_item,
                    length if fixed else 0)
    namespace: dict[str, Any] = {
        '__slots__': tuple(name for name, _ in fields),
        '__doc__': f"ROS 2 message {type_name} (generated from rosbags' Jazzy type store).",
        '_type_name': type_name,
        '_field_names': tuple(name for name, _ in fields),
        '_coerce': coerce,
        '_defaults': defaults,
        '_field_types': field_types,
        '__msgtype__': type_name,
    }
    for const_name, _const_type, value in constants:
        namespace[const_name] = value
    cls = type(type_name.rsplit('/', 1)[1], (Message,), namespace)
    cls.__module__ = type_name.split('/')[0] + '.msg'
    return cls


def _converter(type_name: str) -> Callable[[Any], Message]:
    """A function that turns rosbags' deserialized object of ``type_name`` into our class."""
    return _converters(normalize_type_name(type_name))


@functools.cache
def _converters(type_name: str) -> Callable[[Any], Message]:
    cls = get_message(type_name)
    _, fields = typestore().fielddefs[type_name]
    plan: list[tuple[str, Callable[[Any], Any] | None]] = []
    for name, (kind, detail) in fields:
        if kind == Nodetype.NAME:
            plan.append((name, _converters(detail)))
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            sub = _converters(detail[0][1])
            plan.append((name, lambda items, sub=sub: [sub(i) for i in items]))
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][1][0] == 'string':
            plan.append((name, list))
        else:
            plan.append((name, None))
    setter = object.__setattr__

    def convert(source: Any) -> Message:
        message = cls.__new__(cls)
        for name, conv in plan:
            value = getattr(source, name)
            setter(message, name, value if conv is None else conv(value))
        return message
    return convert


def serialize_message(message: Message) -> bytes:
    """CDR bytes (with the 4-byte encapsulation header) of a message, like rclpy's."""
    type_name = getattr(message, '_type_name', None)
    if not type_name:
        raise TypeError(f'cannot serialize {type(message).__name__}: not a message instance')
    return bytes(typestore().serialize_cdr(message, type_name, little_endian=True))


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
    """
    type_name = message_type if isinstance(message_type, str) else message_type._type_name
    type_name = normalize_type_name(type_name)
    convert = _converter(type_name)  # an unknown type is the caller's error: ValueError
    view = memoryview(data).cast('B')
    little_endian = _CDR_ENCAPSULATIONS.get(bytes(view[:2]))
    if len(view) < 4 or little_endian is None:
        raise DeserializationError(f'{type_name}: not a plain CDR sample (encapsulation header '
                                   f'{bytes(view[:4]).hex() or "missing"}, expected 00000000 '
                                   'or 00010000 and a body)')
    msgdef = typestore().get_msgdef(type_name)
    decode = msgdef.deserialize_cdr_le if little_endian else msgdef.deserialize_cdr_be
    try:
        decoded, _end = decode(view[4:], 0, msgdef.cls, typestore())
    except _DECODE_ERRORS as exc:
        raise DeserializationError(f'{type_name}: {_one_line(exc)}') from exc
    return convert(decoded)


def _one_line(exc: BaseException) -> str:
    """The exception's text on one line, at most 200 characters (it goes into logs)."""
    text = ' '.join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + '...'


def message_type_name(message_type: type[Message] | str) -> str:
    """The ``pkg/msg/Type`` name of a message class (ours or rclpy-like) or name string."""
    if isinstance(message_type, str):
        return normalize_type_name(message_type)
    name = getattr(message_type, '_type_name', None)
    if not name:
        raise TypeError(f'{message_type!r} is not a message class')
    return name


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

"""ROS 2 message classes generated from the Jazzy type store, behaving like rclpy's.

From rosbags' description of a type (:mod:`.typestore`) this module generates, cached per type,
a message class that behaves like rclpy's generated classes: ``Twist()`` builds all-default
fields, nested attribute access, scalar fields type-checked on assignment (as rclpy does: a
``float64`` field rejects ``int``), primitive arrays and sequences stored as numpy arrays of the
field's dtype (lists, tuples, numpy arrays and ``bytes`` accepted). Instances serialize with
rosbags' CDR serializer as they are (:func:`rcbf_ros.messages.cdr.serialize_message`).
"""
from __future__ import annotations

import functools
from typing import Any, Callable

import numpy as np
from rosbags.typesys.store import Nodetype

from rcbf_ros.messages.typestore import (
    jazzy_typestore,
    normalize_type_name,
    PRIMITIVE_DTYPES,
    zero_value,
)

_INT_RANGES: dict[str, tuple[int, int]] = {
    'byte': (0, 255), 'char': (0, 255), 'int8': (-2**7, 2**7 - 1), 'uint8': (0, 2**8 - 1),
    'int16': (-2**15, 2**15 - 1), 'uint16': (0, 2**16 - 1), 'int32': (-2**31, 2**31 - 1),
    'uint32': (0, 2**32 - 1), 'int64': (-2**63, 2**63 - 1), 'uint64': (0, 2**64 - 1),
}

DECLARED_DEFAULTS: dict[tuple[str, str], Any] = {
    ('geometry_msgs/msg/Quaternion', 'w'): 1.0,
    ('sensor_msgs/msg/NavSatStatus', 'status'): -2,
}
"""The non-zero default values that Jazzy's .msg files declare (``float64 w 1``), which
rclpy's generated classes start with and rosbags' type store does not keep; every other field
starts at zero, False, '' or empty."""


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
    dtype = PRIMITIVE_DTYPES[base]
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
    store = jazzy_typestore()
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
            zero = DECLARED_DEFAULTS.get((type_name, name), zero_value(base))
            defaults[name] = functools.partial(lambda z: z, zero)
        elif kind == Nodetype.NAME:
            sub_cls = get_message(detail)
            coerce[name] = _instance_coercer(type_name, name, sub_cls)
            defaults[name] = sub_cls
        else:
            (sub_kind, sub_detail), length = detail
            fixed = kind == Nodetype.ARRAY
            if sub_kind == Nodetype.BASE and sub_detail[0] != 'string':
                dtype = PRIMITIVE_DTYPES[sub_detail[0]]
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


def rosbags_converter(type_name: str) -> Callable[[Any], Message]:
    """A function that turns a rosbags message object of ``type_name`` into our class (the
    fields are taken over as they are, not checked again).

    Raises:
        ValueError: the type is not in rosbags' ROS 2 Jazzy type store.
    """
    return _converters(normalize_type_name(type_name))


@functools.cache
def _converters(type_name: str) -> Callable[[Any], Message]:
    cls = get_message(type_name)
    _, fields = jazzy_typestore().fielddefs[type_name]
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


def message_type_name(message_type: type[Message] | str) -> str:
    """The ``pkg/msg/Type`` name of a message class (ours or rclpy-like) or name string."""
    if isinstance(message_type, str):
        return normalize_type_name(message_type)
    name = getattr(message_type, '_type_name', None)
    if not name:
        raise TypeError(f'{message_type!r} is not a message class')
    return name

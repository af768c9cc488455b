"""Message <-> numpy conversion: the one module where message layouts are decided.

Vectors travel as ``std_msgs/Float64MultiArray`` whose ``layout.dim`` entries label consecutive
sections of ``data`` (label, size, stride = size), e.g. a learner's proposal::

    layout.dim = [u: 2, disturbance_mean: 3, disturbance_std: 3, state: 3]
    data       = [u_RL..., mean..., std..., x...]

A message without labels is one unlabelled section (``default_label``), so any controller that
publishes a bare Float64MultiArray (or a ``geometry_msgs/Twist`` or ``TwistStamped``) works in
front of the filter.

States may also come as ``nav_msgs/Odometry`` where the system's state maps onto one
(:data:`ODOMETRY_STATES`: the Unicycle's [x, y, theta] is the pose's position and yaw).
:data:`STATE_LAYOUTS` and :data:`COMMAND_LAYOUTS` name every entry of the shipped systems'
vectors with its unit.

:func:`sections_to_cdr` and :func:`sections_from_cdr` write and read a serialized
Float64MultiArray as sections, without building the message, through the one reader and
writer of those bytes in :mod:`.cdr` (the bytes and arrays of the message route).

The builders (``sections_to_msg``, ``array_to_twist``, ``command_to_msg``, ...) make instances of
the classes the node's runtime publishes: :mod:`rcbf_ros.ros.runtime` names its ``get_message``
at import (:func:`use_message_classes`; rclpy's on rclpy), and before any runtime is imported
they make the middleware-free classes of :mod:`rcbf_ros.messages.classes`. With
``message_class`` (a type name -> class function) they make that function's classes, whatever
the runtime, as the offline bag tools do.
"""
from __future__ import annotations

import math
import struct
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from rcbf_ros.messages import classes, systems
from rcbf_ros.messages.cdr import (
    CDR_LE_HEADER,
    float64_multiarray_fields,
    float64_multiarray_head,
)
from rcbf_ros.messages.sensor import MAX_FRAME_ID

FLOAT64_MULTIARRAY = 'std_msgs/msg/Float64MultiArray'
TWIST = 'geometry_msgs/msg/Twist'
TWIST_STAMPED = 'geometry_msgs/msg/TwistStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'

MessageClass = Callable[[str], Any]
"""A type name -> message class function (rclpy's get_message, or
:func:`rcbf_ros.messages.classes.get_message`)."""

STATE_MESSAGES = {'array': FLOAT64_MULTIARRAY, 'odometry': ODOMETRY}
"""``state_type`` -> message type of a state topic."""
COMMAND_MESSAGES = {'array': FLOAT64_MULTIARRAY, 'twist': TWIST, 'twist_stamped': TWIST_STAMPED}
"""``command_type`` -> message type of a command topic."""

STATE_LAYOUTS: Mapping[str, systems.Layout] = systems.FactView('state')
"""The state vector of each system of the table (:mod:`rcbf_ros.messages.systems`), (name,
unit) per entry, in order."""
COMMAND_LAYOUTS: Mapping[str, systems.Layout] = systems.FactView('command')
"""The command vector u of each system of the table, (name, unit) per entry, in order."""
ODOMETRY_STATES: Mapping[str, str] = systems.FactView('odometry', skip_none=True)
"""The systems whose state a nav_msgs/Odometry holds, and how (others: not supported, e.g.
PVTOL's thrust and operator, or the five cars of car following, are not in one)."""


_runtime_message_class: MessageClass = classes.get_message


def use_message_classes(message_class: MessageClass) -> None:
    """Make the builders' default classes ``message_class``'s: the node runtime's, which it
    publishes (called once by :mod:`rcbf_ros.ros.runtime` at import)."""
    global _runtime_message_class
    _runtime_message_class = message_class


def _message_class(type_name: str, message_class: MessageClass | None = None) -> Any:
    """The class of ``type_name``: ``message_class``'s, else the node runtime's."""
    return (message_class or _runtime_message_class)(type_name)


def sections_to_msg(sections: Mapping[str, Sequence[float] | np.ndarray], *,
                    message_class: MessageClass | None = None) -> Any:
    """Labelled sections -> Float64MultiArray (section order preserved)."""
    msg_cls = _message_class(FLOAT64_MULTIARRAY, message_class)
    dim_cls = _message_class('std_msgs/msg/MultiArrayDimension', message_class)
    msg = msg_cls()
    dims, data = [], []
    for label, values in sections.items():
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        dims.append(dim_cls(label=label, size=int(array.size), stride=int(array.size)))
        data.append(array)
    msg.layout.dim = dims
    msg.data = np.concatenate(data).tolist() if data else []
    return msg


def sections_to_cdr(sections: Mapping[str, Sequence[float] | np.ndarray]) -> bytes:
    """Labelled sections -> the serialized Float64MultiArray (little-endian CDR with its
    encapsulation header, as ``serialize_message`` gives it), without building the message.

    The bytes are those of ``serialize_message(sections_to_msg(sections))``: a publisher
    takes them in place of the message (rclpy's and ours alike). The layout part is computed
    once per sequence of (label, size).
    """
    arrays = [np.asarray(values, dtype=np.float64).reshape(-1) for values in sections.values()]
    dims = tuple((label, array.size, array.size) for label, array in zip(sections, arrays))
    head = float64_multiarray_head(dims, 0, sum(array.size for array in arrays))
    if not arrays:
        return head
    return head + np.concatenate(arrays).astype('<f8', copy=False).tobytes()


def msg_to_sections(msg: Any, default_label: str = 'data') -> dict[str, np.ndarray]:
    """Float64MultiArray -> {label: array}.

    Raises:
        ValueError: naming the dimension, when the sizes do not add up to ``data``, a label is
            repeated (two sections would claim one name), or a label is not a short printable
            name (at most :data:`MAX_LABEL_CHARS`; labels reach logs and diagnostics).
    """
    data = np.array(msg.data, dtype=np.float64).reshape(-1)  # writable copy
    dims = [(dim.label, int(dim.size)) for dim in msg.layout.dim]
    return _split_sections(dims, int(msg.layout.data_offset), data, default_label)


def sections_from_cdr(data: bytes, default_label: str = 'data'
                      ) -> dict[str, np.ndarray] | None:
    """Serialized Float64MultiArray (CDR with its encapsulation header) -> {label: array}, as
    :func:`msg_to_sections` of the decoded message gives it, without building the message.

    Reads the plain little-endian CDR that publishers send. Anything else (big-endian, bytes
    that end early, a label that is not NUL-terminated UTF-8 without NULs, ...) returns None:
    decode those as a message, whose decoder says what is wrong with them. Bytes after a
    complete message are ignored, as the decoders do.

    Raises:
        ValueError: as :func:`msg_to_sections`, for a decoded layout that does not fit.
    """
    fields = float64_multiarray_fields(data)
    if fields is None:
        return None
    dims, data_offset, values = fields
    return _split_sections([(label, size) for label, size, _ in dims], data_offset,
                           values.astype(np.float64), default_label)


_UINT32 = struct.Struct('<I')


def _split_sections(dims: list[tuple[str, int]], data_offset: int, data: np.ndarray,
                    default_label: str) -> dict[str, np.ndarray]:
    """The sections of a Float64MultiArray's ``data`` (a writable float64 copy) by its
    dimensions (label, size) (see :func:`msg_to_sections`)."""
    if not dims:
        return {default_label: data}
    out: dict[str, np.ndarray] = {}
    offset = data_offset
    for index, (raw_label, size) in enumerate(dims):
        label = _checked_label(index, raw_label) or default_label
        if offset + size > data.size:
            raise ValueError(f'layout.dim[{label!r}]: size {size} runs past data '
                             f'({data.size} values)')
        if label in out:
            raise ValueError(f'layout.dim[{label!r}]: label repeated')
        out[label] = data[offset:offset + size].copy()
        offset += size
    if offset != data.size:
        raise ValueError(f'layout: sections cover {offset} of {data.size} values')
    return out


MAX_LABEL_CHARS = 64
"""Longest section label :func:`msg_to_sections` accepts."""


def _checked_label(index: int, label: str) -> str:
    if len(label) > MAX_LABEL_CHARS:
        raise ValueError(f'layout.dim[{index}].label: {len(label)} characters, more than '
                         f'{MAX_LABEL_CHARS}')
    if not label.isprintable():
        raise ValueError(f'layout.dim[{index}].label {label!r}: not printable')
    return label


def twist_to_array(msg: Any, fields: Sequence[str]) -> np.ndarray:
    """Pick Twist fields (``linear.x``, ``angular.z``, ...) into a vector."""
    out = []
    for field_name in fields:
        group, _, axis = field_name.partition('.')
        out.append(float(getattr(getattr(msg, group), axis)))
    return np.asarray(out, dtype=np.float64)


def array_to_twist(values: Sequence[float] | np.ndarray, fields: Sequence[str], *,
                   message_class: MessageClass | None = None) -> Any:
    """Vector -> Twist with the given fields set (others zero)."""
    msg = _message_class(TWIST, message_class)()
    for field_name, value in zip(fields, np.asarray(values, dtype=np.float64)):
        group, _, axis = field_name.partition('.')
        setattr(getattr(msg, group), axis, float(value))
    return msg


def _value_text(value: Any) -> str:
    """A diagnostic value as its KeyValue text (floats printed with repr)."""
    if isinstance(value, float):
        return 'nan' if math.isnan(value) else repr(value)
    return str(value)


def diagnostic_status(*, name: str, level: int, message: str,
                      values: Mapping[str, Any], hardware_id: str = '',
                      message_class: MessageClass | None = None) -> Any:
    """A diagnostic_msgs/DiagnosticStatus with KeyValue pairs (floats printed with repr)."""
    status_cls = _message_class('diagnostic_msgs/msg/DiagnosticStatus', message_class)
    kv_cls = _message_class('diagnostic_msgs/msg/KeyValue', message_class)
    status = status_cls()
    status.level = bytes([level]) if isinstance(status.level, bytes) else level
    status.name = name
    status.message = message
    status.hardware_id = hardware_id
    status.values = [kv_cls(key=str(k), value=_value_text(v)) for k, v in values.items()]
    return status


def diagnostics_to_cdr(*, stamp_ns: int, name: str, level: int, message: str,
                       values: Mapping[str, Any], hardware_id: str = '',
                       frame_id: str = '') -> bytes:
    """A serialized diagnostic_msgs/DiagnosticArray of one status, without building it.

    The bytes are those of ``serialize_message(diagnostic_array(statuses=[diagnostic_status(
    name=..., level=..., message=..., values=..., hardware_id=...)], stamp_ns=...,
    frame_id=...))`` (little-endian CDR with its encapsulation header).

    Raises:
        ValueError: ``level`` is not a byte (0-255), or the stamp does not fit a Time.
    """
    if not 0 <= level <= 255:
        raise ValueError(f'diagnostic level {level} is not a byte')
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not -2**31 <= sec < 2**31:
        raise ValueError(f'stamp {stamp_ns} ns does not fit builtin_interfaces/msg/Time')
    body = bytearray(struct.pack('<iI', sec, nanosec))
    _put_string(body, frame_id)
    body += bytes(-len(body) % 4) + _UINT32.pack(1)  # one status
    body.append(level)
    for text in (name, message, hardware_id):
        _put_string(body, text)
    body += bytes(-len(body) % 4) + _UINT32.pack(len(values))
    for key, value in values.items():
        _put_string(body, str(key))
        _put_string(body, _value_text(value))
    return CDR_LE_HEADER + bytes(body)


def _put_string(body: bytearray, text: str) -> None:
    """Append a CDR string: padding to 4, uint32 length with the NUL, UTF-8 bytes, NUL."""
    if not isinstance(text, str):
        raise TypeError(f'a string field must be str, got {type(text).__name__}')
    encoded = text.encode('utf-8')
    body += bytes(-len(body) % 4) + _UINT32.pack(len(encoded) + 1) + encoded + b'\x00'


def diagnostic_array(*, statuses: Sequence[Any], stamp_ns: int, frame_id: str = '',
                     message_class: MessageClass | None = None) -> Any:
    """A diagnostic_msgs/DiagnosticArray of ``statuses`` (see :func:`diagnostic_status`)
    stamped ``stamp_ns``."""
    msg = _message_class(DIAGNOSTIC_ARRAY, message_class)()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.status = list(statuses)
    return msg


def checked_frame_id(field: str, frame_id: Any) -> str:
    """``frame_id`` of a message's ``field`` when it holds at most :data:`MAX_FRAME_ID`
    characters, the bound of the tf and sensor readers.

    Raises:
        ValueError: naming ``field``, the id shown cut: a longer id (or not a string).
    """
    if not isinstance(frame_id, str):
        raise ValueError(f'{field}: expected a frame id, got {type(frame_id).__name__}')
    if len(frame_id) > MAX_FRAME_ID:
        raise ValueError(f'{field}: {len(frame_id)} characters, more than the bound '
                         f'{MAX_FRAME_ID}: {frame_id[:40]!r}...')
    return frame_id


def twist_stamped_to_array(msg: Any, fields: Sequence[str]) -> np.ndarray:
    """Pick the ``twist`` fields of a TwistStamped into a vector.

    Raises:
        ValueError: naming ``header.frame_id`` when it is longer than :data:`MAX_FRAME_ID`.
    """
    checked_frame_id('header.frame_id', msg.header.frame_id)
    return twist_to_array(msg.twist, fields)


def array_to_twist_stamped(values: Sequence[float] | np.ndarray, fields: Sequence[str],
                           header: Any, *, message_class: MessageClass | None = None) -> Any:
    """Vector -> TwistStamped with ``header`` (stamp and frame_id copied) and the fields set."""
    msg = _message_class(TWIST_STAMPED, message_class)()
    msg.header.stamp.sec = int(header.stamp.sec)
    msg.header.stamp.nanosec = int(header.stamp.nanosec)
    msg.header.frame_id = str(header.frame_id)
    msg.twist = array_to_twist(values, fields, message_class=message_class)
    return msg


def command_to_msg(u: Sequence[float] | np.ndarray, *, type_name: str,
                   twist_fields: Sequence[str], header: Any = None,
                   message_class: MessageClass | None = None) -> Any:
    """The command ``u`` as the safety filter's ``cmd_safe`` of ``type_name``: a
    Float64MultiArray with one section ``u``; a Twist with u in ``twist_fields`` (others 0); a
    TwistStamped like that with ``header``'s stamp and frame_id.

    Raises:
        ValueError: ``type_name`` is not one of :data:`COMMAND_MESSAGES`.
    """
    if type_name == FLOAT64_MULTIARRAY:
        return sections_to_msg({'u': u}, message_class=message_class)
    if type_name == TWIST:
        return array_to_twist(u, twist_fields, message_class=message_class)
    if type_name == TWIST_STAMPED:
        return array_to_twist_stamped(u, twist_fields, header, message_class=message_class)
    raise ValueError(f'command type {type_name!r} is not one of '
                     f'{sorted(COMMAND_MESSAGES.values())}')


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The heading (rad, in [-pi, pi]) of the rotation (x, y, z, w): the angle of the rotated x
    axis projected on the ground plane, atan2(R[1, 0], R[0, 0]).

    The quaternion need not be unit length: both arguments of the atan2 scale with its squared
    norm, so the heading is that of the normalized rotation. It is first divided by its
    largest component, so that no product overflows (1e155) or underflows.

    Raises:
        ValueError: naming ``pose.orientation`` when it is zero (norm <= 1e-6), NaN or inf,
            or points the x axis straight up or down (no heading).
    """
    q = np.array([x, y, z, w], dtype=np.float64)
    if not np.all(np.isfinite(q)):
        raise ValueError('pose.orientation: contains NaN or inf')
    largest = float(np.max(np.abs(q)))
    if not largest > 0.0:
        raise ValueError('pose.orientation: zero quaternion')
    q = q / largest  # its largest component +-1: every product below is in [-4, 4]
    norm2 = float(q @ q)
    if not largest * math.sqrt(norm2) > 1e-6:
        raise ValueError('pose.orientation: zero quaternion (norm <= 1e-6)')
    x, y, z, w = (float(v) for v in q)
    r10 = 2.0 * (x * y + w * z)
    r00 = w * w + x * x - y * y - z * z
    if math.hypot(r10, r00) <= 1e-9 * norm2:
        raise ValueError('pose.orientation: the x axis points straight up or down (no heading)')
    return math.atan2(r10, r00)


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def check_odometry_support(system: Any) -> None:
    """Raise ``ValueError`` naming ``state_type`` unless an Odometry holds ``system``'s state."""
    if system not in ODOMETRY_STATES:
        raise ValueError(f'state_type: odometry holds the state of {sorted(ODOMETRY_STATES)} '
                         f'only, not {system!r} (use state_type array)')


def odometry_to_state(msg: Any, *, system: str, frame_id: str = '', child_frame_id: str = ''
                      ) -> np.ndarray:
    """The state vector of ``system`` held by a nav_msgs/Odometry (:data:`ODOMETRY_STATES`).

    ``child_frame_id`` (when not ''): the robot's frame (``base_frame_id``), whose pose the
    Odometry must give; a message naming no child frame ('') is taken as giving it.

    Raises:
        ValueError: naming the field: a frame id longer than :data:`MAX_FRAME_ID`, a frame
            other than ``frame_id`` (when not ''), a child frame other than
            ``child_frame_id`` (when both are not ''), an orientation without a heading (see
            :func:`yaw_from_quaternion`), or a system whose state an Odometry does not hold
            (naming ``state_type``).
    """
    check_odometry_support(system)
    checked_frame_id('header.frame_id', msg.header.frame_id)
    checked_frame_id('child_frame_id', msg.child_frame_id)
    if frame_id and msg.header.frame_id != frame_id:
        raise ValueError(f'header.frame_id: {msg.header.frame_id!r} is not state_frame_id '
                         f'{frame_id!r}')
    if child_frame_id and msg.child_frame_id and msg.child_frame_id != child_frame_id:
        raise ValueError(f'child_frame_id: {msg.child_frame_id!r} is not base_frame_id '
                         f"{child_frame_id!r}: the pose must be the robot's, in whose frame "
                         "the sources' points are placed (set base_frame_id to the "
                         "odometry's child frame)")
    pose = msg.pose.pose
    q = pose.orientation
    yaw = yaw_from_quaternion(q.x, q.y, q.z, q.w)
    return np.array([pose.position.x, pose.position.y, yaw], dtype=np.float64)


def state_to_odometry(state: Sequence[float] | np.ndarray, *, system: str, stamp_ns: int,
                      frame_id: str, child_frame_id: str,
                      command: Sequence[float] | np.ndarray | None = None) -> Any:
    """A nav_msgs/Odometry holding ``system``'s state (the inverse of
    :func:`odometry_to_state`), stamped ``stamp_ns``; for the Unicycle the twist holds the
    command [v, omega] in the body frame when given.

    Raises:
        ValueError: naming ``state_type`` when an Odometry does not hold the system's state.
    """
    check_odometry_support(system)
    x, y, theta = (float(v) for v in np.asarray(state, dtype=np.float64).reshape(-1)[:3])
    msg = _message_class(ODOMETRY)()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    orientation = msg.pose.pose.orientation
    orientation.x, orientation.y, orientation.z, orientation.w = quaternion_from_yaw(theta)
    if command is not None:
        v, omega = (float(c) for c in np.asarray(command, dtype=np.float64).reshape(-1)[:2])
        msg.twist.twist.linear.x, msg.twist.twist.angular.z = v, omega
    return msg


def stamp_ns(header: Any) -> int:
    """A header's stamp in nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)

"""Message <-> numpy conversion: the one module where message layouts are decided.

Vectors travel as ``std_msgs/Float64MultiArray`` whose ``layout.dim`` entries label consecutive
sections of ``data`` (label, size, stride = size), e.g. a learner's proposal::

    layout.dim = [u: 2, disturbance_mean: 3, disturbance_std: 3, state: 3]
    data       = [u_RL..., mean..., std..., x...]

A message without labels is one unlabelled section (``default_label``), so any controller that
publishes a bare Float64MultiArray (or a ``geometry_msgs/Twist``) works in front of the filter.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

FLOAT64_MULTIARRAY = 'std_msgs/msg/Float64MultiArray'
TWIST = 'geometry_msgs/msg/Twist'


def _message_class(type_name: str) -> Any:
    from rcbf_ros.ros.runtime import get_message
    return get_message(type_name)


def sections_to_msg(sections: Mapping[str, Sequence[float] | np.ndarray]) -> Any:
    """Labelled sections -> Float64MultiArray (section order preserved)."""
    msg_cls = _message_class(FLOAT64_MULTIARRAY)
    dim_cls = _message_class('std_msgs/msg/MultiArrayDimension')
    msg = msg_cls()
    dims, data = [], []
    for label, values in sections.items():
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        dims.append(dim_cls(label=label, size=int(array.size), stride=int(array.size)))
        data.append(array)
    msg.layout.dim = dims
    msg.data = np.concatenate(data).tolist() if data else []
    return msg


def msg_to_sections(msg: Any, default_label: str = 'data') -> dict[str, np.ndarray]:
    """Float64MultiArray -> {label: array}.

    Raises:
        ValueError: naming the dimension, when the sizes do not add up to ``data``, a label is
            repeated (two sections would claim one name), or a label is not a short printable
            name (at most :data:`MAX_LABEL_CHARS`; labels reach logs and diagnostics).
    """
    data = np.array(msg.data, dtype=np.float64).reshape(-1)  # writable copy
    dims = list(msg.layout.dim)
    if not dims:
        return {default_label: data}
    out: dict[str, np.ndarray] = {}
    offset = int(msg.layout.data_offset)
    for index, dim in enumerate(dims):
        label = _checked_label(index, dim.label) or default_label
        size = int(dim.size)
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


def array_to_twist(values: Sequence[float] | np.ndarray, fields: Sequence[str]) -> Any:
    """Vector -> Twist with the given fields set (others zero)."""
    msg = _message_class(TWIST)()
    for field_name, value in zip(fields, np.asarray(values, dtype=np.float64)):
        group, _, axis = field_name.partition('.')
        setattr(getattr(msg, group), axis, float(value))
    return msg


def diagnostic_status(*, name: str, level: int, message: str,
                      values: Mapping[str, Any], hardware_id: str = '') -> Any:
    """A diagnostic_msgs/DiagnosticStatus with KeyValue pairs (floats printed with repr)."""
    status_cls = _message_class('diagnostic_msgs/msg/DiagnosticStatus')
    kv_cls = _message_class('diagnostic_msgs/msg/KeyValue')

    def text(v: Any) -> str:
        if isinstance(v, float):
            return 'nan' if math.isnan(v) else repr(v)
        return str(v)

    status = status_cls()
    status.level = bytes([level]) if isinstance(status.level, bytes) else level
    status.name = name
    status.message = message
    status.hardware_id = hardware_id
    status.values = [kv_cls(key=str(k), value=text(v)) for k, v in values.items()]
    return status

"""std_msgs/Float64MultiArray through the runtime's CDR the short way (rcbf_ros.messages.cdr):
the same bytes as rosbags' serializer, the same message as rosbags' decoder (or its error), and
the filter edge's Float64ArrayLayout reads and writes of one fixed layout, against those two."""
from __future__ import annotations

import struct
from typing import Any

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.messages import cdr
from rcbf_ros.messages.cdr import DeserializationError, deserialize_message, serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.conversions import sections_to_cdr
from rcbf_ros.node_logic.filter_edge import Float64ArrayLayout
from rcbf_ros.ros.dds.messages import dds_payload

ARRAY = 'std_msgs/msg/Float64MultiArray'
Array = get_message(ARRAY)
Dimension = get_message('std_msgs/msg/MultiArrayDimension')
HYPOTHESIS = settings(max_examples=300, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow])

# Labels of every kind: empty, ASCII, non-ASCII, with NULs, lone surrogates (not encodable).
LABELS = st.text(alphabet=st.characters(codec=None, categories=None), max_size=9)
UINT32 = st.integers(0, 2**32 - 1)
VALUES = st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=9)


def _message(dims: list[tuple[str, int, int]], data_offset: int, values: list[float]) -> Any:
    message = Array(data=np.array(values, dtype=np.float64))
    message.layout.dim = [Dimension(label=label, size=size, stride=stride)
                          for label, size, stride in dims]
    message.layout.data_offset = data_offset
    return message


MESSAGES = st.builds(_message, st.lists(st.tuples(LABELS, UINT32, UINT32), max_size=4),
                     UINT32, VALUES)


def _outcome(function: Any, *args: Any) -> Any:
    """The result, or the type and text of what it raised."""
    try:
        return function(*args)
    except Exception as exc:  # noqa: BLE001 - the oracle's exceptions, whatever they are
        return (type(exc), str(exc))


def _fields(message: Any) -> tuple:
    """Every field of a decoded array, with its Python type, the values as bytes, and the
    array's dtype and writability (NaN-safe, unlike ==)."""
    layout = message.layout
    return (type(message), type(layout), type(layout.dim), type(layout.data_offset),
            layout.data_offset,
            [(type(d), type(d.label), d.label, type(d.size), d.size, type(d.stride), d.stride)
             for d in layout.dim],
            type(message.data), message.data.dtype, message.data.flags.writeable,
            message.data.tobytes())


def _same_decoding(fast: Any, general: Any) -> bool:
    if isinstance(general, tuple):  # the general way raised
        return False
    return _fields(fast) == _fields(general)


@HYPOTHESIS
@given(MESSAGES)
def test_serialize_writes_the_bytes_of_rosbags_or_raises_what_it_raises(message):
    fast = _outcome(serialize_message, message)
    general = _outcome(cdr._serialized_by_rosbags, message, ARRAY)
    assert fast == general


def test_serialize_leaves_unusual_data_arrays_to_rosbags():
    message = _message([('u', 2, 2)], 0, [1.0, 2.0, 3.0, 4.0])
    object.__setattr__(message, 'data', np.arange(4.0)[::2])  # not contiguous
    assert cdr._float64_multiarray_cdr(message) is None
    object.__setattr__(message, 'data', np.arange(2, dtype=np.float32))
    assert cdr._float64_multiarray_cdr(message) is None
    assert _outcome(serialize_message, message) == _outcome(cdr._serialized_by_rosbags,
                                                            message, ARRAY)


def _mutations(data: bytes, draw: Any) -> bytes:
    kind = draw(st.sampled_from(['as is', 'flip', 'truncate', 'extend', 'big endian',
                                 'options', 'random']))
    if kind == 'flip':
        out = bytearray(data)
        for position in draw(st.lists(st.integers(0, max(len(out) - 1, 0)), min_size=1,
                                      max_size=3)):
            if out:
                out[position] ^= 1 << draw(st.integers(0, 7))
        return bytes(out)
    if kind == 'truncate':
        return data[:draw(st.integers(0, len(data)))]
    if kind == 'extend':
        return data + draw(st.binary(min_size=1, max_size=12))
    if kind == 'big endian':
        return data[:1] + b'\x00' + data[2:]
    if kind == 'options':
        return data[:2] + draw(st.binary(min_size=2, max_size=2)) + data[4:]
    if kind == 'random':
        return draw(st.binary(max_size=80))
    return data


@HYPOTHESIS
@given(MESSAGES, st.data())
def test_deserialize_builds_what_rosbags_builds_or_leaves_the_bytes_to_it(message, draw):
    wire = _outcome(cdr._serialized_by_rosbags, message, ARRAY)
    if isinstance(wire, tuple):  # a label that does not encode
        return
    data = _mutations(wire, draw.draw)
    general = _outcome(cdr._decoded_by_rosbags, data, ARRAY)
    fast = cdr._float64_multiarray_message(data)
    if fast is not None:
        assert _same_decoding(fast, general), data.hex()
    assert _outcome(deserialize_message, data, ARRAY).__class__ is general.__class__
    if isinstance(general, tuple):
        assert general[0] is DeserializationError
        assert _outcome(deserialize_message, data, ARRAY) == general
    if data == wire and '\x00' not in ''.join(d.label for d in message.layout.dim):
        assert fast is not None  # every plain sample is read the short way


def test_deserialize_reads_a_bytearray_and_a_memoryview_as_rosbags_does():
    wire = serialize_message(_message([('u', 2, 2)], 0, [1.5, -2.0]))
    for data in (bytearray(wire), memoryview(wire), memoryview(bytearray(wire))):
        assert _same_decoding(cdr._float64_multiarray_message(data),
                              cdr._decoded_by_rosbags(data, ARRAY))


SECTIONS = st.lists(st.tuples(st.text(alphabet=st.characters(exclude_categories=['Cs'],
                                                             exclude_characters='\x00'),
                                      max_size=6),
                              st.integers(0, 5)), min_size=1, max_size=4)


def _layout_dims(sections: list[tuple[str, int]]) -> list[tuple[str, int, int]]:
    if len(sections) == 1 and sections[0][0] == '':
        return []
    return [(label, size, size) for label, size in sections]


@HYPOTHESIS
@given(SECTIONS, st.data())
def test_a_layout_encodes_the_messages_bytes_and_decodes_what_the_decoder_reads(sections, draw):
    layout = Float64ArrayLayout(sections)
    values = draw.draw(st.lists(st.floats(width=64), min_size=layout.size,
                                max_size=layout.size))
    message = _message(_layout_dims(sections), 0, values)
    wire = cdr._serialized_by_rosbags(message, ARRAY)
    assert layout.encode(values) == wire
    assert layout.encode(np.array(values)) == wire
    assert struct.pack(f'<{layout.size}d', *layout.decode(wire)) == struct.pack(
        f'<{layout.size}d', *values)
    assert layout.decode(dds_payload(wire)) is not None  # DDS padding, stated in the options
    data = _mutations(wire, draw.draw)
    decoded = layout.decode(data)
    if decoded is not None:  # then the decoder reads a sample of exactly this layout
        general = cdr._decoded_by_rosbags(data, ARRAY)
        assert [(d.label, d.size, d.stride) for d in general.layout.dim] == _layout_dims(
            sections)
        assert general.layout.data_offset == 0
        assert general.data.tobytes() == struct.pack(f'<{layout.size}d', *decoded)


def test_a_layout_refuses_other_layouts_and_wrong_counts():
    state = Float64ArrayLayout([('state', 3)])
    assert state.decode(sections_to_cdr({'state': [1.0, 2.0]})) is None
    assert state.decode(sections_to_cdr({'x': [1.0, 2.0, 3.0]})) is None
    assert state.decode(sections_to_cdr({'state': [1.0, 2.0, 3.0], 'u': [1.0]})) is None
    assert state.decode(sections_to_cdr({'': [1.0, 2.0, 3.0]})) is None  # a labelled ''
    assert state.decode(bytearray(sections_to_cdr({'state': [1.0, 2.0, 3.0]}))) is None
    unlabelled = Float64ArrayLayout([('', 3)])
    bare = Array(data=[1.0, 2.0, 3.0])
    assert unlabelled.decode(serialize_message(bare)) == (1.0, 2.0, 3.0)
    assert unlabelled.head == serialize_message(bare)[:-24]
    with pytest.raises(ValueError, match='expected 3 values, got 2'):
        state.encode([1.0, 2.0])

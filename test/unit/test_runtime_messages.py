"""Messages of the Cyclone runtime: CDR equals rosbags', equals Cyclone's own IDL serializer,
deserialization inverts it, and the classes behave like rclpy's."""
from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Nodetype

from rcbf_ros.messages.cdr import deserialize_message, serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.messages import dds_payload, dds_type_name, idl_struct, ros_type_name

STORE = get_typestore(Stores.ROS2_JAZZY)

# Field values (nested dicts); non-empty sequences, strings and nested arrays everywhere.
_TIME = {'sec': 1_700_000_000, 'nanosec': 123_456_789}
_HEADER = {'stamp': _TIME, 'frame_id': 'base_link'}
_TWIST = {'linear': {'x': 1.5, 'y': -2.0, 'z': 0.25}, 'angular': {'x': 0.0, 'y': 0.1, 'z': -3.0}}
_POSE = {'position': {'x': 1.0, 'y': 2.0, 'z': 3.0},
         'orientation': {'x': 0.0, 'y': 0.0, 'z': 0.38268343, 'w': 0.92387953}}
SAMPLES: dict[str, dict[str, Any]] = {
    'std_msgs/msg/Float64MultiArray': {
        'layout': {'dim': [{'label': 'rows', 'size': 2, 'stride': 6},
                           {'label': 'cols', 'size': 3, 'stride': 3}], 'data_offset': 1},
        'data': [0.5, -1.25, 3.0, 1e-300, -0.0, 7.0]},
    'std_msgs/msg/Float64': {'data': -2.718281828},
    'std_msgs/msg/Bool': {'data': True},
    'std_msgs/msg/String': {'data': 'héllo wörld'},
    'std_msgs/msg/Header': _HEADER,
    'builtin_interfaces/msg/Time': _TIME,
    'geometry_msgs/msg/Twist': _TWIST,
    'geometry_msgs/msg/TwistStamped': {'header': _HEADER, 'twist': _TWIST},
    'geometry_msgs/msg/PoseStamped': {'header': _HEADER, 'pose': _POSE},
    'geometry_msgs/msg/Pose2D': {'x': 0.1, 'y': -0.2, 'theta': 3.1},
    'nav_msgs/msg/Odometry': {
        'header': _HEADER, 'child_frame_id': 'imu',
        'pose': {'pose': _POSE, 'covariance': [float(k) for k in range(36)]},
        'twist': {'twist': _TWIST, 'covariance': [0.5 * k for k in range(36)]}},
    'diagnostic_msgs/msg/DiagnosticArray': {
        'header': _HEADER,
        'status': [
            {'level': b'\x01', 'name': 'safety_filter', 'message': 'slack active',
             'hardware_id': 'qp',
             'values': [{'key': 'h_0', 'value': '0.12'}, {'key': 'solve_us', 'value': '41'}]},
            {'level': b'\x00', 'name': 'learner', 'message': '', 'hardware_id': '',
             'values': []},
            {'level': b'\x02', 'name': 'sim', 'message': 'x', 'hardware_id': 'h',
             'values': [{'key': 'k', 'value': 'v'}]}]},
}


def _build(type_name: str, values: dict[str, Any], *, native: bool) -> Any:
    """Build the message from ``values``: rosbags' own dataclass (native) or our class."""
    _, fields = STORE.fielddefs[type_name]
    kwargs = {}
    for name, (kind, detail) in fields:
        if name not in values:
            raise AssertionError(f'sample of {type_name} misses {name}')
        value = values[name]
        if kind == Nodetype.NAME:
            value = _build(detail, value, native=native)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (sub_kind, sub_detail), _ = detail
            if sub_kind == Nodetype.NAME:
                value = [_build(sub_detail, item, native=native) for item in value]
            elif native and sub_detail[0] != 'string':
                value = np.array(value, dtype=np.float64 if sub_detail[0] == 'float64'
                                 else np.int64)
        elif native and isinstance(value, bytes):  # rosbags wants int, rclpy-style is bytes
            value = value[0]
        kwargs[name] = value
    if native:
        return STORE.types[type_name](**kwargs)
    return get_message(type_name)(**kwargs)


def _idl_value(type_name: str, values: dict[str, Any]) -> Any:
    """The same values as an instance of the Cyclone IdlStruct mirror."""
    _, fields = STORE.fielddefs[type_name]
    kwargs = {}
    for name, (kind, detail) in fields:
        value = values[name]
        if kind == Nodetype.NAME:
            value = _idl_value(detail, value)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            value = [_idl_value(detail[0][1], item) for item in value]
        elif isinstance(value, bytes):
            value = value[0]
        kwargs[name] = value
    return idl_struct(type_name)(**kwargs)


@pytest.mark.parametrize('type_name', sorted(SAMPLES))
def test_cdr_equals_rosbags_and_cyclone_and_round_trips(type_name):
    ours = _build(type_name, SAMPLES[type_name], native=False)
    wire = serialize_message(ours)
    reference = bytes(STORE.serialize_cdr(_build(type_name, SAMPLES[type_name], native=True),
                                          type_name))
    assert wire == reference
    assert wire[:4] == b'\x00\x01\x00\x00'  # little-endian plain CDR (XCDR1)
    # Cyclone's own serializer of the generated @final IDL mirror writes the same bytes.
    assert _idl_value(type_name, SAMPLES[type_name]).serialize() == reference
    back = deserialize_message(wire, get_message(type_name))
    assert back == ours
    assert serialize_message(back) == wire


def test_deserialize_accepts_what_cyclone_writes():
    sample = SAMPLES['diagnostic_msgs/msg/DiagnosticArray']
    data = _idl_value('diagnostic_msgs/msg/DiagnosticArray', sample).serialize()
    message = deserialize_message(data, 'diagnostic_msgs/msg/DiagnosticArray')
    assert [s.name for s in message.status] == ['safety_filter', 'learner', 'sim']
    assert [(kv.key, kv.value) for kv in message.status[0].values] == [('h_0', '0.12'),
                                                                     ('solve_us', '41')]
    assert message.status[2].level == 2


def test_byte_fields_accept_rclpy_bytes_and_ints():
    status = get_message('diagnostic_msgs/msg/DiagnosticStatus')(level=b'\x02')
    assert status.level == 2
    status.level = get_message('diagnostic_msgs/msg/DiagnosticStatus').ERROR
    assert serialize_message(status)[4] == 2


def test_dds_type_names_follow_rmw_convention():
    assert dds_type_name('std_msgs/msg/Float64MultiArray') == \
        'std_msgs::msg::dds_::Float64MultiArray_'
    assert idl_struct('geometry_msgs/msg/Twist').__idl_typename__ == \
        'geometry_msgs::msg::dds_::Twist_'
    assert ros_type_name('nav_msgs::msg::dds_::Odometry_') == 'nav_msgs/msg/Odometry'
    assert ros_type_name('DCPSParticipant') == 'DCPSParticipant'


def test_type_hash_is_rosbags_rihs01():
    assert messages.type_hash('std_msgs/String') == STORE.hash_rihs01('std_msgs/msg/String')
    assert messages.type_hash('std_msgs/msg/String').startswith('RIHS01_')


def test_defaults_nesting_and_numpy_like_rclpy():
    odometry = get_message('nav_msgs/msg/Odometry')()
    assert odometry.header.stamp.sec == 0 and odometry.header.frame_id == ''
    assert odometry.pose.covariance.shape == (36,) and odometry.pose.covariance.dtype == np.float64
    odometry.header.stamp.sec = 5
    assert odometry.header.stamp.sec == 5
    array = get_message('std_msgs/msg/Float64MultiArray')(data=np.arange(3.0))
    array.data = (1.0, 2.0)
    assert array.data.tolist() == [1.0, 2.0]
    source = np.ones(2)
    array.data = source
    source[0] = 9.0
    assert array.data.tolist() == [1.0, 1.0]  # assignment copies, like rclpy's array.array
    assert get_message('sensor_msgs/msg/NavSatStatus').STATUS_FIX == 0
    assert get_message('std_msgs/Float64') is get_message('std_msgs/msg/Float64')


def test_declared_defaults_are_rclpys():
    """``float64 w 1`` in Quaternion.msg: rclpy starts an Odometry's orientation at the
    identity (w = 1), and so does a message of ours; the default goes on the wire."""
    assert get_message('nav_msgs/msg/Odometry')().pose.pose.orientation.w == 1.0
    assert get_message('sensor_msgs/msg/NavSatStatus')().status == -2
    quaternion = serialize_message(get_message('geometry_msgs/msg/Quaternion')())
    assert struct.unpack_from('<4d', quaternion, 4) == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize('type_name, field, value, error, words', [
    ('std_msgs/msg/Float64', 'data', 1, TypeError, ['data', 'float']),
    ('std_msgs/msg/Bool', 'data', 1, TypeError, ['data', 'bool']),
    ('std_msgs/msg/String', 'data', b'x', TypeError, ['data', 'str']),
    ('builtin_interfaces/msg/Time', 'sec', 2**31, ValueError, ['sec', 'range']),
    ('builtin_interfaces/msg/Time', 'nanosec', -1, ValueError, ['nanosec']),
    ('geometry_msgs/msg/PoseWithCovariance', 'covariance', [0.0] * 35, ValueError,
     ['covariance', '36']),
    ('std_msgs/msg/Float64MultiArray', 'data', [[1.0]], ValueError, ['data']),
    ('geometry_msgs/msg/TwistStamped', 'twist', 3.0, TypeError, ['twist', 'Twist']),
    ('diagnostic_msgs/msg/DiagnosticStatus', 'values', ['k'], TypeError, ['values']),
])
def test_bad_assignment_names_the_field(type_name, field, value, error, words):
    message = get_message(type_name)()
    with pytest.raises(error) as info:
        setattr(message, field, value)
    assert all(word in str(info.value) for word in words)


def test_unknown_field_and_type_are_clear_errors():
    with pytest.raises(TypeError, match='lineer'):
        get_message('geometry_msgs/msg/Twist')(lineer=None)
    with pytest.raises(AttributeError, match='lineer'):
        get_message('geometry_msgs/msg/Twist')().lineer = 1.0
    with pytest.raises(ValueError, match='no_msgs/msg/Nothing'):
        get_message('no_msgs/msg/Nothing')
    with pytest.raises(ValueError, match='pkg/msg/Type'):
        get_message('Twist')


# --- malformed CDR: one error type, naming the type ---------------------------------------------
ARRAY = 'std_msgs/msg/Float64MultiArray'


def _valid_array() -> bytes:
    """``u: [1.0, 0.5]``; body offsets (after the 4-byte header): dim count 0, label length 4,
    label 8, size 12, stride 16, data_offset 20, data count 24, data 32."""
    message = get_message(ARRAY)(data=[1.0, 0.5])
    message.layout.dim = [get_message('std_msgs/msg/MultiArrayDimension')(label='u', size=2,
                                                                          stride=2)]
    return serialize_message(message)


def _patched(offset: int, value: bytes) -> bytes:
    data = bytearray(_valid_array())
    data[4 + offset:4 + offset + len(value)] = value
    return bytes(data)


def test_valid_array_layout_is_as_the_malformed_cases_assume():
    data = _valid_array()
    assert struct.unpack_from('<I', data, 4)[0] == 1             # one dimension
    assert struct.unpack_from('<I', data, 8)[0] == 2             # 'u\0'
    assert data[12:14] == b'u\x00'
    assert struct.unpack_from('<I', data, 28)[0] == 2            # two data values
    assert struct.unpack_from('<2d', data, 36) == (1.0, 0.5) and len(data) == 52


MALFORMED = {
    'empty': b'',
    'header only': b'\x00\x01\x00\x00',
    'short header': b'\x00\x01',
    'unknown encapsulation': b'\x07\x07\x00\x00' + _valid_array()[4:],
    'XCDR2 encapsulation': b'\x00\x07\x00\x00' + _valid_array()[4:],
    'huge dimension count': _patched(0, struct.pack('<I', 0xFFFFFFFF)),
    'dimension count beyond the buffer': _patched(0, struct.pack('<I', 1000)),
    'string length beyond the buffer': _patched(4, struct.pack('<I', 0x7FFFFFF0)),
    'string length zero (no terminator room)': _patched(4, struct.pack('<I', 0)),
    'string without terminator': _patched(9, b'x'),
    'non-UTF-8 label': _patched(8, b'\xff'),
    'huge data count': _patched(24, struct.pack('<I', 0xFFFFFFFF)),
    'data count beyond the buffer': _patched(24, struct.pack('<I', 3)),
    'a String sample taken as an array': serialize_message(
        get_message('std_msgs/msg/String')(data='hello world')),
}


@pytest.mark.parametrize('case', sorted(MALFORMED))
def test_malformed_array_raises_deserialization_error_naming_the_type(case):
    with pytest.raises(messages.DeserializationError, match=ARRAY) as info:
        deserialize_message(MALFORMED[case], ARRAY)
    assert isinstance(info.value, ValueError)
    assert '\n' not in str(info.value) and len(str(info.value)) < 300


@pytest.mark.parametrize('type_name', ['std_msgs/msg/Float64MultiArray',
                                       'geometry_msgs/msg/Twist',
                                       'diagnostic_msgs/msg/DiagnosticArray'])
def test_every_truncation_raises_deserialization_error(type_name):
    wire = serialize_message(_build(type_name, SAMPLES[type_name], native=False))
    for length in range(len(wire)):
        with pytest.raises(messages.DeserializationError, match=type_name):
            deserialize_message(wire[:length], type_name)


def test_trailing_bytes_after_a_complete_sample_are_ignored_as_rmw_does():
    wire = _valid_array()
    for extra in (1, 3, 4, 16, 1000):
        message = deserialize_message(wire + b'\x00' * extra, ARRAY)
        assert message.data.tolist() == [1.0, 0.5] and message.layout.dim[0].label == 'u'


@pytest.mark.parametrize('text', ['', 'a', 'ab', 'abc', 'abcd', '{"event": "start"}'])
def test_dds_payload_pads_with_zeros_and_states_the_padding(text):
    cdr = serialize_message(get_message('std_msgs/msg/String')(data=text))
    payload = dds_payload(cdr)
    pad = -len(cdr) % 4
    assert len(payload) % 4 == 0 and len(payload) == len(cdr) + pad
    # XTypes 1.3 7.6.3.1.2: the low two bits of the options count the padding bytes.
    assert payload[:3] == cdr[:3] and payload[3] == cdr[3] | pad
    assert payload[4:len(cdr)] == cdr[4:] and payload[len(cdr):] == bytes(pad)
    assert deserialize_message(payload, 'std_msgs/msg/String').data == text


def test_dds_payload_leaves_aligned_streams_and_pads_stubs():
    aligned = serialize_message(get_message('std_msgs/msg/Float64')(data=1.5))
    assert len(aligned) % 4 == 0 and dds_payload(aligned) is aligned
    assert dds_payload(b'\x00') == b'\x00\x00\x00\x00'


def test_big_endian_sample_decodes():
    native = _build(ARRAY, SAMPLES[ARRAY], native=True)
    wire = bytes(STORE.serialize_cdr(native, ARRAY, little_endian=False))
    assert wire[:2] == b'\x00\x00'
    assert deserialize_message(wire, ARRAY) == _build(ARRAY, SAMPLES[ARRAY], native=False)


def test_very_long_string_decodes():
    text = 'é' * 100_000
    wire = serialize_message(get_message('std_msgs/msg/String')(data=text))
    assert deserialize_message(wire, 'std_msgs/msg/String').data == text


def test_random_and_bit_flipped_bytes_decode_or_raise_deserialization_error():
    rng = np.random.default_rng(7)
    bases = {name: serialize_message(_build(name, SAMPLES[name], native=False))
             for name in (ARRAY, 'geometry_msgs/msg/Twist', 'diagnostic_msgs/msg/DiagnosticArray')}
    outcomes = {'decoded': 0, 'refused': 0}
    for name, wire in bases.items():
        for trial in range(300):
            if trial % 3 == 0:
                data = rng.integers(0, 256, int(rng.integers(0, 120)), dtype=np.uint8).tobytes()
            else:
                flipped = bytearray(wire)
                for _ in range(int(rng.integers(1, 4))):
                    position = int(rng.integers(4 if trial % 3 == 1 else 0, len(flipped)))
                    flipped[position] ^= 1 << int(rng.integers(0, 8))
                data = bytes(flipped)
            try:
                deserialize_message(data, name)
                outcomes['decoded'] += 1
            except messages.DeserializationError:
                outcomes['refused'] += 1
    assert outcomes['decoded'] > 50 and outcomes['refused'] > 50, outcomes


def test_unknown_type_is_not_a_deserialization_error():
    with pytest.raises(ValueError, match='no_msgs/msg/Nothing') as info:
        deserialize_message(_valid_array(), 'no_msgs/msg/Nothing')
    assert not isinstance(info.value, messages.DeserializationError)

"""Messages of the Cyclone runtime: CDR equals rosbags', equals Cyclone's own IDL serializer,
deserialization inverts it, and the classes behave like rclpy's."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Nodetype

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.messages import (
    dds_type_name,
    deserialize_message,
    get_message,
    idl_struct,
    ros_type_name,
    serialize_message,
)

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

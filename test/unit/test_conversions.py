"""Float64MultiArray sections: labels that would make two sections share a name, or that
could not be printed on one line of a log or a diagnostic, are refused with the dimension."""
from __future__ import annotations

import subprocess
import sys

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.messages.conversions import MAX_LABEL_CHARS, msg_to_sections, sections_to_msg
from rcbf_ros.ros.runtime import get_message


def _array(labels_sizes: list[tuple[str, int]]) -> object:
    message = get_message('std_msgs/msg/Float64MultiArray')()
    dim = get_message('std_msgs/msg/MultiArrayDimension')
    message.layout.dim = [dim(label=label, size=size, stride=size)
                          for label, size in labels_sizes]
    message.data = [float(k) for k in range(sum(size for _, size in labels_sizes))]
    return message


def test_sections_round_trip():
    sections = msg_to_sections(sections_to_msg({'u': [1.0, 2.0], 'state': [3.0, 4.0, 5.0]}))
    assert list(sections) == ['u', 'state']
    np.testing.assert_array_equal(sections['state'], [3.0, 4.0, 5.0])


def test_unlabelled_dimension_takes_the_default_label():
    assert list(msg_to_sections(_array([('', 2)]), default_label='u')) == ['u']


@pytest.mark.parametrize('labels, words', [
    ([('u', 1), ('u', 1)], ["'u'", 'repeated']),
    ([('', 1), ('u', 1)], ["'u'", 'repeated']),               # unlabelled is u here
    ([('u', 1), ('x' * (MAX_LABEL_CHARS + 1), 1)], ['dim[1]', 'characters']),
    ([('u\nstate', 2)], ['dim[0]', 'not printable', r'\n']),
    ([('u\x00', 2)], ['dim[0]', 'not printable']),
])
def test_bad_labels_are_refused_naming_the_dimension(labels, words):
    with pytest.raises(ValueError) as info:
        msg_to_sections(_array(labels), default_label='u')
    text = str(info.value)
    assert all(word in text for word in words), text
    assert '\n' not in text and len(text) < 200


def test_replacement_characters_are_printable_labels():
    assert list(msg_to_sections(_array([('u\ufffd', 2)]))) == ['u\ufffd']


# --- nav_msgs/Odometry and TwistStamped ----------------------------------------------------------

def _quaternion_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), by the product of the three rotations."""
    def mul(a, b):
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return np.array([aw * bx + ax * bw + ay * bz - az * by,
                         aw * by - ax * bz + ay * bw + az * bx,
                         aw * bz + ax * by - ay * bx + az * bw,
                         aw * bw - ax * bx - ay * by - az * bz])
    qz = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    qy = np.array([0.0, np.sin(pitch / 2), 0.0, np.cos(pitch / 2)])
    qx = np.array([np.sin(roll / 2), 0.0, 0.0, np.cos(roll / 2)])
    return mul(mul(qz, qy), qx)


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w), the textbook closed form."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_yaw_of_a_quaternion_matches_the_closed_form():
    from rcbf_ros.messages.conversions import yaw_from_quaternion
    rng = np.random.default_rng(11)
    for _ in range(500):
        yaw = rng.uniform(-np.pi, np.pi)
        pitch, roll = rng.uniform(-1.4, 1.4), rng.uniform(-np.pi, np.pi)
        q = _quaternion_zyx(yaw, pitch, roll) * rng.uniform(0.2, 5.0)  # not unit length
        got = yaw_from_quaternion(*q)
        # ZYX Euler angles: the yaw is the heading for |pitch| < pi/2 ...
        assert abs(np.angle(np.exp(1j * (got - yaw)))) < 1e-9
        # ... and the heading of the rotated x axis, atan2(R10, R00), for any rotation.
        rotation = _rotation_matrix(q)
        assert abs(got - np.arctan2(rotation[1, 0], rotation[0, 0])) < 1e-9
        assert abs(yaw_from_quaternion(*-q) - got) < 1e-12  # q and -q: the same rotation
    for yaw in (0.0, 0.5, np.pi / 2, -2.0, 3.0):
        assert yaw_from_quaternion(0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)) == pytest.approx(
            yaw, abs=1e-15)


@pytest.mark.parametrize('quaternion, words', [
    ((0.0, 0.0, 0.0, 0.0), 'zero quaternion'),
    ((0.0, 0.0, float('nan'), 1.0), 'NaN or inf'),
    ((0.0, float('inf'), 0.0, 1.0), 'NaN or inf'),
    ((0.0, np.sin(-np.pi / 4), 0.0, np.cos(-np.pi / 4)), 'straight up or down'),  # pitch 90 deg
])
def test_an_orientation_without_heading_is_refused_naming_the_field(quaternion, words):
    from rcbf_ros.messages.conversions import yaw_from_quaternion
    with pytest.raises(ValueError, match=f'^pose.orientation: .*{words}'):
        yaw_from_quaternion(*quaternion)


@settings(max_examples=300, deadline=None)
@given(yaw=st.floats(-3.1, 3.1), pitch=st.floats(-1.4, 1.4), roll=st.floats(-3.1, 3.1),
       exponent=st.integers(-320, 307))
def test_a_quaternion_of_any_scale_gives_the_heading_of_its_rotation_without_warnings(
        yaw, pitch, roll, exponent):
    """(0, 0, 0, 1e155) is the identity: its products overflow unless it is scaled first."""
    import warnings

    from rcbf_ros.messages.conversions import yaw_from_quaternion
    unit = _quaternion_zyx(yaw, pitch, roll)
    scale = 10.0 ** exponent if exponent > -300 else 5e-324 * 10.0 ** (exponent + 320)
    q = [float(v) * scale for v in unit]
    with warnings.catch_warnings(), np.errstate(all='raise', under='ignore'):
        warnings.simplefilter('error')
        if not np.linalg.norm(np.asarray(q) / scale) * scale > 1e-6:
            with pytest.raises(ValueError, match='^pose.orientation: zero quaternion'):
                yaw_from_quaternion(*q)
            return
        got = yaw_from_quaternion(*q)
    assert abs(np.angle(np.exp(1j * (got - yaw_from_quaternion(*unit))))) < 1e-9


def test_a_huge_identity_quaternion_is_the_identity():
    from rcbf_ros.messages.conversions import yaw_from_quaternion
    assert yaw_from_quaternion(0.0, 0.0, 0.0, 1e155) == 0.0
    assert yaw_from_quaternion(0.0, 0.0, 1.7e308, 1.7e308) == pytest.approx(np.pi / 2)


def test_odometry_holds_the_unicycle_state_and_nothing_else():
    from rcbf_ros.messages.conversions import odometry_to_state, state_to_odometry
    msg = state_to_odometry([1.5, -2.0, 2.5], system='unicycle', stamp_ns=3_250_000_000,
                            frame_id='map', child_frame_id='base_link', command=[1.0, -0.5])
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (3, 250_000_000)
    assert (msg.twist.twist.linear.x, msg.twist.twist.angular.z) == (1.0, -0.5)
    np.testing.assert_allclose(odometry_to_state(msg, system='unicycle', frame_id='map'),
                               [1.5, -2.0, 2.5], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="^header.frame_id: 'map' is not state_frame_id 'odom'"):
        odometry_to_state(msg, system='unicycle', frame_id='odom')
    for system in ('pvtol', 'car_following', 'my_pkg.Robot'):
        with pytest.raises(ValueError, match='^state_type: odometry holds the state of'):
            odometry_to_state(msg, system=system)


def test_twist_stamped_keeps_the_header():
    from rcbf_ros.messages.conversions import array_to_twist_stamped, twist_stamped_to_array
    header = get_message('std_msgs/msg/Header')()
    header.stamp.sec, header.stamp.nanosec, header.frame_id = 7, 8, 'base_link'
    msg = array_to_twist_stamped([0.5, -1.0], ['linear.x', 'angular.z'], header)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (
        7, 8, 'base_link')
    np.testing.assert_array_equal(twist_stamped_to_array(msg, ['linear.x', 'angular.z']),
                                  [0.5, -1.0])


# The bag tools' outputs as plain field dicts, the form the bag writer takes them in: the
# builders with the middleware-free classes must give the same CDR.
_STAMP = {'sec': 12, 'nanosec': 345}
_COMMAND_DICTS = {
    'std_msgs/msg/Float64MultiArray': {
        'layout': {'dim': [{'label': 'u', 'size': 2, 'stride': 2}], 'data_offset': 0},
        'data': [0.75, -0.125]},
    'geometry_msgs/msg/Twist': {'linear': {'x': 0.75, 'y': 0.0, 'z': 0.0},
                                'angular': {'x': 0.0, 'y': 0.0, 'z': -0.125}},
    'geometry_msgs/msg/TwistStamped': {
        'header': {'stamp': _STAMP, 'frame_id': 'base_link'},
        'twist': {'linear': {'x': 0.75, 'y': 0.0, 'z': 0.0},
                  'angular': {'x': 0.0, 'y': 0.0, 'z': -0.125}}},
}


@pytest.mark.parametrize('type_name', sorted(_COMMAND_DICTS))
def test_commands_of_the_pure_classes_serialize_as_their_field_dicts(type_name):
    from rcbf_ros.messages import classes
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.conversions import command_to_msg
    header = classes.get_message('std_msgs/msg/Header')(frame_id='base_link')
    header.stamp.sec, header.stamp.nanosec = _STAMP['sec'], _STAMP['nanosec']
    msg = command_to_msg(np.array([0.75, -0.125]), type_name=type_name,
                         twist_fields=['linear.x', 'angular.z'], header=header,
                         message_class=classes.get_message)
    assert type(msg) is classes.get_message(type_name)
    assert serialize_message(msg) == serialize_message(_COMMAND_DICTS[type_name], type_name)


def test_a_command_type_without_a_layout_is_refused_naming_it():
    from rcbf_ros.messages import classes
    from rcbf_ros.messages.conversions import command_to_msg
    with pytest.raises(ValueError, match="^command type 'std_msgs/msg/Float64' is not one of"):
        command_to_msg([1.0], type_name='std_msgs/msg/Float64', twist_fields=['linear.x'],
                       message_class=classes.get_message)


def test_diagnostics_of_the_pure_classes_serialize_as_their_field_dicts():
    from rcbf_ros.messages import classes
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.conversions import diagnostic_array, diagnostic_status
    status = diagnostic_status(name='safety_filter', level=1, message='corrected',
                               values={'h.obstacle_0': 0.25, 'slack': float('nan'), 'steps': 3},
                               hardware_id='robot', message_class=classes.get_message)
    msg = diagnostic_array(statuses=[status], stamp_ns=1_700_000_000_123_456_789,
                           message_class=classes.get_message)
    expected = {
        'header': {'stamp': {'sec': 1_700_000_000, 'nanosec': 123_456_789}, 'frame_id': ''},
        'status': [{'level': 1, 'name': 'safety_filter', 'message': 'corrected',
                    'hardware_id': 'robot',
                    'values': [{'key': 'h.obstacle_0', 'value': '0.25'},
                               {'key': 'slack', 'value': 'nan'},
                               {'key': 'steps', 'value': '3'}]}]}
    type_name = 'diagnostic_msgs/msg/DiagnosticArray'
    assert serialize_message(msg) == serialize_message(expected, type_name)


_BUILD_BEFORE_ANY_RUNTIME = """
import sys
from rcbf_ros.messages import classes
from rcbf_ros.messages.conversions import array_to_twist, sections_to_msg
built = [sections_to_msg({'u': [1.0]}), array_to_twist([1.0], ['linear.x'])]
assert all(isinstance(msg, classes.Message) for msg in built), built
print(sorted(m for m in sys.modules if m.split('.')[0] in ('cyclonedds', 'rclpy')
             or m.startswith('rcbf_ros.ros')))
"""


def test_the_builders_need_no_middleware():
    """Before any runtime is imported the builders make rcbf_ros.messages' own classes, and
    rcbf_ros.messages loads neither rcbf_ros.ros, nor Cyclone DDS, nor rclpy."""
    result = subprocess.run([sys.executable, '-c', _BUILD_BEFORE_ANY_RUNTIME],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == '[]'


def test_the_builders_make_the_classes_the_runtime_names():
    from rcbf_ros.messages import conversions
    from rcbf_ros.ros import runtime
    asked = []

    def recording(type_name: str) -> type:
        asked.append(type_name)
        return runtime.get_message(type_name)
    conversions.use_message_classes(recording)
    try:
        conversions.array_to_twist([1.0], ['linear.x'])
    finally:
        conversions.use_message_classes(runtime.get_message)
    assert asked == ['geometry_msgs/msg/Twist']


# --- serialized Float64MultiArrays, read and written without building the message ---------------

def _section_sets(rng: np.random.Generator) -> list[dict[str, np.ndarray]]:
    """Fixed cases (empty, empty sections, unlabelled, non-ASCII) and random ones: labels of
    every length modulo 4 and data of every length modulo 2 (so every CDR padding occurs)."""
    cases = [{}, {'u': []}, {'u': [1.0, 2.0]}, {'': [1.0]}, {'ü': [1.0], 'abc': [], 'x': [-0.0]},
             {'u': [np.nan, np.inf, -np.inf, 5e-324]}]
    for _ in range(300):
        cases.append({
            ''.join(chr(int(c)) for c in rng.integers(97, 123, int(rng.integers(0, 9)))) + str(i):
            rng.normal(size=int(rng.integers(0, 6))) for i in range(int(rng.integers(0, 6)))})
    return [{label: np.asarray(values, dtype=np.float64) for label, values in case.items()}
            for case in cases]


def test_sections_to_cdr_is_the_serialized_message():
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.conversions import sections_to_cdr
    for sections in _section_sets(np.random.default_rng(7)):
        assert sections_to_cdr(sections) == serialize_message(sections_to_msg(sections)), sections
    with pytest.raises(TypeError, match='label'):
        sections_to_cdr({1: [1.0]})


def _generic_sections(data: bytes) -> object:
    """What decoding ``data`` as a message and taking its sections gives (or the error)."""
    from rcbf_ros.messages.cdr import DeserializationError, deserialize_message
    try:
        message = deserialize_message(data, 'std_msgs/msg/Float64MultiArray')
    except DeserializationError:
        return 'undecodable'
    try:
        return msg_to_sections(message, default_label='u')
    except ValueError as exc:
        return f'refused: {exc}'


def _fast_sections(data: bytes) -> object:
    from rcbf_ros.messages.conversions import sections_from_cdr
    try:
        return sections_from_cdr(data, default_label='u')
    except ValueError as exc:
        return f'refused: {exc}'


def _same(fast: object, generic: object) -> bool:
    if isinstance(fast, dict) and isinstance(generic, dict):
        return list(fast) == list(generic) and all(
            fast[k].tobytes() == generic[k].tobytes() and fast[k].flags.writeable
            for k in fast)
    return fast == generic


def test_sections_from_cdr_reads_what_the_decoder_reads_or_leaves_it_to_the_decoder():
    """Well-formed samples are read without the decoder, to the same arrays (bit for bit);
    mutated, truncated, extended or random bytes are either read the same way or handed back
    (None) for the decoder to name what is wrong; a layout that does not fit is refused with
    the same words as msg_to_sections."""
    from rcbf_ros.messages.cdr import serialize_message
    rng = np.random.default_rng(11)
    valid = [serialize_message(sections_to_msg(s)) for s in _section_sets(rng)]
    for data in valid:
        fast = _fast_sections(data)
        assert fast is not None and _same(fast, _generic_sections(data))
    mutated = []
    for data in valid[:150]:
        for _ in range(8):
            out = bytearray(data)
            for _ in range(int(rng.integers(1, 4))):
                out[int(rng.integers(0, len(out)))] ^= 1 << int(rng.integers(0, 8))
            mutated.append(bytes(out))
        mutated += [data[:int(rng.integers(0, len(data)))], data + b'\x00\x07' * 3,
                    data[:1] + b'\x00' + data[2:],  # big-endian header
                    rng.integers(0, 256, int(rng.integers(0, 80)), dtype=np.uint8).tobytes()]
    bad_label = bytearray(serialize_message(sections_to_msg({'ab': [1.0]})))
    bad_label[12] = 0xFF  # not UTF-8
    mutated.append(bytes(bad_label))
    handed_back = read = 0
    for data in mutated:
        fast = _fast_sections(data)
        if fast is None:
            handed_back += 1
        else:
            read += 1
            assert _same(fast, _generic_sections(data)), (data.hex(), fast)
    assert handed_back > 50 and read > 200, (handed_back, read)
    # Refused layouts: the words of msg_to_sections.
    overrun = sections_to_msg({'u': [1.0, 2.0]})
    overrun.layout.dim[0].size = 3
    assert _fast_sections(serialize_message(overrun)) == _generic_sections(
        serialize_message(overrun)) == "refused: layout.dim['u']: size 3 runs past data (2 values)"


def test_diagnostics_to_cdr_is_the_serialized_diagnostic_array():
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.conversions import (
        diagnostic_array,
        diagnostic_status,
        diagnostics_to_cdr,
    )
    rng = np.random.default_rng(5)
    choices = [1.5, float('nan'), -0.0, 1e-300, 'ü', True, 3, '', 'abc', None]
    for _ in range(200):
        values = {'k' * int(rng.integers(1, 6)) + str(j): choices[int(rng.integers(0, 10))]
                  for j in range(int(rng.integers(0, 6)))}
        status = dict(name='n' * int(rng.integers(0, 5)), level=int(rng.integers(0, 3)),
                      message='m' * int(rng.integers(0, 7)) + 'é', values=values,
                      hardware_id='h' * int(rng.integers(0, 3)))
        stamp_ns = int(rng.integers(0, 2**31 * 10**9))
        frame_id = 'f' * int(rng.integers(0, 4))
        expected = serialize_message(diagnostic_array(
            statuses=[diagnostic_status(**status)], stamp_ns=stamp_ns, frame_id=frame_id))
        assert diagnostics_to_cdr(stamp_ns=stamp_ns, frame_id=frame_id, **status) == expected
    with pytest.raises(ValueError, match='level 256'):
        diagnostics_to_cdr(stamp_ns=0, name='', level=256, message='', values={})

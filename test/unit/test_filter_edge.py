"""The safety filter's message edge (rcbf_ros.node_logic.filter_edge), without DDS.

Closed forms: what it reads from a sample is what rosbags' own decoder reads from the same
bytes, and what it writes is what rosbags' decoder reads back as the values written. Hostile
bytes (anything, truncated, bit-flipped, huge counts and lengths, NaN): a one-line reason and
the right count, never an exception.
"""
from __future__ import annotations

import math
from pathlib import Path
import struct
from typing import Any

from hypothesis import example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.conversions import (
    array_to_twist,
    array_to_twist_stamped,
    sections_to_cdr,
    sections_to_msg,
    state_to_odometry,
)
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.filter_edge import DROPPED, FilterEdge, REFUSED_PROPOSAL, REFUSED_STATE

ARRAY = 'std_msgs/msg/Float64MultiArray'
FIELDS = ('linear.x', 'angular.z')
HYPOTHESIS = settings(max_examples=200, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow])
FINITE = st.floats(-1e6, 1e6, allow_nan=False, width=64)


def _edge(state_type: str = 'array', command_type: str = 'array') -> FilterEdge:
    return FilterEdge(state_type=state_type, command_type=command_type, system='unicycle',
                      n_x=3, n_u=2)


def _rosbags(data: bytes, type_name: str) -> Any:
    """rosbags' own decoder: the independent reader."""
    return jazzy_typestore().deserialize_cdr(data, type_name)


def _rosbags_sections(data: bytes) -> dict[str, list[float]]:
    message = _rosbags(data, ARRAY)
    values, out, offset = list(message.data), {}, message.layout.data_offset
    for dim in message.layout.dim:
        out[dim.label] = values[offset:offset + dim.size]
        offset += dim.size
    return out


# closed forms --------------------------------------------------------------------------------
@HYPOTHESIS
@given(u=st.lists(FINITE, min_size=2, max_size=2), state=st.lists(FINITE, min_size=3,
                                                                   max_size=3),
       with_state=st.booleans(), unlabelled=st.booleans())
def test_a_proposal_reads_as_rosbags_decodes_it(u, state, with_state, unlabelled):
    sections = {'u': u, 'state': state} if with_state else {'u': u}
    data = (serialize_message(get_bare(u)) if unlabelled and not with_state
            else sections_to_cdr(sections))
    sample = _edge().read_proposal(data, twist_fields=FIELDS)
    assert sample.count == '' and sample.error == '' and not sample.undecodable
    decoded = {'u': list(_rosbags(data, ARRAY).data)} if unlabelled and not with_state \
        else _rosbags_sections(data)
    assert sample.proposal.u.tolist() == decoded['u'] == u
    if with_state:
        assert sample.proposal.state.tolist() == decoded['state']


def get_bare(values: list[float]) -> Any:
    """A Float64MultiArray without layout (what a bare controller publishes)."""
    from rcbf_ros.messages.classes import get_message
    return get_message(ARRAY)(data=np.array(values, dtype=np.float64))


@HYPOTHESIS
@given(state=st.lists(FINITE, min_size=3, max_size=3), label=st.sampled_from(['state', 'x', '']))
def test_a_state_reads_as_rosbags_decodes_it(state, label):
    data = sections_to_cdr({label: state}) if label else serialize_message(get_bare(state))
    sample, count = _edge().read_state(data, received_ns=7)
    assert count == '' and sample.error == '' and sample.received_ns == 7
    expected = list(_rosbags(data, ARRAY).data)
    assert sample.state.tolist() == expected == state


@HYPOTHESIS
@given(u=st.lists(FINITE, min_size=2, max_size=2))
def test_the_command_written_is_the_values_rosbags_reads(u):
    data = _edge().command(np.array(u), twist_fields=FIELDS)
    assert type(data) is bytes
    assert _rosbags_sections(data) == {'u': u}


def _decision(state: list[float], u: list[float]) -> logic.Decision:
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.parameters.rules import load_params
    root = Path(__file__).resolve().parents[2]
    params = load_params(root / 'config' / 'unicycle.yaml', 'safety_filter')
    config = filter_config_from_params(params)
    settings_ = logic.node_settings_from_params(params)
    safety_filter = logic.build_safety_filter(config=config, settings=settings_)
    return logic.decide(safety_filter=safety_filter, proposal=logic.Proposal(u=np.array(u)),
                        latest_state=logic.StateSample(0, np.array(state)), now_ns=0,
                        max_state_age_s=1.0), safety_filter.barrier_names


@pytest.mark.parametrize('state', [[-3.0, 0.0, 0.0], [-0.85, 0.0, 0.0], [np.nan, 0.0, 0.0]])
def test_filter_info_and_diagnostics_read_back_as_written(state):
    """filter_info: the sections of info_sections; diagnostics: one status with the
    decision's level, its key/values and the counts, stamped as asked."""
    decision, names = _decision(state, [1.0, 0.2])
    edge = _edge()
    info = _rosbags_sections(edge.info_cdr(decision))
    expected = {k: v.tolist() for k, v in logic.info_sections(decision).items()}
    assert info == expected
    data = edge.diagnostics_cdr(decision, barrier_names=names, stamp_ns=3_000_000_005,
                                name='filter', hardware_id='base',
                                counts={DROPPED: 4, REFUSED_STATE: 1})
    message = _rosbags(data, 'diagnostic_msgs/msg/DiagnosticArray')
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (3, 5)
    (status,) = message.status
    level, text, values = logic.diagnostic_values(decision=decision, barrier_names=names)
    assert (status.level, status.message, status.name, status.hardware_id) == (
        level, text, 'filter', 'base')
    keys = {kv.key: kv.value for kv in status.values}
    assert keys[DROPPED] == '4' and keys[REFUSED_STATE] == '1'
    assert set(keys) == set(values) | {DROPPED, REFUSED_STATE}


class _Clock:
    """A node clock at a fixed time: ``now()`` as the runtimes' Time (``nanoseconds``)."""

    class _Time:
        nanoseconds = 7_000_000_011

    def now(self) -> Any:
        return self._Time()


ANSWER_SETTINGS = logic.node_settings_from_params({'diagnostics.name': 'filter',
                                                   'diagnostics.hardware_id': 'base'})


def _answer(decision: logic.Decision, names: Any, **timing: Any) -> filter_edge.Answer:
    return _edge().answer(decision, settings=ANSWER_SETTINGS, barrier_names=names, header=None,
                          clock=_Clock(), counts={DROPPED: 2}, **timing)


@pytest.mark.parametrize('state', [[-3.0, 0.0, 0.0], [-0.85, 0.0, 0.0], [np.nan, 0.0, 0.0]])
def test_an_answer_is_its_command_filter_info_and_due_diagnostics_as_rosbags_reads_them(state):
    """One pass: the command's values, filter_info's sections, and the diagnostics exactly
    when due (WARN / ERROR always, OK at most every diagnostics.min_period_s), stamped by the
    clock, with the counts."""
    decision, names = _decision(state, [1.0, 0.2])
    period_ns = int(ANSWER_SETTINGS.diagnostics_min_period_s * 1e9)
    for last_ok_ns, due in ((None, True), (10 - period_ns, True),
                            (11 - period_ns, decision.level != logic.OK)):
        answer = _answer(decision, names, now_ns=10, last_ok_ns=last_ok_ns)
        assert (answer.diagnostics_due, answer.error) == (due, '')
        assert _rosbags_sections(answer.command) == {'u': decision.u_safe.tolist()}
        assert _rosbags_sections(answer.info) == {
            k: v.tolist() for k, v in logic.info_sections(decision).items()}
        if not due:
            assert answer.diagnostics is None
            continue
        message = _rosbags(answer.diagnostics, 'diagnostic_msgs/msg/DiagnosticArray')
        assert (message.header.stamp.sec, message.header.stamp.nanosec) == (7, 11)
        (status,) = message.status
        assert (status.level, status.name, status.hardware_id) == (decision.level, 'filter',
                                                                   'base')
        assert {kv.key: kv.value for kv in status.values}[DROPPED] == '2'


@pytest.mark.parametrize('broken', ['info_cdr', 'diagnostics_cdr'])
def test_a_detail_that_cannot_be_made_leaves_the_command_and_says_why(broken, monkeypatch):
    """The command is made first; a defect making filter_info or the diagnostics after it is
    caught (one line), and what was made before it is kept."""
    decision, names = _decision([-3.0, 0.0, 0.0], [1.0, 0.2])

    def fails(*_args: Any, **_kwargs: Any) -> bytes:
        raise RuntimeError(f'{broken}\nbroken')
    monkeypatch.setattr(filter_edge, broken, fails)
    answer = _answer(decision, names, now_ns=0, last_ok_ns=None)
    assert _rosbags_sections(answer.command) == {'u': [1.0, 0.2]}
    assert answer.error == f'RuntimeError: {broken} broken'
    assert answer.diagnostics is None
    assert (answer.info is None) == (broken == 'info_cdr')


def test_an_answer_whose_command_cannot_be_made_raises():
    """No command, nothing to publish: the caller sends the fail-safe instead."""
    decision, names = _decision([-3.0, 0.0, 0.0], [1.0, 0.2])
    odd = logic.Decision(u_safe=np.array(['x', 'y']), u_rl=None, level=logic.ERROR,
                         reason='odd', fail_safe=True)
    with pytest.raises(ValueError):
        _answer(odd, names, now_ns=0, last_ok_ns=None)


@pytest.mark.parametrize('type_name', ['geometry_msgs/msg/Twist',
                                       'geometry_msgs/msg/TwistStamped'])
def test_twists_read_and_write_in_their_fields(type_name):
    stamped = type_name.endswith('Stamped')
    edge = _edge(command_type='twist_stamped' if stamped else 'twist')
    if stamped:
        from rcbf_ros.messages.classes import get_message
        header = get_message('std_msgs/msg/Header')(frame_id='base')
        header.stamp.sec, header.stamp.nanosec = 12, 34
        message = array_to_twist_stamped([0.5, -0.25], FIELDS, header)
    else:
        message = array_to_twist([0.5, -0.25], FIELDS)
    sample = edge.read_proposal(serialize_message(message), twist_fields=FIELDS)
    assert sample.proposal.u.tolist() == [0.5, -0.25]
    if stamped:
        assert (sample.header.stamp.sec, sample.header.stamp.nanosec,
                sample.header.frame_id) == (12, 34, 'base')
    answer = edge.command(np.array([0.1, 0.2]), twist_fields=FIELDS, header=sample.header)
    read = _rosbags(serialize_message(answer), type_name)
    twist = read.twist if stamped else read
    assert (twist.linear.x, twist.angular.z, twist.linear.y) == (0.1, 0.2, 0.0)
    if stamped:
        assert read.header.frame_id == 'base'


def test_an_odometry_state_is_the_pose_in_its_frame():
    edge = _edge(state_type='odometry')
    data = serialize_message(state_to_odometry([1.0, -2.0, 0.5], system='unicycle',
                                               stamp_ns=0, frame_id='odom',
                                               child_frame_id='base'))
    sample, count = edge.read_state(data, received_ns=0, frame_id='odom')
    assert count == '' and np.allclose(sample.state, [1.0, -2.0, 0.5], atol=1e-12)
    sample, count = edge.read_state(data, received_ns=0, frame_id='map')
    assert count == REFUSED_STATE and sample.state is None
    assert sample.error.startswith('header.frame_id')


@pytest.mark.parametrize('child, robot, kept', [
    ('base', 'base', True), ('', 'base_link', True), ('base_footprint', '', True),
    ('base_footprint', 'base_link', False), ('base_link', 'base_link/', False)])
def test_an_odometry_gives_the_pose_of_the_robot_s_frame_or_is_refused(child, robot, kept):
    # a pose of another frame than the one the sources' points are placed in would put every
    # point where the robot is not (a message naming no child frame is taken as the robot's)
    edge = _edge(state_type='odometry')
    data = serialize_message(state_to_odometry([1.0, -2.0, 0.5], system='unicycle',
                                               stamp_ns=0, frame_id='odom',
                                               child_frame_id=child))
    sample, count = edge.read_state(data, received_ns=0, frame_id='odom', child_frame_id=robot)
    if kept:
        assert count == '' and np.allclose(sample.state, [1.0, -2.0, 0.5], atol=1e-12)
        return
    assert count == REFUSED_STATE and sample.state is None
    assert sample.error.startswith(f'child_frame_id: {child!r} is not base_frame_id {robot!r}')


def test_the_offline_readers_read_what_the_node_reads():
    data = sections_to_cdr({'u': [1.0, 2.0], 'disturbance_std': [0.1, 0.1, 0.1]})
    sections, header = filter_edge.proposal_sections(data, type_name=ARRAY, twist_fields=())
    assert header is None
    assert {k: list(v) for k, v in sections.items()} == _rosbags_sections(data)
    assert list(filter_edge.state_sections(
        serialize_message(sections_to_msg({'state': [1.0, 2.0, 3.0]})), type_name=ARRAY,
        system='unicycle')['state']) == [1.0, 2.0, 3.0]


@pytest.mark.parametrize('reader', ['proposal', 'state'])
def test_a_type_without_a_proposal_or_state_is_refused_naming_it(reader):
    with pytest.raises(ValueError, match='std_msgs/msg/String'):
        if reader == 'proposal':
            filter_edge.proposal_sections(b'\x00\x01\x00\x00', type_name='std_msgs/msg/String',
                                          twist_fields=())
        else:
            filter_edge.state_sections(b'\x00\x01\x00\x00', type_name='std_msgs/msg/String',
                                       system='unicycle')


def test_obstacles_read_as_rows():
    data = serialize_message(get_bare([0.0, 1.0, 0.5, 2.0, 3.0, 0.25]))
    assert _edge().read_obstacles(data) == {'obstacles.x': [0.0, 2.0],
                                            'obstacles.y': [1.0, 3.0],
                                            'obstacles.radius': [0.5, 0.25]}
    with pytest.raises(ValueError, match='^undecodable sample: '):
        _edge().read_obstacles(b'\x00\x01\x00\x00\xff')


# hostile bytes -------------------------------------------------------------------------------
def _huge_count(count: int) -> bytes:
    """A Float64MultiArray whose dimension count (or data length) claims ``count``."""
    return b'\x00\x01\x00\x00' + struct.pack('<I', count) + bytes(8)


VALID = [sections_to_cdr({'u': [1.0, 2.0]}), sections_to_cdr({'state': [1.0, 2.0, 3.0]}),
         sections_to_cdr({'u': [1.0, 2.0], 'state': [0.0, 0.0, 0.0]})]
HOSTILE = st.one_of(
    st.binary(max_size=200),
    st.builds(lambda data, cut: data[:cut], st.sampled_from(VALID), st.integers(0, 80)),
    st.builds(lambda data, at, bit: data[:at] + bytes([data[at] ^ (1 << bit)]) + data[at + 1:],
              st.sampled_from(VALID), st.integers(0, 40), st.integers(0, 7)),
    st.builds(_huge_count, st.sampled_from([2**32 - 1, 2**31, 10**6, 3])),
    st.builds(lambda values: sections_to_cdr({'u': values}),
              st.lists(st.floats(width=64), max_size=5)),
    st.builds(lambda values: sections_to_cdr({'state': values}),
              st.lists(st.floats(width=64), max_size=5)),
)


def _one_line(text: str) -> bool:
    return bool(text) and '\n' not in text and len(text) <= 1000


@HYPOTHESIS
@given(data=HOSTILE)
@example(data=b'')
@example(data=_huge_count(2**32 - 1))
@example(data=sections_to_cdr({'u': [math.nan, 0.0]}))
def test_no_bytes_make_a_reader_raise(data):
    for command_type in ('array', 'twist', 'twist_stamped'):
        sample = _edge(command_type=command_type).read_proposal(data, twist_fields=FIELDS)
        if sample.proposal is None:
            assert sample.count in (DROPPED, REFUSED_PROPOSAL) and _one_line(sample.error)
            assert sample.undecodable == (sample.count == DROPPED)
        else:
            assert sample.count == '' and np.isfinite(sample.proposal.u).all()
    for state_type in ('array', 'odometry'):
        state, count = _edge(state_type=state_type).read_state(data, received_ns=0)
        if state.state is None:
            assert count in (DROPPED, REFUSED_STATE) and _one_line(state.error)
        else:
            assert count == '' and state.state.shape == (3,)
    try:
        _edge().read_obstacles(data)
    except ValueError as exc:
        assert _one_line(str(exc))


def test_nan_and_wrong_lengths_are_refused_naming_the_section():
    edge = _edge()
    for sections, words in (({'u': [math.nan, 0.0]}, 'u: contains NaN'),
                            ({'u': [1.0, 2.0, 3.0]}, 'u: expected 2 values'),
                            ({'u': [1.0, 2.0], 'disturbance_std': [-1.0, 0.0, 0.0]},
                             'disturbance_std'),
                            ({'v': [1.0, 2.0]}, 'v: unknown proposal section')):
        sample = edge.read_proposal(sections_to_cdr(sections), twist_fields=FIELDS)
        assert (sample.proposal, sample.count) == (None, REFUSED_PROPOSAL)
        assert sample.error.startswith(words), sample.error
    state, count = edge.read_state(sections_to_cdr({'state': [0.0, math.inf, 0.0]}),
                                   received_ns=0)
    assert (state.state, count, state.error) == (None, REFUSED_STATE,
                                                 'state: contains NaN or inf')


def test_undecodable_samples_are_dropped_with_the_decoders_reason():
    edge = _edge()
    for data in (b'', b'\x00\x01\x00\x00' + b'\xff' * 3, _huge_count(2**32 - 1)):
        sample = edge.read_proposal(data, twist_fields=FIELDS)
        assert (sample.count, sample.undecodable) == (DROPPED, True)
        assert sample.error.startswith('DeserializationError: '), sample.error
        state, count = edge.read_state(data, received_ns=0)
        assert count == DROPPED and state.error.startswith('undecodable sample: ')


def test_the_refilter_stops_on_an_undecodable_proposal_in_one_line(tmp_path, capsys):
    """A recorded Twist proposal that does not decode: one line naming the topic and its log
    time, exit 2, no output bag left."""
    from rcbf_ros.bag import BagWriter
    from rcbf_ros.bag.refilter import main, refilter_bag, RefilterError
    source = tmp_path / 'run'
    with BagWriter(source) as bag:
        bag.add_topic('/state', ARRAY)
        bag.add_topic('/cmd_proposed', 'geometry_msgs/msg/Twist')
        bag.write_message('/state', sections_to_msg({'state': [-2.0, 0.0, 0.0]}), 10)
        bag.write('/cmd_proposed', b'\x00\x01\x00\x00\x01\x02', 20)
    with pytest.raises(RefilterError, match=r'^/cmd_proposed at log time 20: undecodable '):
        refilter_bag(source, tmp_path / 'out', 'unicycle')
    assert main([str(source), str(tmp_path / 'out2'), '--params-file', 'unicycle']) == 2
    error = capsys.readouterr().err
    assert error.count('\n') == 1 and 'undecodable sample' in error
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'out2').exists()


@pytest.mark.parametrize('type_name', [ARRAY, 'geometry_msgs/msg/Twist',
                                       'geometry_msgs/msg/TwistStamped'])
def test_the_offline_command_is_the_bytes_of_the_nodes(type_name):
    """command_cdr (refilter's) reads back as the command, and for arrays is the node's
    bytes."""
    from rcbf_ros.messages.classes import get_message
    header = get_message('std_msgs/msg/Header')(frame_id='base')
    data = filter_edge.command_cdr(np.array([0.25, -1.5]), type_name=type_name,
                                   twist_fields=FIELDS, header=header)
    if type_name == ARRAY:
        assert data == _edge().command(np.array([0.25, -1.5]), twist_fields=FIELDS)
        assert _rosbags_sections(data) == {'u': [0.25, -1.5]}
        return
    read = _rosbags(data, type_name)
    twist = read.twist if type_name.endswith('Stamped') else read
    assert (twist.linear.x, twist.angular.z, twist.angular.x) == (0.25, -1.5, 0.0)
    if type_name.endswith('Stamped'):
        assert read.header.frame_id == 'base'


def test_a_diagnostic_names_at_most_its_bound_of_barriers_those_of_least_h():
    """20,000 barriers made each status 170 ms to encode, and the node answers in between:
    a status names at most DIAGNOSTIC_BARRIERS of them, those of least h, and says so."""
    count = 5 * filter_edge.DIAGNOSTIC_BARRIERS
    h = np.linspace(10.0, 1.0, count)
    h[7] = np.nan                       # not evaluated: shown last, if at all
    result = type('Result', (), {})()
    for name, value in (('status', 'solved'), ('slack', 0.0), ('h', h),
                        ('constraint_values', h + 0.5), ('solve_time_s', 0.0),
                        ('total_time_s', 0.0), ('needed_slack', 0.0),
                        ('proposal_clipped', False)):
        setattr(result, name, value)
    decision = logic.Decision(u_safe=np.zeros(2), u_rl=np.zeros(2), level=logic.OK,
                              result=result, fail_safe=False, reason='',
                              state_source='latest')
    names = [f'obstacle_{k}' for k in range(count)]
    _, _, values = filter_edge.diagnostic_values(decision=decision, barrier_names=names)
    shown = [key[2:] for key in values if key.startswith('h.')]
    least = [names[k] for k in range(count - filter_edge.DIAGNOSTIC_BARRIERS, count)]
    assert shown == least           # the least h, in the barriers' order
    assert [key[11:] for key in values if key.startswith('constraint.')] == least
    assert values['barriers_shown'].startswith(f'{filter_edge.DIAGNOSTIC_BARRIERS} of {count}')
    few = names[:filter_edge.DIAGNOSTIC_BARRIERS]
    result.h, result.constraint_values = h[:len(few)], h[:len(few)]
    _, _, values = filter_edge.diagnostic_values(decision=decision, barrier_names=few)
    assert sum(key.startswith('h.') for key in values) == len(few)
    assert 'barriers_shown' not in values


@pytest.mark.parametrize('field', ['header.frame_id', 'child_frame_id'])
def test_an_odometry_frame_id_over_the_readers_bound_is_refused_in_a_short_line(field):
    from rcbf_ros.messages.sensor import MAX_FRAME_ID
    edge = _edge(state_type='odometry')
    for length, refused in ((MAX_FRAME_ID, False), (MAX_FRAME_ID + 1, True), (1_000_000, True)):
        frames = {'frame_id': 'odom', 'child_frame_id': 'base'}
        frames['frame_id' if field == 'header.frame_id' else 'child_frame_id'] = 'x' * length
        data = serialize_message(state_to_odometry([1.0, -2.0, 0.5], system='unicycle',
                                                   stamp_ns=0, **frames))
        sample, count = edge.read_state(data, received_ns=0)
        if not refused:
            assert count == '' and sample.state is not None
            continue
        assert count == REFUSED_STATE and sample.state is None
        assert sample.error.startswith(f'{field}: {length} characters, more than the bound '
                                       f'{MAX_FRAME_ID}: ')
        assert len(sample.error) < 200


def test_a_twist_stamped_frame_id_over_the_readers_bound_is_refused_in_a_short_line():
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.messages.sensor import MAX_FRAME_ID
    edge = _edge(command_type='twist_stamped')
    header = get_message('std_msgs/msg/Header')(frame_id='b' * 1_000_000)
    data = serialize_message(array_to_twist_stamped([0.5, -0.25], FIELDS, header))
    sample = edge.read_proposal(data, twist_fields=FIELDS)
    assert sample.proposal is None and sample.count == REFUSED_PROPOSAL
    assert sample.error.startswith(f'header.frame_id: 1000000 characters, more than the bound '
                                   f'{MAX_FRAME_ID}: ')
    assert len(sample.error) < 200


@HYPOTHESIS
@given(reason=st.text(max_size=3000) | st.just('frame ' * 200_000))
def test_every_reason_reaches_the_log_and_diagnostics_as_one_bounded_line(reason):
    """A decision's reason is the text of the fail-safe's log line and of the diagnostics'
    message and ``reason`` value: cut to REASON_LIMIT there, on one line."""
    decision = logic.Decision(u_safe=np.zeros(2), u_rl=None, level=logic.ERROR,
                              reason=f'bad state: {reason}', fail_safe=True)
    _, message, values = filter_edge.diagnostic_values(decision=decision, barrier_names=[])
    for text in (decision.reason, message, values['reason']):
        assert len(text) <= filter_edge.REASON_LIMIT and '\n' not in text
        assert text.startswith('bad state:')
    line = ' '.join(f'bad state: {reason}'.split())
    if len(line) <= filter_edge.REASON_LIMIT:
        assert decision.reason == line
    else:
        assert decision.reason.endswith(f'({len(line) - filter_edge.REASON_LIMIT} characters '
                                        'more)')

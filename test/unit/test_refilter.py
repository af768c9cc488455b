"""Offline re-filtering (rcbf_ros.bag.refilter): a synthetic recorded run re-filtered with the
same and
with other parameters, the output read back by independent readers and checked by
``pymcap-cli doctor``; bad inputs give errors naming the problem."""
from __future__ import annotations

import json
import os
from pathlib import Path
import shutil
import subprocess
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
import torch
import yaml

from rcbf_ros.bag import BagWriter, read_bag
from rcbf_ros.bag.refilter import main, refilter_bag, RefilterError
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.node_logic.safety_filter import NODE_PARAMETER_DEFAULTS

PYMCAP_CLI = shutil.which('pymcap-cli') or str(Path(sys.executable).parent / 'pymcap-cli')
T0 = 1_700_000_000_000_000_000
STEP_NS = 20_000_000
N_STEPS = 40
# Synthetic unicycle run: driving along y = 0 at v = 1 from x = -2.4 to x = -1.23.
STATES = [np.array([-2.4 + 0.03 * k, 0.0, 0.0]) for k in range(N_STEPS)]
PROPOSALS = [np.array([1.0, 0.05 * np.sin(k)]) for k in range(N_STEPS)]
# Two recorded states with no proposal after them, inside config B's new obstacle.
INSIDE_B = [np.array([-0.5, 0.0, 0.0]), np.array([-0.55, 0.05, 0.1])]

COMMON = {'system': 'unicycle', 'alpha': 2.0,
          'input_limits': {'min': [-2.5, -2.5], 'max': [2.5, 2.5]},
          'fail_safe_action': [0.0, 0.0]}
OBSTACLES_A = {'x': [1.5, -1.5], 'y': [1.5, 1.5], 'radius': [0.6, 0.6], 'margin': 0.1,
               'lookahead': 0.03, 'heading_index': 2}
# B: A plus an obstacle right in the robot's path.
OBSTACLES_B = dict(OBSTACLES_A, x=[1.5, -1.5, -0.5], y=[1.5, 1.5, 0.0],
                   radius=[0.6, 0.6, 0.3])
PARAMS_A = dict(COMMON, obstacles=OBSTACLES_A)
PARAMS_B = dict(COMMON, obstacles=OBSTACLES_B)


def _sections(**sections: np.ndarray) -> dict:
    dims, data = [], []
    for label, values in sections.items():
        values = np.asarray(values, dtype=np.float64)
        dims.append({'label': label, 'size': values.size, 'stride': values.size})
        data.append(values)
    return {'layout': {'dim': dims, 'data_offset': 0}, 'data': np.concatenate(data)}


def _node_filter(params: dict) -> SafetyFilter:
    """The filter as the safety_filter node builds it by default (its OSQP settings)."""
    config = filter_config_from_params(params)
    defaults = NODE_PARAMETER_DEFAULTS
    return SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action,
                        eps_abs=defaults['osqp.eps_abs'], eps_rel=defaults['osqp.eps_rel'],
                        max_iter=defaults['osqp.max_iter'])


def _inputs(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None,
                             bool]:
    """(state, u, mean, std, own_state) of proposal k: even ones carry their state and a GP
    estimate; odd ones rely on the /state topic and no disturbance."""
    if k % 2 == 0:
        return STATES[k], PROPOSALS[k], np.array([0.0, 0.01, 0.0]), np.full(3, 0.05), True
    return STATES[k], PROPOSALS[k], None, None, False


def _expected_commands(params: dict) -> list[np.ndarray]:
    """What a filter with ``params`` answers to the recorded proposals, in order (the
    proposal before the first state is never filtered)."""
    safety_filter = _node_filter(params)
    out = []
    for k in range(N_STEPS):
        state, u, mean, std, _ = _inputs(k)
        out.append(safety_filter.filter(state, u, mean, std).u_safe)
    return out


def _write_source(directory: Path, *, with_proposals: bool = True,
                  form: str = 'earlier') -> Path:
    """/state, /cmd_proposed, the answers of a node-like filter with config A, /reward.

    ``form`` 'earlier': the answers as /cmd_safe with sections u, u_rl, u_s (and the state the
    proposal carried), as bags were recorded before the filter published filter_info;
    'filter_info': /cmd_safe holds the command alone and /filter_info the rest."""
    recorded = _expected_commands(PARAMS_A)
    with BagWriter(directory) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        if with_proposals:
            bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_safe', 'std_msgs/msg/Float64MultiArray')
        if form == 'filter_info':
            bag.add_topic('/filter_info', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/reward', 'std_msgs/msg/Float64')
        if with_proposals:  # before any state: cannot be filtered
            bag.write_message('/cmd_proposed', _sections(u=np.array([1.0, 0.0])), T0 - 1000)
        for k in range(N_STEPS):
            t = T0 + k * STEP_NS
            state, u, mean, std, own = _inputs(k)
            bag.write_message('/state', _sections(state=state), t)
            if not with_proposals:
                continue
            if own:
                proposal = _sections(u=u, disturbance_mean=mean, disturbance_std=std,
                                     state=state)
                answer = _sections(u=recorded[k], u_rl=u, u_s=recorded[k] - u, state=state)
            else:
                proposal = _sections(u=u)
                answer = _sections(u=recorded[k], u_rl=u, u_s=recorded[k] - u)
            bag.write_message('/cmd_proposed', proposal, t + 1_000_000)
            if form == 'filter_info':  # the state answered rides along, own or topic's
                bag.write_message('/cmd_safe', _sections(u=recorded[k]), t + 3_000_000)
                bag.write_message('/filter_info', _sections(
                    u=recorded[k], u_rl=u, u_s=recorded[k] - u, fail_safe=[0.0],
                    status=[0.0], state=state), t + 3_000_000)
            else:
                bag.write_message('/cmd_safe', answer, t + 3_000_000)
            bag.write_message('/reward', {'data': -0.1 * k}, t + 4_000_000)
        for j, state in enumerate(INSIDE_B):
            bag.write_message('/state', _sections(state=state), T0 + (N_STEPS + j) * STEP_NS)
    return directory


@pytest.fixture(scope='module')
def source_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.set_num_threads(1)
    return _write_source(tmp_path_factory.mktemp('src') / 'run')


@pytest.fixture(scope='module')
def info_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_source(tmp_path_factory.mktemp('src_info') / 'run', form='filter_info')


@pytest.mark.parametrize('form', ['earlier', 'filter_info'])
def test_same_parameters_change_nothing(source_bag: Path, info_bag: Path, tmp_path: Path,
                                        form: str) -> None:
    source = source_bag if form == 'earlier' else info_bag
    summary = refilter_bag(source, tmp_path / 'same', PARAMS_A)
    assert summary.recorded_topic == ('/cmd_safe' if form == 'earlier' else '/filter_info')
    assert summary.proposals == N_STEPS + 1
    assert summary.processed == N_STEPS
    assert summary.skipped == {'no state received yet': 1}
    assert (summary.state_from_proposal, summary.state_from_topic) == (N_STEPS // 2,
                                                                       N_STEPS // 2)
    assert summary.recorded_commands == summary.compared == N_STEPS
    # Same filter, same inputs in the same order: bit-identical commands.
    assert summary.changed == 0 and summary.max_abs_du == 0.0 and summary.mean_abs_du == 0.0
    assert summary.active == summary.recorded_active
    assert summary.fail_safe == 0
    assert summary.states_evaluated == N_STEPS + len(INSIDE_B)
    assert summary.states_violating == 0
    assert set(summary.min_h) == {'obstacle_0', 'obstacle_1'}


def test_new_obstacle_changes_commands_where_expected(source_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / 'with_b'
    summary = refilter_bag(source_bag, out, PARAMS_B)
    recorded_a = _expected_commands(PARAMS_A)
    filtered_b = _expected_commands(PARAMS_B)
    expected_changed = [k for k in range(N_STEPS)
                        if np.linalg.norm(filtered_b[k] - recorded_a[k]) > summary.tolerance]
    # The new obstacle acts ahead of the robot only: far away it changes nothing.
    assert 0 < len(expected_changed) < N_STEPS and 0 not in expected_changed
    assert summary.changed == len(expected_changed)
    deltas = [np.linalg.norm(filtered_b[k] - recorded_a[k]) for k in range(N_STEPS)]
    assert summary.max_abs_du == pytest.approx(max(deltas), rel=1e-6, abs=1e-9)
    assert summary.mean_abs_du == pytest.approx(np.mean(deltas), rel=1e-6, abs=1e-9)
    assert summary.active > summary.recorded_active
    assert summary.fail_safe == 0
    # Exactly the two recorded states inside the new obstacle violate it.
    assert summary.states_violating == len(INSIDE_B)
    assert summary.violations_per_barrier == {'obstacle_0': 0, 'obstacle_1': 0,
                                              'obstacle_2': len(INSIDE_B)}
    assert summary.min_h['obstacle_2'] < 0 < summary.min_h['obstacle_1']

    # The new commands, read back with rosbags, satisfy config B's RCBF rows: the QP built
    # at (x, u_new) needs no correction (G z <= h holds at z = 0 on the barrier rows).
    problem_b = filter_config_from_params(PARAMS_B).problem
    store = jazzy_typestore()
    commands = []
    with AnyReader([out], default_typestore=store) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        for connection, _, raw in reader.messages(
                connections=[c for c in reader.connections
                             if c.topic == '/refilter/cmd_safe']):
            msg = reader.deserialize(raw, connection.msgtype)
            # The command alone, as the node's cmd_safe.
            assert [(d.label, d.size) for d in msg.layout.dim] == [('u', 2)]
            commands.append(np.asarray(msg.data))
        infos = [reader.deserialize(raw, connection.msgtype) for connection, _, raw in
                 reader.messages(connections=[c for c in reader.connections
                                              if c.topic == '/refilter/filter_info'])]
    # one answer per proposal: the first, before any state, is the fail-safe
    answers = N_STEPS + 1
    assert counts == {'/state': N_STEPS + len(INSIDE_B), '/cmd_proposed': N_STEPS + 1,
                      '/cmd_safe': N_STEPS, '/reward': N_STEPS, '/refilter/cmd_safe': answers,
                      '/refilter/filter_info': answers, '/refilter/diagnostics': answers}
    labels = [dim.label for dim in infos[0].layout.dim]
    assert labels[:4] == ['u', 'u_rl', 'u_s', 'fail_safe'] and infos[0].data[6] == 1.0
    assert list(commands[0]) == [0.0, 0.0]
    commands, infos = commands[1:], infos[1:]
    details = []
    for k, (command, info) in enumerate(zip(commands, infos)):
        sections, offset = {}, 0
        for dim in info.layout.dim:
            sections[dim.label] = np.asarray(info.data[offset:offset + dim.size])
            offset += dim.size
        assert list(sections) == ['u', 'u_rl', 'u_s', 'fail_safe', 'status', 'h', 'constraint',
                                  'slack', 'needed_slack', 'solve_time_s', 'state']
        assert np.all(np.isfinite(info.data))
        np.testing.assert_array_equal(sections['u'], command)
        np.testing.assert_array_equal(sections['state'], _inputs(k)[0])  # the state answered
        details.append((command, sections['u_rl'], sections['u_s']))
    commands = details
    for k, (u_new, u_rl, u_s) in enumerate(commands):
        state, u, mean, std, _ = _inputs(k)
        np.testing.assert_array_equal(u_rl, u)
        np.testing.assert_allclose(u_new, filtered_b[k], atol=1e-6)
        np.testing.assert_allclose(u_s, u_new - u_rl, atol=1e-15)
        as_tensor = [None if a is None else torch.from_numpy(np.array(a)).unsqueeze(0)
                     for a in (state, u_new, mean, std)]
        rows = problem_b.qp(*as_tensor).h[0, :problem_b.n_barriers].numpy()
        assert np.all(rows >= -1e-6), (k, rows)


def test_output_bag_read_by_mcap_ros2_and_doctor(source_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / 'checked'
    refilter_bag(source_bag, out, PARAMS_B)
    mcap_file = out / 'checked_0.mcap'
    decoded: dict[str, list] = {}
    with open(mcap_file, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append((message.log_time, msg))
    assert {k: len(v) for k, v in decoded.items()} == {
        '/state': N_STEPS + len(INSIDE_B), '/cmd_proposed': N_STEPS + 1, '/cmd_safe': N_STEPS,
        '/reward': N_STEPS, '/refilter/cmd_safe': N_STEPS + 1,
        '/refilter/filter_info': N_STEPS + 1, '/refilter/diagnostics': N_STEPS + 1}
    # Source topics are copied byte for byte with their times.
    source = [(m.topic, m.data, m.log_time_ns, m.publish_time_ns) for m in read_bag(source_bag)]
    copied = [(m.topic, m.data, m.log_time_ns, m.publish_time_ns) for m in read_bag(out)
              if not m.topic.startswith('/refilter/')]
    assert copied == source
    # Diagnostics as the node publishes them, stamped at the proposal's log time.
    proposal_times = [t for t, _ in decoded['/cmd_proposed']]
    assert [t for t, _ in decoded['/refilter/diagnostics']] == proposal_times
    for (log_time, array), t in zip(decoded['/refilter/diagnostics'][1:], proposal_times[1:]):
        assert log_time == t
        status = array.status[0]
        assert array.header.stamp.sec * 10**9 + array.header.stamp.nanosec == t
        values = {kv.key: kv.value for kv in status.values}
        assert {'h.obstacle_2', 'constraint.obstacle_2', 'slack', 'status'} <= set(values)
        assert status.level in (0, 1)
        assert float(values['constraint.obstacle_2']) >= -1e-6
    result = subprocess.run([PYMCAP_CLI, 'doctor', str(mcap_file)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'passed' in result.stdout


def test_command_line_with_params_file(source_bag: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    params_file = tmp_path / 'b.yaml'
    params_file.write_text(yaml.safe_dump({
        '/**': {'ros__parameters': dict(COMMON, obstacles=OBSTACLES_A)},
        '/other': {'ros__parameters': {'alpha': -1.0}},
        '/safety_filter': {'ros__parameters': {'obstacles': OBSTACLES_B}}}))
    json_path = tmp_path / 'summary.json'
    code = main([str(source_bag), str(tmp_path / 'cli'), '--params-file', str(params_file),
                 '--json', str(json_path)])
    assert code == 0
    printed = capsys.readouterr().out
    assert 'changed (|du| > 1e-06):' in printed and 'obstacle_2' in printed
    summary = yaml.safe_load(json_path.read_text())  # JSON is YAML
    assert summary['states_violating'] == len(INSIDE_B) and summary['changed'] > 0
    assert summary['skipped_total'] == 1


@pytest.mark.parametrize(('case', 'needle'), [
    ('missing_source', 'does not exist'),
    ('no_proposals', '/cmd_proposed'),
    ('bad_param', 'obstacles.y'),
    ('bad_alpha', 'alpha'),
    ('missing_params_file', 'params file'),
    ('wrong_state_length', 'n_x'),
    ('output_exists', 'already holds a bag'),
])
def test_bad_inputs_name_the_problem(case: str, needle: str, source_bag: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    source, params = str(source_bag), str(tmp_path / 'params.yaml')
    body = dict(PARAMS_A)
    if case == 'missing_source':
        source = str(tmp_path / 'no_such_bag')
    elif case == 'no_proposals':
        source = str(_write_source(tmp_path / 'states_only', with_proposals=False))
    elif case == 'bad_param':
        body = dict(COMMON, obstacles=dict(OBSTACLES_A, y=[1.5]))
    elif case == 'bad_alpha':
        body = dict(PARAMS_A, alpha=-2.0)
    elif case == 'missing_params_file':
        params = str(tmp_path / 'absent.yaml')
    elif case == 'wrong_state_length':
        body = {'system': 'pvtol', 'walls': {'nx': [0.0], 'ny': [1.0], 'offset': [-1.0]}}
    if case != 'missing_params_file':
        Path(params).write_text(yaml.safe_dump({'/**': {'ros__parameters': body}}))
    output = tmp_path / 'out'
    if case == 'output_exists':
        refilter_bag(source_bag, output, PARAMS_A)
    with pytest.raises(RefilterError, match=needle):
        refilter_bag(source, output, params)
    assert main([source, str(output), '--params-file', params]) == 2
    assert needle in capsys.readouterr().err
    if case == 'wrong_state_length':  # no half-written bag is left behind
        assert not output.exists()


def write_twist_source(directory: Path, type_name: str) -> Path:
    """/state and /cmd_proposed of a Twist (or TwistStamped) controller: the STATES and the
    PROPOSALS in ``linear.x`` / ``angular.z``, a stamp and frame of its own on each."""
    with BagWriter(directory) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_proposed', type_name)
        for k in range(N_STEPS):
            t = T0 + k * STEP_NS
            bag.write_message('/state', _sections(state=STATES[k]), t)
            twist = {'linear': {'x': float(PROPOSALS[k][0]), 'y': 0.0, 'z': 0.0},
                     'angular': {'x': 0.0, 'y': 0.0, 'z': float(PROPOSALS[k][1])}}
            if type_name.endswith('Stamped'):
                twist = {'header': {'stamp': {'sec': 100 + k, 'nanosec': 7 * k},
                                    'frame_id': f'base_{k}'}, 'twist': twist}
            bag.write_message('/cmd_proposed', twist, t + 1_000_000)
    return directory


@pytest.mark.parametrize('type_name', ['geometry_msgs/msg/Twist',
                                       'geometry_msgs/msg/TwistStamped'])
def test_twist_proposals_are_answered_in_their_own_type(type_name: str, tmp_path: Path) -> None:
    source = write_twist_source(tmp_path / 'run', type_name)
    summary = refilter_bag(source, tmp_path / 'out', PARAMS_B)
    assert summary.processed == N_STEPS and summary.active > 0
    with AnyReader([tmp_path / 'out']) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        read = {topic: [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(
            connections=[c for c in reader.connections if c.topic == topic])]
            for topic in ('/refilter/cmd_safe', '/refilter/filter_info')}
    assert types['/refilter/cmd_safe'] == type_name
    assert len(read['/refilter/cmd_safe']) == N_STEPS
    for k, (command, info) in enumerate(zip(*read.values())):
        u = np.asarray(info.data[:2])  # filter_info's first section: u
        assert info.layout.dim[0].label == 'u'
        if type_name.endswith('Stamped'):
            assert (command.header.stamp.sec, command.header.stamp.nanosec,
                    command.header.frame_id) == (100 + k, 7 * k, f'base_{k}')
            command = command.twist
        assert [command.linear.x, command.angular.z] == u.tolist()
        assert [command.linear.y, command.linear.z, command.angular.x, command.angular.y] == \
            [0.0] * 4


_WITHOUT_MIDDLEWARE = """
import json, sys
import numpy as np
from rcbf_ros.bag.refilter import refilter_bag
from rcbf_ros.messages import classes
from rcbf_ros.messages.cdr import deserialize_message, serialize_message
from rcbf_ros.messages.conversions import array_to_twist
summary = refilter_bag(sys.argv[1], sys.argv[2], json.loads(sys.argv[3]))
twist = array_to_twist(np.array([1.0, 0.5]), ['linear.x', 'angular.z'],
                       message_class=classes.get_message)
assert deserialize_message(serialize_message(twist), 'geometry_msgs/msg/Twist') == twist
print(json.dumps({'processed': summary.processed,
                  'loaded': sorted(m for m in sys.modules
                                   if m.split('.')[0] == 'cyclonedds' or m == 'rclpy'
                                   or m.startswith('rcbf_ros.ros'))}))
"""


def test_refiltering_and_the_message_layer_load_no_middleware(tmp_path: Path) -> None:
    """The bag tools and rcbf_ros.messages build, write and read messages without a DDS
    runtime: neither rcbf_ros.ros, nor Cyclone DDS, nor rclpy is imported."""
    source = write_twist_source(tmp_path / 'run', 'geometry_msgs/msg/TwistStamped')
    result = subprocess.run(
        [sys.executable, '-c', _WITHOUT_MIDDLEWARE, str(source), str(tmp_path / 'out'),
         json.dumps(PARAMS_B)], capture_output=True, text=True, timeout=120,
        env=dict(os.environ, OMP_NUM_THREADS='1'))
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report == {'processed': N_STEPS, 'loaded': []}


@pytest.mark.parametrize(('case', 'needle'), [
    ('empty_output', 'output: must not be empty'),
    ('sensor_sources', 'front.topic: the source bag has no /scan topic'),
    ('json_under_a_file', '--json'),
    ('json_in_a_missing_directory', '--json'),
    ('json_is_a_directory', '--json'),
    ('json_empty', '--json'),
    pytest.param('json_a_fifo', 'exists and is not a regular file',
                 marks=pytest.mark.timeout(120)),  # writing to the FIFO would block
])
def test_bad_command_lines_are_refused_in_one_line_before_the_run(
        case: str, needle: str, source_bag: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2, one line naming the argument, no bag written (not even into the working
    directory) and no traceback."""
    work = tmp_path / 'work'
    work.mkdir()
    monkeypatch.chdir(work)
    params = tmp_path / 'params.yaml'
    body = dict(PARAMS_A)
    if case == 'sensor_sources':
        body.update(observation_sources=['front'],
                    front={'type': 'scan', 'topic': '/scan'})
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': body}}))
    output = '' if case == 'empty_output' else str(tmp_path / 'out')
    if case == 'json_a_fifo':
        os.mkfifo(tmp_path / 'fifo.json')
    argv = [str(source_bag), output, '--params-file', str(params)]
    argv += {'json_under_a_file': ['--json', str(params / 'x.json')],
             'json_in_a_missing_directory': ['--json', str(tmp_path / 'no' / 'x.json')],
             'json_is_a_directory': ['--json', str(work)],
             'json_empty': ['--json', ''],
             'json_a_fifo': ['--json', str(tmp_path / 'fifo.json')]}.get(case, [])
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], captured.err
    assert 'Traceback' not in captured.err and captured.out == ''
    assert list(work.iterdir()) == [] and not (tmp_path / 'out').exists()


def test_a_summary_that_cannot_be_written_keeps_the_bag(
        source_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The JSON path checked fine but its write fails after the run (the directory went
    away): exit 1, one line naming --json, the new bag kept."""
    from rcbf_ros.bag import refilter
    monkeypatch.setattr(refilter, '_json_path_problem', lambda path: '')
    output = tmp_path / 'out'
    code = main([str(source_bag), str(output), '--params-file', 'unicycle',
                 '--json', str(tmp_path / 'gone' / 'x.json')])
    err = capsys.readouterr().err
    assert code == 1
    assert len(err.strip().splitlines()) == 1 and '--json' in err and 'Traceback' not in err
    assert any(m.topic == refilter.OUTPUT_COMMAND_TOPIC for m in read_bag(output))


@pytest.mark.parametrize('target', ['the_mcap', 'a_hard_link_to_the_mcap', 'metadata',
                                    'new_file_in_the_bag', 'the_params_file',
                                    'a_link_to_the_params_file'])
def test_a_json_path_naming_an_input_is_refused_and_the_input_kept(
        target: str, source_bag: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """``--json`` naming a file of the run's inputs (the source bag's ``.mcap`` or
    ``metadata.yaml``, a new name inside the bag directory, the params file; through a link
    or a hard link too): exit 2 before the run, one line naming --json, every input byte for
    byte as it was, no output bag. Writing the summary there would replace the recording."""
    bag = tmp_path / 'run'
    shutil.copytree(source_bag, bag)
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': PARAMS_A}}))
    mcap = next(bag.glob('*.mcap'))
    path = {'the_mcap': mcap, 'metadata': bag / 'metadata.yaml',
            'new_file_in_the_bag': bag / 'summary.json', 'the_params_file': params,
            'a_hard_link_to_the_mcap': tmp_path / 'hard.json',
            'a_link_to_the_params_file': tmp_path / 'link.json'}[target]
    if target == 'a_hard_link_to_the_mcap':
        os.link(mcap, path)
    if target == 'a_link_to_the_params_file':
        path.symlink_to(params)
    before = {f: f.read_bytes() for f in [*bag.iterdir(), params]}
    output = tmp_path / 'out'
    assert main([str(bag), str(output), '--params-file', str(params),
                 '--json', str(path)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and '--json' in lines[0], captured.err
    assert 'Traceback' not in captured.err and captured.out == ''
    assert {f: f.read_bytes() for f in [*bag.iterdir(), params]} == before
    assert not output.exists()


def test_a_json_path_beside_the_inputs_is_written(source_bag: Path, tmp_path: Path) -> None:
    """The rule refuses the inputs only: a summary beside the source bag is written."""
    path = source_bag.parent / 'summary.json'
    assert main([str(source_bag), str(tmp_path / 'out'), '--params-file', 'unicycle',
                 '--json', str(path)]) == 0
    assert json.loads(path.read_text())['source'] == str(source_bag)

"""The safety_filter node as a separate process over real Cyclone DDS (loopback).

- bad input: NaN / wrong-length proposals, no state yet, a stale state -> the fail-safe command
  and an ERROR diagnostic naming the reason; a good proposal then passes through the QP;
- the node behind a remapped proposal topic, and in Twist mode;
- invalid parameters: the process exits with status 2 and names the key;
- closed loop (slow): simulator + deliberately unsafe nominal controller + safety_filter
  (+ recorder) started by rcbf_ros launch, >= 2000 lock-step steps into the obstacles: zero
  violations of any true clearance h_i, and u_safe == u_RL wherever no row is active.
"""
from __future__ import annotations

import collections
import json
from pathlib import Path
import subprocess
import sys
import threading
import time
from typing import Any, Callable

from dds_harness import stop, subprocess_env  # this directory: on sys.path for pytest
import numpy as np
import pytest

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.parameters.rules import find_config, load_params

REPO = Path(__file__).resolve().parents[2]
UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
WAIT_S = 60.0

pytestmark = pytest.mark.integration


EVERY_DIAGNOSTIC = ('-p', 'diagnostics.min_period_s:=0.0')
"""A diagnostic with every answer (the default rate-limits OK ones): the exchanges below pair
each command with its diagnostic."""


def _start_filter(domain_id: int, *ros_args: str, params_file: str = UNICYCLE
                  ) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
         '--params-file', params_file, *EVERY_DIAGNOSTIC, *ros_args],
        env=subprocess_env(domain_id), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _level(status: Any) -> int:
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


class Probe:
    """An in-process node of the test: publishes, and collects what arrives, in a spin thread."""

    def __init__(self, domain_id: int) -> None:
        from rcbf_ros.ros.runtime import Node, rclpy
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node = Node('probe')
        self.received: dict[str, list] = collections.defaultdict(list)
        self.lock = threading.Lock()
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)

    def qos(self, depth: int = 1000):
        from rcbf_ros.ros.runtime import QoSProfile
        return QoSProfile(depth=depth)

    def subscribe(self, type_name: str, topic: str,
                  convert: Callable[[Any], Any] = lambda m: m) -> None:
        from rcbf_ros.ros.runtime import get_message

        def store(msg: Any) -> None:
            item = (time.monotonic(), convert(msg))
            with self.lock:
                self.received[topic].append(item)
        self.node.create_subscription(get_message(type_name), topic, store, self.qos())

    def publisher(self, type_name: str, topic: str):
        from rcbf_ros.ros.runtime import get_message
        return self.node.create_publisher(get_message(type_name), topic, self.qos(10))

    def start(self) -> Probe:
        self._thread.start()
        return self

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.received[topic])

    def wait_for(self, topic: str, count: int, timeout_s: float = WAIT_S) -> list:
        deadline = time.monotonic() + timeout_s
        while self.count(topic) < count:
            if time.monotonic() > deadline:
                raise AssertionError(f'{topic}: {self.count(topic)} of {count} messages '
                                     f'within {timeout_s} s')
            time.sleep(0.01)
        with self.lock:
            return [item for _, item in self.received[topic]]

    def close(self) -> None:
        self._running = False
        if self._thread.is_alive():  # not started when a test failed before start()
            self._thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def _wait_matched(publisher: Any, process: subprocess.Popen) -> None:
    deadline = time.monotonic() + WAIT_S
    while publisher.get_subscription_count() == 0:
        assert process.poll() is None, stop(process, timeout=10)
        assert time.monotonic() < deadline, 'the safety_filter never subscribed'
        time.sleep(0.02)


def _connect(probe: Probe, process: subprocess.Popen, proposal_type: str,
             proposal_topic: str = '/cmd_proposed', *, with_state: bool = True
             ) -> tuple[Any, Any]:
    """Subscribe /diagnostics, publish proposals (and states, unless ``with_state`` is False)
    to the filter, start the probe and wait until the filter has subscribed to each.

    Returns the proposal publisher and the state publisher (None without states).
    """
    probe.subscribe('diagnostic_msgs/msg/DiagnosticArray', '/diagnostics', _diagnostic)
    state_pub = (probe.publisher('std_msgs/msg/Float64MultiArray', '/state') if with_state
                 else None)
    proposal_pub = probe.publisher(proposal_type, proposal_topic)
    probe.start()
    _wait_matched(proposal_pub, process)
    if state_pub is not None:
        _wait_matched(state_pub, process)
    return proposal_pub, state_pub


def _exchange(probe: Probe, proposal_pub: Any, proposal: Any,
              command_topic: str = '/cmd_safe') -> tuple[Any, tuple[int, str, dict[str, str]]]:
    """Publish one proposal; return the command and the diagnostic it was answered with."""
    commands, diagnostics = probe.count(command_topic), probe.count('/diagnostics')
    proposal_pub.publish(proposal)
    command = probe.wait_for(command_topic, commands + 1)[commands]
    return command, probe.wait_for('/diagnostics', diagnostics + 1)[diagnostics]


def _handshake(probe: Probe, proposal_pub: Any, proposal: Any,
               command_topic: str = '/cmd_safe') -> Any:
    """Re-publish ``proposal`` until it is answered; return the first answer.

    The first samples of a new writer can be lost until the filter's reader has matched it (see
    ``_exchange_with_state``); one answered sample proves the match, so later exchanges are
    reliable. Late answers to the repeats are awaited before the counts are used again.
    """
    before = probe.count(command_topic)
    for _ in range(100):
        proposal_pub.publish(proposal)
        deadline = time.monotonic() + 0.5
        while probe.count(command_topic) == before and time.monotonic() < deadline:
            time.sleep(0.01)
        if probe.count(command_topic) > before:
            settled = -1
            while settled != probe.count(command_topic):   # quiet for 0.3 s: no answer in flight
                settled = probe.count(command_topic)
                time.sleep(0.3)
            probe.wait_for('/diagnostics', probe.count(command_topic))
            return probe.wait_for(command_topic, before + 1)[before]
    raise AssertionError('the safety_filter never answered a proposal')


def _exchange_with_state(probe: Probe, state_pub: Any, state: list[float], proposal_pub: Any,
                         proposal: Any, command_topic: str = '/cmd_safe'
                         ) -> tuple[Any, tuple[int, str, dict[str, str]]]:
    """Publish a state, then a proposal; repeat while the answer says the filter had no state.

    ``_wait_matched`` sees the match from the writer's side only: until the filter's reader has
    matched the new /state writer too, a volatile sample on it can be dropped. Once one got
    through, the reliable writer delivers every later one, in order.
    """
    from rcbf_ros.messages.conversions import sections_to_msg
    for _ in range(100):
        state_pub.publish(sections_to_msg({'state': state}))
        time.sleep(0.05)
        command, diagnostic = _exchange(probe, proposal_pub, proposal, command_topic)
        if not diagnostic[1].startswith('no state received yet'):
            return command, diagnostic
    raise AssertionError('the safety_filter never received a /state sample')


def _sections(msg: Any) -> dict[str, np.ndarray]:
    from rcbf_ros.messages.conversions import msg_to_sections
    return {k: v.copy() for k, v in msg_to_sections(msg).items()}


def _diagnostic(msg: Any) -> tuple[int, str, dict[str, str]]:
    status = msg.status[0]
    return _level(status), status.message, {kv.key: kv.value for kv in status.values}


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def test_bad_input_yields_fail_safe_and_error_diagnostics(ros_domain_id, probe):
    from rcbf_ros.messages.conversions import sections_to_msg
    process = _start_filter(ros_domain_id, '-r', 'cmd_proposed:=/my_controller/cmd',
                            '-p', 'safety_filter:max_state_age_s:=0.3',
                            '-p', 'safety_filter:fail_safe_action:=[0.0, 0.5]')
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info', _sections)
        proposal_pub, state_pub = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                           '/my_controller/cmd')
        unsafe = {'u': [2.5, 0.0]}  # full speed at the centre obstacle from 0.25 m
        good_state = [-0.85, 0.0, 0.0]

        def propose(sections: dict) -> tuple[Any, tuple[int, str, dict[str, str]]]:
            return _exchange(probe, proposal_pub, sections_to_msg(sections))

        def after_state(state: list[float], wait_s: float) -> tuple[Any, Any]:
            state_pub.publish(sections_to_msg({'state': state}))
            time.sleep(wait_s)
            return propose(unsafe)

        _handshake(probe, proposal_pub, sections_to_msg(unsafe))
        answers = [(probe.wait_for('/cmd_safe', 1)[0],
                    probe.wait_for('/diagnostics', 1)[0])]                    # 0: no state yet
        answers.append(_exchange_with_state(probe, state_pub, good_state, proposal_pub,
                                            sections_to_msg(unsafe)))         # 1: filtered
        answers.append(propose({'u': [float('nan'), 0.0]}))                   # 2: NaN
        answers.append(propose({'u': [1.0, 0.0, 0.0]}))                       # 3: wrong length
        answers.append(propose({'u': [0.1, 0.0], 'state': [0.0, 0.0]}))       # 4: short state
        answers.append(after_state([np.inf, 0.0, 0.0], 0.05))                 # 5: bad state
        answers.append(after_state(good_state, 0.6))                          # 6: stale (> 0.3 s)
    finally:
        output = stop(process, timeout=10)
    commands = [command for command, _ in answers]
    diagnostics = [diagnostic for _, diagnostic in answers]

    fail_safe = [0.0, 0.5]
    expected_reasons = {0: 'no state received yet', 2: 'bad proposal: u: contains NaN',
                        3: 'bad proposal: u: expected 2 values',
                        4: 'bad proposal: state: expected 3 values',
                        5: 'bad state: state: contains NaN', 6: 'stale state'}
    for index, reason in expected_reasons.items():
        level, message, values = diagnostics[index]
        assert level == 2 and message.startswith(reason), (index, message)
        assert values['fail_safe'] == 'True' and values['reason'].startswith(reason)
        assert values['status'] == 'not solved'
        np.testing.assert_array_equal(commands[index]['u'], fail_safe)
    # cmd_safe is the command alone; the rest, NaN-free even for the fail-safe, on filter_info.
    assert all(list(command) == ['u'] for command in commands)
    infos = probe.wait_for('/filter_info', probe.count('/cmd_safe'))
    assert all(np.all(np.isfinite(np.concatenate(list(info.values())))) for info in infos)
    info = next(info for info in infos if info['status'][0] == 0)  # the filtered one
    # The good proposal went through the QP: slowed down, and diagnosed by barrier name.
    level, message, values = diagnostics[1]
    assert level == 0 and message == 'filtering' and values['fail_safe'] == 'False'
    assert 0.0 < commands[1]['u'][0] < 2.5
    np.testing.assert_array_equal(info['u'], commands[1]['u'])
    np.testing.assert_array_equal(info['u_rl'], [2.5, 0.0])
    np.testing.assert_allclose(info['u_s'], commands[1]['u'] - [2.5, 0.0])
    names = load_params(find_config('unicycle'), 'safety_filter')
    config = filter_config_from_params(names)
    for name in config.problem.barrier_names:
        assert float(values[f'h.{name}']) == float(values[f'h.{name}'])  # a number, not nan
    assert float(values['h.obstacle_0']) == pytest.approx(0.82 ** 2 - 0.7 ** 2)
    assert float(values['solve_time_s']) > 0
    # The log says why, throttled per reason.
    assert 'fail-safe: no state received yet' in output
    assert 'fail-safe: bad proposal: u: contains NaN' in output
    assert 'fail-safe: stale state' in output


def test_twist_mode(ros_domain_id, probe):
    from rcbf_ros.messages.conversions import array_to_twist, sections_to_msg, twist_to_array
    fields = ['linear.x', 'angular.z']
    process = _start_filter(ros_domain_id, '-p', 'safety_filter:command_type:=twist')
    try:
        probe.subscribe('geometry_msgs/msg/Twist', '/cmd_safe',
                        lambda m: twist_to_array(m, fields))
        proposal_pub, state_pub = _connect(probe, process, 'geometry_msgs/msg/Twist')
        _handshake(probe, proposal_pub, array_to_twist([1.0, 0.3], fields))   # no state yet
        free, _ = _exchange_with_state(probe, state_pub, [-2.5, -2.5, -0.75 * np.pi],
                                       proposal_pub, array_to_twist([1.0, 0.3], fields))
        state_pub.publish(sections_to_msg({'state': [-0.85, 0.0, 0.0]}))
        time.sleep(0.05)
        slowed, _ = _exchange(probe, proposal_pub, array_to_twist([2.5, 0.0], fields))
    finally:
        stop(process, timeout=10)
    commands = [free, slowed]           # passes through where free; slowed down near the obstacle
    np.testing.assert_array_equal(commands[0], [1.0, 0.3])
    assert 0.0 < commands[1][0] < 2.5


def test_pvtol_proposal_with_learned_disturbance(ros_domain_id, probe):
    """PVTOL's band barrier (bands.operator.*: user-named keys) and the proposal's GP box."""
    from rcbf_ros.messages.conversions import sections_to_msg
    process = _start_filter(ros_domain_id, params_file=str(REPO / 'config' / 'pvtol.yaml'))
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        proposal_pub, _ = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                   with_state=False)
        state = [-4.5, -1.0, 0.3, 0.0, -0.2, 1.0, -5.0]  # 0.5 from the operator, moving away
        proposal = {'u': [1.0, 0.5], 'disturbance_mean': [0.0] * 7,
                    'disturbance_std': [0.0, 0.0, 0.1, 0.1, 0.1, 0.1, 0.0], 'state': state}
        _handshake(probe, proposal_pub, sections_to_msg(proposal))
        answers = [_exchange(probe, proposal_pub, sections_to_msg(proposal)),
                   _exchange(probe, proposal_pub, sections_to_msg({'u': [1.0, 0.5],
                                                                   'state': state}))]
    finally:
        stop(process, timeout=10)
    commands = [command for command, _ in answers]
    diagnostics = [diagnostic for _, diagnostic in answers]
    params = load_params(REPO / 'config' / 'pvtol.yaml', 'safety_filter')
    problem = filter_config_from_params(params).problem
    assert {'operator_upper', 'operator_lower'} <= set(problem.barrier_names)
    _, _, values = diagnostics[0]
    assert all(f'h.{name}' in values for name in problem.barrier_names)
    assert np.isfinite(float(values['h.operator_lower']))
    # Same state and proposal: the learned std makes the filter correct a proposal the nominal
    # rows pass (with a std of 0.3 the rows would be infeasible within the limits: fail-safe).
    from rcbf_ros.core.filter import SafetyFilter
    reference = SafetyFilter(problem, fail_safe_action=params.get('fail_safe_action'))
    robust = reference.filter(state, [1.0, 0.5], proposal['disturbance_mean'],
                              proposal['disturbance_std'])
    nominal = reference.filter(state, [1.0, 0.5])
    np.testing.assert_allclose(commands[0]['u'], robust.u_safe, atol=1e-6)
    np.testing.assert_allclose(commands[1]['u'], nominal.u_safe, atol=1e-6)
    assert not np.allclose(robust.u_safe, nominal.u_safe, atol=1e-3)


@pytest.mark.parametrize('args, key', [
    (('-p', 'safety_filter:max_state_age_s:=-1.0'), 'max_state_age_s'),
    (('-p', 'safety_filter:alpha:=-2.0'), 'alpha'),
    (('-p', 'safety_filter:command_type:=twist', '-p', "safety_filter:twist_fields:=['linear.x']"),
     'twist_fields'),
])
def test_invalid_parameters_exit_2_naming_the_key(ros_domain_id, args, key):
    process = _start_filter(ros_domain_id, *args)
    try:
        code = process.wait(timeout=WAIT_S)
    finally:
        output = stop(process, timeout=10)
    assert code == 2, output
    assert f'invalid parameters: {key}' in output


def test_sigint_while_proposals_stream_exits_0_without_traceback(ros_domain_id, probe):
    """Ctrl-C lands while callbacks run and publish: the one under way finishes, none follows,
    and the node stops cleanly (under rclpy its publish used to find the context invalid)."""
    from rcbf_ros.messages.conversions import sections_to_msg
    process = _start_filter(ros_domain_id)
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_safe', _sections)
        proposal_pub, _ = _connect(probe, process, 'std_msgs/msg/Float64MultiArray',
                                   with_state=False)
        proposal = sections_to_msg({'u': [2.5, 0.0], 'state': [-0.85, 0.0, 0.0]})
        _handshake(probe, proposal_pub, proposal)
        answered = probe.count('/cmd_safe')
        deadline = time.monotonic() + WAIT_S
        while probe.count('/cmd_safe') < answered + 50 and time.monotonic() < deadline:
            proposal_pub.publish(proposal)
            time.sleep(0.002)
        assert probe.count('/cmd_safe') >= answered + 50, 'the filter stopped answering'
        for _ in range(200):  # proposals keep coming while the signal lands
            proposal_pub.publish(proposal)
        process.send_signal(2)
        for _ in range(200):
            proposal_pub.publish(proposal)
            time.sleep(0.001)
        code = process.wait(timeout=30)
    finally:
        output = stop(process, timeout=10)
    assert code == 0, output
    assert 'Traceback' not in output and 'Error' not in output, output


def test_odometry_and_twist_stamped_from_end_to_end(ros_domain_id, probe, tmp_path):
    """A robot's standard messages in lock-step: the simulator publishes nav_msgs/Odometry,
    the nominal controller answers each with a TwistStamped carrying the Odometry's header,
    the filter passes that header through, and the simulator takes each answer for the state
    whose stamp it carries. Into the obstacles at full speed, no true clearance goes negative."""
    from rcbf_ros.messages.conversions import stamp_ns
    steps = 120
    common = ['-p', 'system:=unicycle', '-p', 'state_type:=odometry', '-p',
              'command_type:=twist_stamped']
    processes = [
        subprocess.Popen([sys.executable, '-m', 'sim_nodes.simulator_node', '--ros-args',
                          *common, '-p', f'max_steps:={steps}', '-p', 'max_episodes:=1',
                          '-p', 'start:=[-2.5, 0.0, 0.0]', '-p', 'goal:=[2.5, 0.0]'],
                         env=subprocess_env(ros_domain_id), cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT),
        _start_filter(ros_domain_id, '-r', '__node:=safety_filter', *common,
                      '-p', 'state_frame_id:=map'),
        subprocess.Popen([sys.executable, '-m', 'sim_nodes.nominal_controller_node',
                          '--ros-args', *common, '-p', 'goal:=[2.5, 0.0]'],
                         env=subprocess_env(ros_domain_id), cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT)]
    header = lambda m: (stamp_ns(m.header), m.header.frame_id)  # noqa: E731
    probe.subscribe('nav_msgs/msg/Odometry', '/state', header)
    probe.subscribe('geometry_msgs/msg/TwistStamped', '/cmd_proposed', header)
    probe.subscribe('geometry_msgs/msg/TwistStamped', '/cmd_safe', header)
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/h_true', _sections)
    probe.subscribe('std_msgs/msg/String', '/episode', lambda m: json.loads(m.data))
    probe.start()
    try:
        code = processes[0].wait(timeout=240)
    finally:
        outputs = [stop(process, timeout=10) for process in processes]
    assert code == 0, outputs[0]
    ends = [e for _, e in probe.received['/episode'] if e['event'] == 'end']
    assert len(ends) == 1 and ends[0]['violations'] == 0, ends
    assert ends[0]['steps'] == steps or ends[0]['goal_reached'], ends
    assert min(float(np.min(h['h_true'])) for _, h in probe.received['/h_true']) >= 0.0
    states = {stamp for _, (stamp, _) in probe.received['/state']}
    commands = [item for _, item in probe.received['/cmd_safe']]
    assert len(commands) >= ends[0]['steps']
    # Every safe command carries the stamp of a state and the Odometry's frame, as proposed.
    assert all(stamp in states and frame == 'map' for stamp, frame in commands)
    # A state not answered within action_timeout_s is published again (a late subscriber
    # under load), so one state can be proposed for, and answered, twice in a row.
    proposals = _without_repeats([item for _, item in probe.received['/cmd_proposed']])
    answered = _without_repeats(commands)
    assert proposals[:len(answered)] == answered
    assert 'Traceback' not in ''.join(outputs)


# --- closed loop --------------------------------------------------------------------------------

@pytest.mark.slow
def test_unsafe_controller_behind_the_filter_never_violates(ros_domain_id, probe, tmp_path):
    from rcbf_ros.messages.conversions import msg_to_sections
    episodes, max_steps = 4, 800
    bag = tmp_path / 'bag'
    nodes = ['simulator', 'safety_filter', 'nominal_controller']
    recorder = (REPO / 'rcbf_ros' / 'ros' / 'recorder_node.py').exists()
    command = [sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_filter',
               '--domain-id', str(ros_domain_id),
               '-p', f'simulator:max_episodes:={episodes}',
               '-p', f'simulator:max_steps:={max_steps}',
               '-p', 'simulator:random_start:=true']
    if recorder:
        command += ['-p', f'recorder:output:={bag}']
    else:
        command += ['--without', 'recorder']
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/h_true',
                    lambda m: msg_to_sections(m)['h_true'].copy())
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info', _sections)
    probe.subscribe('std_msgs/msg/Float64MultiArray', '/cmd_proposed', _sections)
    probe.subscribe('std_msgs/msg/String', '/episode', lambda m: json.loads(m.data))
    probe.start()
    launch = subprocess.run(command, env=subprocess_env(ros_domain_id), cwd=REPO,
                            capture_output=True, text=True, timeout=1200)
    output = launch.stdout + launch.stderr
    assert launch.returncode == 0, output[-4000:]
    for node in nodes:
        assert f'[{node}]' in output

    events = [e for _, e in probe.received['/episode']]
    ends = [e for e in events if e['event'] == 'end']
    assert len(ends) == episodes, events
    steps = sum(e['steps'] for e in ends)
    assert steps >= 800
    assert all(e['violations'] == 0 for e in ends), ends
    # Led around the obstacles, not parked in front of one (config input_weight).
    assert all(e['goal_reached'] for e in ends), ends
    h_true = np.array([h for _, h in probe.received['/h_true']])
    assert len(h_true) >= steps and h_true.min() >= 0.0

    # u_safe == u_RL wherever no row is active at u_RL. Safe commands answer proposals in order;
    # pair them through u_rl == u (the probe may have matched either writer a little later).
    params = load_params(find_config('unicycle'), 'safety_filter')
    problem = filter_config_from_params(params).problem
    import torch
    proposals = [p for _, p in probe.received['/cmd_proposed']]
    commands = [c for _, c in probe.received['/filter_info']]
    pairs, index = [], 0
    for command in commands:
        while index < len(proposals) and not np.array_equal(proposals[index]['u'],
                                                            command['u_rl']):
            index += 1
        if index < len(proposals):
            pairs.append((proposals[index], command))
            index += 1
    assert len(pairs) >= steps, (len(pairs), len(commands), len(proposals))
    passive = active = 0
    lo, hi = np.array(problem.system.u_min), np.array(problem.system.u_max)
    config = filter_config_from_params(params)
    box = [torch.tensor([values], dtype=torch.float64)
           for values in (config.static_mean, config.static_std)]
    for proposal, command in pairs:
        x, u_rl, u_safe = proposal['state'], proposal['u'], command['u']
        # The rows at u_RL under the config's disturbance box (the robust margin included).
        qp = problem.qp(torch.from_numpy(x).unsqueeze(0), torch.from_numpy(u_rl).unsqueeze(0),
                        *box)
        rows = qp.h[0, :problem.n_barriers].numpy()
        if np.all(rows > 1e-6) and np.all(u_rl < hi) and np.all(u_rl > lo):
            np.testing.assert_array_equal(u_safe, u_rl)  # exactly, through DDS and back
            passive += 1
        else:
            assert np.any(u_safe != u_rl)
            active += 1
    # The unsafe controller mostly asks for |omega| > 2.5 (a limit row) or pushes into an
    # obstacle, so pass-through steps are the minority; both kinds must be exercised.
    assert passive >= 10 and active > 100, (passive, active)

    if recorder:
        from rosbags.highlevel import AnyReader
        with AnyReader([bag]) as reader:
            connections = [c for c in reader.connections if c.topic == '/h_true']
            bag_h = [reader.deserialize(raw, c.msgtype).data
                     for c, _, raw in reader.messages(connections=connections)]
        # The recorder subscribes to each topic once discovery shows it; the simulator waits
        # for the filter and the controller, not for it, so a slower start (rclpy's) can miss
        # the first volatile samples. From then on it holds every one the probe received.
        assert len(bag_h) >= steps - 100, (len(bag_h), steps)
        np.testing.assert_array_equal(np.array(bag_h), h_true[len(h_true) - len(bag_h):])


def _without_repeats(items: list) -> list:
    """``items`` with each run of equal neighbours kept once."""
    return [item for i, item in enumerate(items) if i == 0 or item != items[i - 1]]

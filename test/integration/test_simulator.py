"""simulator + nominal_controller as separate processes in lock-step over real Cyclone DDS.

A listener process (this file run as a script) records ``state`` and ``episode`` to a JSON file.
The listener subscribes first, so the simulator publishes its first state before any controller
exists: it must re-publish after ``action_timeout_s`` (the late-subscriber path) and carry on.
The recorded state stream is then compared with an offline rollout of the same env, seed and
controller: lock-step over DDS must reproduce it exactly, step for step.
"""
from __future__ import annotations

import json
from pathlib import Path
import sys
import time

from dds_harness import spawn  # this directory: on sys.path for pytest and the children
import numpy as np
import pytest

TIMEOUT_S = 120.0
MAX_STEPS = 150
EPISODES = 2
SEED = 3


def role_listener(out_path: str, episodes: int) -> None:
    """Record every state section and episode event until ``episodes`` episodes ended."""
    from rcbf_ros.messages.conversions import msg_to_sections
    from rcbf_ros.ros.runtime import get_message, Node, QoSProfile, rclpy
    rclpy.init(args=[])
    node = Node('test_listener')
    record: dict = {'states': [], 'events': []}
    array = get_message('std_msgs/msg/Float64MultiArray')
    node.create_subscription(
        array, 'state', lambda m: record['states'].append(
            msg_to_sections(m)['state'].tolist()), QoSProfile(depth=1000))
    node.create_subscription(
        get_message('std_msgs/msg/String'), 'episode',
        lambda m: record['events'].append(json.loads(m.data)), QoSProfile(depth=100))
    deadline = time.monotonic() + TIMEOUT_S
    try:
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
            ends = [e for e in record['events'] if e['event'] == 'end']
            if len(ends) >= episodes:
                break
        for _ in range(10):  # trailing samples
            rclpy.spin_once(node, timeout_sec=0.02)
    finally:
        Path(out_path).write_text(json.dumps(record))
        node.destroy_node()
        rclpy.try_shutdown()




def _finish(simulator, listener, controller) -> str:
    """Wait for the simulator (its last episode) and the listener to exit 0; stop them all.

    Returns the simulator's stderr."""
    try:
        sim_out, sim_err = simulator.communicate(timeout=TIMEOUT_S)
        assert simulator.returncode == 0, f'simulator failed:\n{sim_err}{sim_out}'
        listener.communicate(timeout=TIMEOUT_S)
        assert listener.returncode == 0
    finally:
        for process in (controller, simulator, listener):
            if process.poll() is None:
                process.terminate()
                process.communicate(timeout=30)
    return sim_err


def _offline_rollout() -> tuple[list[np.ndarray], list[float], list[int]]:
    """Same env, seed and controller without middleware: states after reset and every step."""
    from rcbf_ros.envs import UnicycleEnv
    from rcbf_ros.envs.nominal import unicycle_go_to_goal
    from rcbf_ros.parameters.rules import find_config, load_params
    env = UnicycleEnv(load_params(find_config('unicycle'), 'simulator'), max_steps=MAX_STEPS,
                      random_start=True)
    states, returns, violations = [], [], []
    for episode in range(EPISODES):
        _, info = env.reset(seed=SEED if episode == 0 else None)
        states.append(info['state'])
        total, count, done = 0.0, 0, False
        while not done:
            _, reward, terminated, truncated, info = env.step(
                unicycle_go_to_goal(info['state'], env.goal))
            total += reward
            count += info['violation']
            states.append(info['state'])
            done = terminated or truncated
        returns.append(total)
        violations.append(count)
    return states, returns, violations


@pytest.mark.integration
def test_lockstep_simulator_and_nominal_controller(ros_domain_id, tmp_path):
    out = tmp_path / 'record.json'
    listener = spawn(ros_domain_id, __file__, 'listener', str(out), str(EPISODES))
    simulator = spawn(
        ros_domain_id, '-m', 'sim_nodes.simulator_node', '--ros-args',
        '-p', 'system:=unicycle', '-p', f'max_steps:={MAX_STEPS}', '-p', 'random_start:=true',
        '-p', f'max_episodes:={EPISODES}', '-p', f'seed:={SEED}', '-p', 'mode:=lockstep',
        '-p', 'action_timeout_s:=1.0')
    time.sleep(3.0)  # let the simulator publish its first state to the listener alone
    controller = spawn(
        ros_domain_id, '-m', 'sim_nodes.nominal_controller_node', '--ros-args',
        '-p', 'system:=unicycle', '-r', 'cmd_proposed:=cmd_safe')
    sim_err = _finish(simulator, listener, controller)
    record = json.loads(out.read_text())

    # A sample written while the reader is being matched can come twice (the transient-local
    # writer's history and the live write; seen on rmw_cyclonedds): equal neighbours are one.
    events = [e for i, e in enumerate(record['events']) if i == 0 or e != record['events'][i - 1]]
    assert [(e['event'], e['episode']) for e in events] == [
        ('start', 1), ('end', 1), ('start', 2), ('end', 2)]
    expected_states, expected_returns, expected_violations = _offline_rollout()
    for end, expected_return, violations in zip(events[1::2], expected_returns,
                                                expected_violations):
        assert end['return'] == pytest.approx(expected_return, abs=1e-12)
        assert end['violations'] == violations  # unfiltered: it does drive through obstacles
    assert sum(expected_violations) > 0
    assert events[1]['steps'] == MAX_STEPS or events[1]['goal_reached']
    assert events[0]['h_true_names'] == [f'obstacle_{i}' for i in range(5)]

    # The first state went out before the controller existed: re-published at least once.
    states = [np.asarray(s) for s in record['states']]
    assert np.array_equal(states[0], states[1])
    assert 'publishing it again' in sim_err
    deduplicated = [s for i, s in enumerate(states)
                    if i == 0 or not np.array_equal(s, states[i - 1])]
    assert len(deduplicated) == len(expected_states)
    np.testing.assert_array_equal(np.stack(deduplicated), np.stack(expected_states))


@pytest.mark.integration
def test_realtime_simulator_holds_the_last_action(ros_domain_id, tmp_path):
    from rcbf_ros.envs import UnicycleEnv
    from rcbf_ros.parameters.rules import find_config, load_params
    out = tmp_path / 'record.json'
    steps = 100
    listener = spawn(ros_domain_id, __file__, 'listener', str(out), '1')
    simulator = spawn(
        ros_domain_id, '-m', 'sim_nodes.simulator_node', '--ros-args',
        '-p', 'system:=unicycle', '-p', f'max_steps:={steps}', '-p', 'max_episodes:=1',
        '-p', 'mode:=realtime', '-p', 'rate_hz:=50.0')
    controller = spawn(
        ros_domain_id, '-m', 'sim_nodes.nominal_controller_node', '--ros-args',
        '-p', 'system:=unicycle', '-r', 'cmd_proposed:=cmd_safe')
    _finish(simulator, listener, controller)
    record = json.loads(out.read_text())
    events = record['events']
    assert [(e['event'], e['episode']) for e in events] == [('start', 1), ('end', 1)]
    assert events[1]['steps'] == steps and events[1]['truncated']
    states = np.asarray(record['states'])
    assert len(states) == steps + 1  # reliable: the reset state and one per step
    # Zero-order hold of zeros alone (no controller) would only slide back down the slope.
    env = UnicycleEnv(load_params(find_config('unicycle'), 'simulator'), max_steps=steps)
    _, info = env.reset(seed=0)
    np.testing.assert_array_equal(states[0], info['state'])
    for _ in range(steps):
        _, _, _, _, info = env.step([0.0, 0.0])
    assert np.linalg.norm(states[-1][:2] - info['state'][:2]) > 0.5
    # The goal-seeking actions were applied: the robot got closer to the goal (2.5, 2.5).
    assert np.linalg.norm(states[-1][:2] - 2.5) < np.linalg.norm(states[0][:2] - 2.5) - 0.5



@pytest.mark.integration
@pytest.mark.parametrize('value, shown', [('cmd_safe', "'cmd_safe'"), ("['', 'x']", "['', 'x']")])
def test_bad_wait_for_publishers_exits_2_in_one_line(ros_domain_id, value, shown):
    simulator = spawn(ros_domain_id, '-m', 'sim_nodes.simulator_node', '--ros-args',
                      '-p', f'wait_for_publishers:={value}')
    out, err = simulator.communicate(timeout=TIMEOUT_S)
    assert simulator.returncode == 2, err
    assert err.strip() == ('simulator: invalid parameters: wait_for_publishers: expected a '
                           f'list of topic names, got {shown}')

if __name__ == '__main__':
    if sys.argv[1] == 'listener':
        role_listener(sys.argv[2], int(sys.argv[3]))

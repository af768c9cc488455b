"""The simulator's lock-step takes each answer for the state it answers: a late duplicate answer
to a state published again is dropped, whether the answer names its state by the filter's
``filter_info`` ``state`` section or by a TwistStamped's stamp. Callbacks called directly (one
process, no peers)."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.conversions import sections_to_msg
from rcbf_ros.ros.dds import rclpy_compat as rclpy


@pytest.fixture
def make_simulator(ros_domain_id):
    nodes = []

    def make(*params: str) -> Any:
        from sim_nodes.simulator_node import SimulatorNode
        args = ['--ros-args', '-p', 'system:=unicycle', '-p', 'max_steps:=50']
        for param in params:
            args += ['-p', param]
        rclpy.init(args=args, domain_id=ros_domain_id)
        node = SimulatorNode()
        nodes.append(node)
        node.start_episode()  # as once the loop listens
        return node
    yield make
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()


def _filter_info(u: list[float], state: np.ndarray) -> Any:
    """What the safety filter publishes on filter_info (the launches' action topic)."""
    u = np.asarray(u)
    return sections_to_msg({'u': u, 'u_rl': u, 'u_s': np.zeros(2), 'fail_safe': [0.0],
                            'status': [0.0], 'h': np.ones(5), 'state': state})


def _twist_stamped(u: list[float], stamp_ns: int) -> Any:
    msg = get_message('geometry_msgs/msg/TwistStamped')()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.twist.linear.x, msg.twist.angular.z = u
    return msg


def test_a_late_duplicate_filter_info_answer_is_dropped(make_simulator):
    sim = make_simulator()
    first = sim.info['state'].copy()
    sim.on_action(_filter_info([1.0, 0.0], first))
    assert sim.env.steps == 1 and sim.awaiting_action
    second = sim.info['state'].copy()
    sim.on_action(_filter_info([1.0, 0.0], first))       # the answer to the re-published state
    assert sim.env.steps == 1 and sim.awaiting_action    # dropped, still waiting
    sim.on_action(_filter_info([0.5, 0.2], second))
    assert sim.env.steps == 2
    np.testing.assert_array_equal(sim.applied, [0.5, 0.2])


def test_a_late_duplicate_twist_stamped_answer_is_dropped(make_simulator):
    sim = make_simulator('command_type:=twist_stamped', 'state_type:=odometry')
    odometry = sim.state_message()
    assert (odometry.header.frame_id, odometry.child_frame_id) == ('map', 'base_link')
    first = sim.clock_ns
    assert first == int(odometry.header.stamp.sec) * 10**9 + int(odometry.header.stamp.nanosec)
    sim.on_action(_twist_stamped([1.0, 0.0], first))
    assert sim.env.steps == 1 and sim.clock_ns == first + sim.dt_ns
    sim.on_action(_twist_stamped([1.0, 0.0], first))      # late: the stamp of an earlier state
    assert sim.env.steps == 1 and sim.awaiting_action
    sim.on_action(_twist_stamped([0.5, 0.2], sim.clock_ns))
    assert sim.env.steps == 2
    # A stamp that names no state of this run (a controller's own clock) is taken.
    sim.on_action(_twist_stamped([0.5, 0.2], 1_700_000_000 * 10**9))
    assert sim.env.steps == 3


def test_a_state_published_again_keeps_its_stamp(make_simulator):
    sim = make_simulator('state_type:=odometry')
    stamp = sim.state_message().header.stamp
    sim.publish_state()  # the watchdog's re-publication
    assert sim.state_message().header.stamp == stamp
    np.testing.assert_allclose(
        [sim.state_message().pose.pose.position.x, sim.state_message().pose.pose.position.y],
        sim.info['state'][:2])


@pytest.mark.parametrize('param, key', [
    ('state_type:=odom', 'state_type'), ('command_type:=twist_cov', 'command_type'),
    ("twist_fields:=['linear.x']", 'twist_fields'),
])
def test_bad_message_settings_are_refused_naming_the_key(ros_domain_id, param, key):
    from sim_nodes.simulator_node import SimulatorNode
    rclpy.init(args=['--ros-args', '-p', param, '-p', 'command_type:=twist']
               if key == 'twist_fields' else ['--ros-args', '-p', param],
               domain_id=ros_domain_id)
    try:
        with pytest.raises(ValueError, match=f'^{key}: '):
            SimulatorNode()
    finally:
        rclpy.try_shutdown()


def test_odometry_state_needs_a_system_an_odometry_holds(ros_domain_id):
    from sim_nodes.simulator_node import SimulatorNode
    rclpy.init(args=['--ros-args', '-p', 'system:=pvtol', '-p', 'state_type:=odometry'],
               domain_id=ros_domain_id)
    try:
        with pytest.raises(ValueError, match="^state_type: odometry holds the state of "
                                             r"\['unicycle'\] only, not 'pvtol'"):
            SimulatorNode()
    finally:
        rclpy.try_shutdown()


def test_every_closed_loop_gives_the_simulator_the_filters_answers_with_their_state():
    # cmd_safe holds the command alone; filter_info's first section is that command and its
    # state section the state answered, which lock-step needs to drop late answers.
    from rcbf_ros.launch.table import CLOSED_LOOPS
    for setup in CLOSED_LOOPS:
        simulator = setup.node('simulator')
        assert ('cmd_safe', 'filter_info') in simulator.remappings, setup.name
        assert not any(source == 'filter_info' or target == 'cmd_safe'
                       for entry in setup.nodes if entry.name != 'simulator'
                       for source, target in entry.remappings), setup.name


def test_the_simulators_own_parameters_describe_themselves(make_simulator):
    from sim_nodes.simulator_node import NODE_PARAMETERS
    node = make_simulator()
    described = 0
    for spec in NODE_PARAMETERS:
        if spec.pattern or spec.name == 'max_steps':  # max_steps came as an override
            continue
        descriptor = node.describe_parameter(spec.name)
        assert descriptor.description == spec.description, spec.name
        ranges = [*descriptor.floating_point_range, *descriptor.integer_range]
        assert [(r.from_value, r.to_value) for r in ranges] == (
            [spec.range] if spec.range else []), spec.name
        described += 1
    assert described >= 5

"""When the simulator starts its first episode: once the loop listens (loop_waits_for); and
the Odometry frames it is given."""
from __future__ import annotations

import pytest

from sim_nodes.simulator_node import loop_waits_for

FILTER, CONTROLLER, RECORDER, ECHO = b'f' * 12, b'c' * 12, b'r' * 12, b'e' * 12
TOPICS = ('/state', '/observation', '/h_true', '/reward', '/episode', '/sim/step')


def _waits_for(readers: dict, publishers: dict, matched: dict | None = None) -> str:
    counts = {topic: len(readers.get(topic, ())) for topic in TOPICS}
    counts.update(matched or {})
    return loop_waits_for(state_topic='/state', matched=counts,
                          readers={topic: readers.get(topic, []) for topic in TOPICS},
                          loop_publishers=publishers)


def test_without_loop_publishers_a_state_subscriber_is_enough():
    assert _waits_for({}, {}) == 'a subscriber on /state'
    assert _waits_for({'/state': [ECHO]}, {}) == ''


def test_waits_for_each_loop_publisher_to_exist_and_listen():
    loop = {'/cmd_safe': [FILTER], '/cmd_proposed': []}
    # Something echoes /state: the old rule would have started here, without the controller.
    assert _waits_for({'/state': [ECHO, FILTER]}, loop) == 'a publisher on /cmd_proposed'
    loop['/cmd_proposed'] = [CONTROLLER]  # its publisher is up, its subscription not yet
    assert _waits_for({'/state': [ECHO, FILTER]}, loop) == \
        'the publisher on /cmd_proposed to subscribe to the simulator'
    assert _waits_for({'/state': [ECHO, FILTER, CONTROLLER]}, loop) == ''


def test_the_loop_may_listen_on_any_of_the_simulators_topics():
    loop = {'/cmd_safe': [FILTER], '/cmd_proposed': [CONTROLLER]}
    assert _waits_for({'/state': [FILTER], '/sim/step': [CONTROLLER]}, loop) == ''


def test_waits_until_the_loops_subscriptions_are_matched():
    loop = {'/cmd_safe': [FILTER], '/cmd_proposed': [CONTROLLER]}
    readers = {'/state': [FILTER, CONTROLLER]}
    assert _waits_for(readers, loop, {'/state': 1}) == \
        '2 subscription(s) on /state to match (1 so far)'


def test_processes_outside_the_loop_neither_hold_back_nor_count():
    loop = {'/cmd_safe': [FILTER], '/cmd_proposed': [CONTROLLER]}
    # A recorder (or anyone) subscribed to every topic but not matched yet does not hold back.
    readers = {topic: [RECORDER] for topic in TOPICS}
    readers['/state'] = [RECORDER, FILTER, CONTROLLER]
    assert _waits_for(readers, loop, {topic: 0 for topic in TOPICS} | {'/state': 2}) == ''


def test_waits_for_each_named_listener_to_subscribe_to_the_loops_topics():
    loop = {'/cmd_safe': [FILTER], '/cmd_proposed': [CONTROLLER]}
    readers = {'/state': [FILTER, CONTROLLER]}

    def waits(listening: dict, matched: int) -> str:
        return loop_waits_for(state_topic='/state', matched={'/state': matched},
                              readers=readers, loop_publishers=loop,
                              listeners={'recorder': listening})
    everywhere = {'/state': [RECORDER], '/cmd_safe': [RECORDER], '/cmd_proposed': [RECORDER]}
    assert waits(everywhere | {'/state': []}, 2) == 'recorder to subscribe to /state'
    # On the state but not yet on the proposals: its first proposals would be lost.
    assert waits(everywhere | {'/cmd_proposed': []}, 2) == \
        'recorder to subscribe to /cmd_proposed'
    readers = {'/state': [FILTER, CONTROLLER, RECORDER]}
    # Subscribed but not matched yet: its first states would be lost.
    assert waits(everywhere, 2) == '3 subscription(s) on /state to match (2 so far)'
    assert waits(everywhere, 3) == ''


@pytest.mark.parametrize('frames, key', [
    ({'frame_id': ''}, 'frame_id'), ({'frame_id': '/map'}, 'frame_id'),
    ({'child_frame_id': 'base link'}, 'child_frame_id'),
    ({'child_frame_id': 'b' * 1025}, 'child_frame_id'),
    ({'child_frame_id': 'map'}, 'child_frame_id'),     # a self-parent odometry
])
def test_odometry_frames_the_readers_refuse_are_refused_naming_the_key(frames, key):
    from rcbf_ros.parameters.reader import read_parameters
    from sim_nodes.simulator_node import SimulatorSettings
    with pytest.raises(ValueError, match=f'^{key}: '):
        read_parameters(SimulatorSettings, {'state_type': 'odometry', **frames})
    read_parameters(SimulatorSettings, {'state_type': 'array', **frames})  # not published

"""The safety_filter node's callbacks on CDR bytes, called directly (one process, no peers).

Every sample gets an answer or a recorded reason, never an exception: an undecodable proposal is
answered with the fail-safe and ``undecodable proposal``, an undecodable state makes the latest
state a bad one, and the diagnostics count what was dropped (undecodable) and refused
(decodable but unusable). A defect inside the filtering yields the fail-safe, not a traceback.
"""
from __future__ import annotations

from pathlib import Path
import struct
from typing import Any

import numpy as np
import pytest

from rcbf_ros.ros import filter_logic
from rcbf_ros.ros.conversions import array_to_twist, msg_to_sections, sections_to_msg
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.messages import serialize_message

REPO = Path(__file__).resolve().parents[2]
UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
FAIL_SAFE = [0.0, 0.5]
GOOD_STATE = [-0.85, 0.0, 0.0]


def _cdr(sections: dict) -> bytes:
    return serialize_message(sections_to_msg(sections))


def _non_utf8_label(sections: dict) -> bytes:
    """``sections`` as CDR with the first byte of the first label made 0xFF (not UTF-8)."""
    data = bytearray(_cdr(sections))
    assert struct.unpack_from('<I', data, 8)[0] >= 2
    data[12] = 0xFF
    return bytes(data)


class FilterHarness:
    """A SafetyFilterNode whose two publishers record instead of sending."""

    def __init__(self) -> None:
        from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
        self.node = SafetyFilterNode()
        self.commands: list[Any] = []
        self.diagnostics: list[tuple[int, str, dict[str, str]]] = []
        self.node._cmd_pub.publish = self.commands.append

        def diagnose(msg: Any) -> None:
            status = msg.status[0]
            self.diagnostics.append((int(status.level), status.message,
                                     {kv.key: kv.value for kv in status.values}))
        self.node._diag_pub.publish = diagnose

    def propose(self, data: bytes) -> tuple[np.ndarray, tuple[int, str, dict[str, str]]]:
        before = len(self.commands)
        self.node._on_proposal(data)
        assert len(self.commands) == before + 1
        command = self.commands[-1]
        if self.node.settings.command_type == 'array':
            u = msg_to_sections(command)['u']
        else:
            u = np.array([command.linear.x, command.angular.z])
        return u, self.diagnostics[-1]


def _harness(ros_domain_id: int, *ros_args: str):
    # safety_filter:...: after the file, so that it wins over its /safety_filter section.
    rclpy.init(args=['--ros-args', '--params-file', UNICYCLE, '-p',
                     f'safety_filter:fail_safe_action:={FAIL_SAFE}', *ros_args],
               domain_id=ros_domain_id)
    return FilterHarness()


@pytest.fixture
def harness(ros_domain_id):
    instance = _harness(ros_domain_id)
    yield instance
    instance.node.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture
def twist_harness(ros_domain_id):
    instance = _harness(ros_domain_id, '-p', 'safety_filter:command_type:=twist')
    yield instance
    instance.node.destroy_node()
    rclpy.try_shutdown()


def test_undecodable_proposal_gets_the_fail_safe_and_is_counted(harness):
    harness.node._on_state(_cdr({'state': GOOD_STATE}))
    u, (level, message, values) = harness.propose(_non_utf8_label({'u': [2.5, 0.0]}))
    np.testing.assert_array_equal(u, FAIL_SAFE)
    assert level == filter_logic.ERROR
    assert message.startswith('undecodable proposal: ') and 'utf-8' in message
    assert values['fail_safe'] == 'True' and values['dropped_samples'] == '1'
    assert values['refused_proposals'] == '0' and values['refused_states'] == '0'
    u, (level, message, values) = harness.propose(_cdr({'u': [2.5, 0.0]}))
    assert level == filter_logic.OK and 0.0 < u[0] < 2.5   # the next one is filtered again
    assert values['dropped_samples'] == '1'


def test_refused_proposals_and_states_are_counted(harness):
    harness.node._on_state(_cdr({'state': [np.nan, 0.0, 0.0]}))
    _, (_, message, values) = harness.propose(_cdr({'u': [np.nan, 0.0]}))
    assert message.startswith('bad proposal: u: contains NaN')
    assert values['refused_proposals'] == '1' and values['refused_states'] == '1'
    _, (_, message, values) = harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert message.startswith('bad state: state: contains NaN')
    assert values['refused_proposals'] == '1' and values['dropped_samples'] == '0'


def test_undecodable_state_replaces_the_latest_state_as_bad(harness):
    harness.node._on_state(_cdr({'state': GOOD_STATE}))
    harness.node._on_state(_non_utf8_label({'state': GOOD_STATE}))
    u, (level, message, values) = harness.propose(_cdr({'u': [1.0, 0.0]}))
    np.testing.assert_array_equal(u, FAIL_SAFE)
    assert message.startswith('bad state: undecodable sample: ')
    assert values['dropped_samples'] == '1'
    harness.node._on_state(_cdr({'state': GOOD_STATE}))
    _, (level, _, _) = harness.propose(_cdr({'u': [1.0, 0.0]}))
    assert level == filter_logic.OK


def test_undecodable_twist_gets_the_fail_safe(twist_harness):
    twist = serialize_message(array_to_twist([1.0, 0.0], ['linear.x', 'angular.z']))
    u, (_, message, values) = twist_harness.propose(twist[:20])
    np.testing.assert_array_equal(u, FAIL_SAFE)
    assert message.startswith('undecodable proposal: ') and 'geometry_msgs/msg/Twist' in message
    assert values['dropped_samples'] == '1'


def test_a_defect_in_the_filtering_yields_the_fail_safe_not_an_exception(harness, monkeypatch):
    def broken(**_kwargs: Any) -> None:
        raise RuntimeError('broken\nfilter')
    monkeypatch.setattr(filter_logic, 'decide', broken)
    monkeypatch.setattr(filter_logic, 'state_from_sections', broken)
    harness.node._on_state(_cdr({'state': GOOD_STATE}))
    assert harness.node._latest_state.error == 'internal error: RuntimeError: broken filter'
    u, (level, message, _) = harness.propose(_cdr({'u': [1.0, 0.0]}))
    np.testing.assert_array_equal(u, FAIL_SAFE)
    assert level == filter_logic.ERROR
    assert message == 'internal error: RuntimeError: broken filter'


def test_random_and_mutated_samples_never_raise_and_each_proposal_is_answered(harness):
    rng = np.random.default_rng(3)
    valid = [_cdr({'u': [1.0, 0.0]}), _cdr({'u': [1.0, 0.0], 'state': GOOD_STATE}),
             _cdr({'state': GOOD_STATE})]
    system = harness.node.config.problem.system
    low, high = np.array(system.u_min) - 1e-6, np.array(system.u_max) + 1e-6
    for trial in range(300):
        if trial % 4 == 0:
            data = rng.integers(0, 256, int(rng.integers(0, 100)), dtype=np.uint8).tobytes()
        else:
            data = bytearray(valid[trial % 3])
            for _ in range(int(rng.integers(1, 4))):
                data[int(rng.integers(0, len(data)))] ^= 1 << int(rng.integers(0, 8))
            data = bytes(data)
        harness.node._on_state(data)
        u, (level, _, _) = harness.propose(data)
        assert np.all(np.isfinite(u)) and np.all(u >= low) and np.all(u <= high)
        if level == filter_logic.ERROR:
            assert u.tolist() == FAIL_SAFE
    counts = harness.node.input_counts
    assert counts['dropped_samples'] > 0 and counts['refused_proposals'] > 0, counts

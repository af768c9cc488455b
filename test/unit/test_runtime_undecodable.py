"""The Cyclone runtime never lets an undecodable sample escape into the executor: the
subscription drops it, counts it and warns (one line naming the topic, throttled), and the
next sample is delivered as usual. A raw subscription gets the bytes, undecodable or not."""
from __future__ import annotations

import struct

import pytest
from runtime_node import runtime_node

from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.conversions import sections_to_msg
from rcbf_ros.ros.dds import endpoints as dds_endpoints
from rcbf_ros.ros.dds import rclpy_compat as rclpy

Array = get_message('std_msgs/msg/Float64MultiArray')


def _non_utf8_label() -> bytes:
    """A sample that DDS accepts (its structure is valid) but whose label is not UTF-8."""
    data = bytearray(serialize_message(sections_to_msg({'u': [1.0, 0.5]})))
    assert struct.unpack_from('<I', data, 8)[0] == 2 and data[12:14] == b'u\x00'
    data[12] = 0xFF
    return bytes(data)


@pytest.fixture
def node(ros_domain_id):
    with runtime_node('undecodable_test', domain_id=ros_domain_id) as instance:
        yield instance


def _spin_until(node, condition, limit: int = 200) -> None:
    for _ in range(limit):
        if condition():
            return
        rclpy.spin_once(node, timeout_sec=0.05)
    raise AssertionError('condition not met')


def test_undecodable_samples_are_dropped_counted_and_reported_once(node, capfd, monkeypatch):
    monkeypatch.setattr(dds_endpoints, 'UNDECODABLE_WARNING_PERIOD_S', 60.0)
    received, raw = [], []
    publisher = node.create_publisher(Array, 'cmd_proposed', 10)
    subscription = node.create_subscription(Array, 'cmd_proposed',
                                            lambda m: received.append(m.data.tolist()), 10)
    node.create_subscription(Array, 'cmd_proposed', raw.append, 10, raw=True)
    _spin_until(node, lambda: publisher.get_subscription_count() == 2)
    bad = _non_utf8_label()
    for _ in range(3):
        publisher.publish(bad)
    publisher.publish(sections_to_msg({'u': [2.0, 0.0]}))
    _spin_until(node, lambda: received and len(raw) == 4)   # spin_once never raised
    assert received == [[2.0, 0.0]]
    assert subscription.undecodable_count == 3
    assert raw[:3] == [bad] * 3
    warnings = [line for line in capfd.readouterr().err.splitlines() if 'undecodable' in line]
    assert len(warnings) == 1, warnings
    assert '[WARN]' in warnings[0] and '/cmd_proposed' in warnings[0]
    assert 'std_msgs/msg/Float64MultiArray' in warnings[0] and 'utf-8' in warnings[0]

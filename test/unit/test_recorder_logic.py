"""The recorder's pure decisions: what QoS to request, and which bytes of a sample to store."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from rcbf_ros.bag import RecordedQos
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.ros.dds.messages import dds_payload
from rcbf_ros.ros.recorder_node import (
    cdr_payload,
    RecorderConfig,
    RecorderNode,
    request_durability,
    request_reliability,
)
from rcbf_ros.ros.runtime import DurabilityPolicy

STORE = jazzy_typestore()
STRING = 'std_msgs/msg/String'
LATCHED = RecordedQos(durability='transient_local')


def _string(text: str) -> bytes:
    return bytes(STORE.serialize_cdr(STORE.types[STRING](data=text), STRING))


@pytest.mark.parametrize('text', ['', 'a', 'ab', 'abc', 'abcd', '{"event": "start"}'])
def test_stored_bytes_are_the_serialized_message_whatever_the_padding(text):
    cdr = _string(text)
    assert cdr_payload(dds_payload(cdr)) == cdr
    assert cdr_payload(cdr) == cdr


def test_undeclared_padding_is_kept_as_received():
    # rmw_cyclonedds pads with zeros without saying so; rosbag2 stores such samples whole.
    padded = _string('ab') + b'\x00'
    assert padded[3] == 0 and cdr_payload(padded) == padded


def test_declared_padding_goes_even_if_not_zero_and_stubs_pass_through():
    cdr = _string('ab')  # 11 bytes
    sample = cdr[:3] + bytes([cdr[3] | 1]) + cdr[4:] + b'\xab'
    assert cdr_payload(sample) == cdr
    assert cdr_payload(b'\x00\x01\x00\x03') == b'\x00\x01\x00\x03'  # states more than it has
    assert cdr_payload(b'\x00\x01') == b'\x00\x01'


def test_durability_follows_the_publishers_offer():
    assert request_durability([LATCHED]) == 'transient_local'
    assert request_durability([LATCHED, LATCHED]) == 'transient_local'
    # A transient-local reader would not match the volatile writer: ask for volatile.
    assert request_durability([LATCHED, RecordedQos()]) == 'volatile'
    assert request_durability([]) == 'volatile'


def test_reliability_follows_the_publishers_offer():
    assert request_reliability([RecordedQos()], False) == 'reliable'
    assert request_reliability([RecordedQos(), RecordedQos.sensor_data()], False) == 'best_effort'
    assert request_reliability([RecordedQos()], True) == 'best_effort'


class _FakeRecorderNode:
    """What RecorderNode._subscribe uses of its node, recording the subscriptions it makes."""

    def __init__(self, offered: list[RecordedQos] | None) -> None:
        self.offered = offered
        self.config = RecorderConfig()
        self.recorder = SimpleNamespace(add=lambda topic, type_name, qos: True,
                                        dropped_unknown_type=set())
        self._subscriptions_by_topic: dict = {}
        self.subscribed: list[tuple[str, object]] = []

    def _offered_qos(self, topic: str) -> list[RecordedQos] | None:
        return self.offered

    def create_subscription(self, msg_type, topic, callback, qos, raw):
        self.subscribed.append((topic, qos))
        return object()

    def get_logger(self):
        return SimpleNamespace(info=lambda text: None, warning=lambda text: None)


def test_a_topic_is_subscribed_once_it_has_a_publisher_with_its_offer():
    waiting = _FakeRecorderNode([])  # seen through a subscriber only (an echo started first)
    RecorderNode._subscribe(waiting, '/episode', STRING)
    assert waiting.subscribed == []  # a volatile guess would miss the latched history
    latched = _FakeRecorderNode([LATCHED])
    RecorderNode._subscribe(latched, '/episode', STRING)
    ((topic, qos),) = latched.subscribed
    assert topic == '/episode' and qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    unknown = _FakeRecorderNode(None)  # a runtime that does not report offers: as before
    RecorderNode._subscribe(unknown, '/episode', STRING)
    assert unknown.subscribed[0][1].durability == DurabilityPolicy.VOLATILE


def test_a_sample_the_bag_refuses_is_left_out_and_the_recording_goes_on(tmp_path):
    from rcbf_ros.bag import BagWriter, read_bag_messages
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.recorder_node import Recorder
    type_name = 'std_msgs/msg/Float64MultiArray'
    reports: list[str] = []
    bag = BagWriter(tmp_path / 'bag')
    clock = iter(range(1, 100))
    recorder = Recorder(bag, lambda: next(clock) * 1000, report=reports.append)
    assert recorder.add('/state', type_name, [])
    good = serialize_message(get_message(type_name)(data=[1.0, 2.0]), type_name)
    for sample in (good, b'\xff\xff\x00\x00junk', b'', good, b'\x07'):
        recorder.on_message('/state', sample)  # never raises
    recorder.close()
    assert recorder.refused_samples == 3 and recorder.stopped is None
    assert len(reports) == 1 and 'left out of the bag' in reports[0]
    assert [m.data for m, _ in read_bag_messages(tmp_path / 'bag')].count(good) == 2

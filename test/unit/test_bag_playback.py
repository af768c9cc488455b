"""Replay scheduling and QoS choice (pure logic of the replay node) on real bags."""
from __future__ import annotations

from itertools import islice
from pathlib import Path
from typing import Iterator

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.bag import BagMessage, BagWriter, RecordedQos
from rcbf_ros.bag.playback import iter_bag_messages, playback_schedule, replay_qos

T0 = 1_000_000_000_000


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    with BagWriter(tmp_path / 'b') as writer:
        writer.add_topic('/a', 'std_msgs/msg/Float64MultiArray')
        writer.add_topic('/b', 'geometry_msgs/msg/Twist', qos=RecordedQos.sensor_data())
        # Written out of time order across topics: playback must follow log time.
        for i in range(5):
            writer.write_message('/a', {'data': [float(i)]}, T0 + i * 100_000_000)
        for i in range(5):
            writer.write_message('/b', {'linear': {'x': float(i)}}, T0 + i * 100_000_000 + 50)
    return tmp_path / 'b'


def test_schedule_follows_log_time_scaled_by_rate(bag: Path) -> None:
    messages = list(iter_bag_messages(bag))
    assert [m.topic for m in messages[:4]] == ['/a', '/b', '/a', '/b']
    offsets = [s.send_offset_s for s in playback_schedule(messages, rate=2.0)]
    expected = [(m.log_time_ns - T0) / 1e9 / 2.0 for m in messages]
    assert offsets == pytest.approx(expected, abs=1e-12)


def test_loop_repeats_after_one_gap(bag: Path) -> None:
    messages = list(iter_bag_messages(bag, topics=['/a']))
    assert len(messages) == 5
    once = [s.send_offset_s for s in playback_schedule(messages)]
    looped = list(islice(playback_schedule(messages, loops=0), 15))
    # span 0.4 s, mean gap 0.1 s: pass j starts at j * 0.5 s.
    assert [s.send_offset_s for s in looped[5:10]] == pytest.approx([t + 0.5 for t in once])
    assert [s.message.data for s in looped[10:]] == [m.data for m in messages]
    assert len(list(playback_schedule(messages, loops=3))) == 15


def test_bad_rate_is_named(bag: Path) -> None:
    with pytest.raises(ValueError, match='rate'):
        list(playback_schedule(list(iter_bag_messages(bag)), rate=0.0))


def test_replay_qos_keeps_agreed_offer_else_default() -> None:
    assert replay_qos([RecordedQos.sensor_data()]).reliability == 'best_effort'
    mixed = replay_qos([RecordedQos(), RecordedQos.sensor_data()])
    assert (mixed.reliability, mixed.history) == ('reliable', 'keep_all')
    assert replay_qos([RecordedQos(durability='transient_local')]).durability == 'transient_local'


@settings(max_examples=100, deadline=None)
@given(gaps=st.lists(st.integers(0, 10**9), max_size=8), rate=st.floats(0.1, 10.0),
       loops=st.integers(1, 3))
def test_a_streamed_schedule_is_the_listed_one_and_takes_one_message_at_a_time(
        gaps: list[int], rate: float, loops: int) -> None:
    """Messages given as a callable (read afresh each pass) get the send times of the
    formula, as a list does; and each is taken from the stream only when it is due."""
    times = [T0 + sum(gaps[:k]) for k in range(len(gaps))]
    messages = [BagMessage('/a', 't', bytes([k % 256]), t, t) for k, t in enumerate(times)]
    taken = []

    def stream() -> Iterator[BagMessage]:
        for message in messages:
            taken.append(message)
            yield message

    scheduled = []
    for item in playback_schedule(stream, rate=rate, loops=loops):
        assert taken[-1] is item.message  # nothing read ahead: memory of one message
        scheduled.append(item)
    listed = list(playback_schedule(messages, rate=rate, loops=loops))
    assert scheduled == listed
    span = (times[-1] - times[0]) / 1e9 / rate if times else 0.0
    period = span + (span / (len(times) - 1) if len(times) > 1 else 0.0)
    expected = [j * period + (t - times[0]) / 1e9 / rate for j in range(loops) for t in times]
    assert [s.send_offset_s for s in scheduled] == pytest.approx(expected, abs=1e-9)
    assert [s.message for s in scheduled] == messages * loops

"""Replay publishes only what DDS can send as recorded: CDR messages of a ROS type.

A channel recorded in another message encoding (JSON, protobuf) or with a schema that is not
a ROS message definition is left out before anything is published, one line naming the topic
and its encoding (refused if asked for by name); a message that DDS refuses all the same ends
the replay with one line and exit status 2, never a traceback.
"""
from __future__ import annotations

from pathlib import Path

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
from mcap.writer import Writer
import pytest

from rcbf_ros.bag import bag_info
from rcbf_ros.bag.playback import topics_to_play
from rcbf_ros.messages.typestore import jazzy_typestore, message_definition_text

TYPE = 'std_msgs/msg/Float64MultiArray'
EMPTY_ARRAY = b'\x00\x01\x00\x00' + bytes(12)
"""A Float64MultiArray in CDR: no dimensions, offset 0, no data."""
PLAYABLE = ('cdr', 'ros2msg'), ('cdr', 'ros2idl')


def _bag(path: Path, channels: list[tuple[str, str, str, bytes]]) -> Path:
    """An MCAP file with one message on each ``(topic, message encoding, schema encoding,
    message)``; schema encoding '' is a channel without a schema."""
    definition = message_definition_text(TYPE, jazzy_typestore()).encode()
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start('ros2', 'test')
        for k, (topic, message_encoding, schema_encoding, data) in enumerate(channels):
            schema = writer.register_schema(TYPE, schema_encoding, definition) \
                if schema_encoding else 0
            channel = writer.register_channel(topic, message_encoding, schema)
            writer.add_message(channel, 1000 + k, data, 1000 + k)
        writer.finish()
    return path


encodings = st.tuples(st.sampled_from(['cdr', 'json', 'protobuf', 'ros1', 'CDR', '']),
                      st.sampled_from(['ros2msg', 'ros2idl', 'jsonschema', 'protobuf', '']))


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kinds=st.lists(encodings, min_size=1, max_size=5))
def test_only_cdr_topics_of_a_ros_type_are_played_and_each_other_is_named(tmp_path, kinds):
    channels = [(f'/t{k}', message, schema, EMPTY_ARRAY) for k, (message, schema)
                in enumerate(kinds)]
    info = bag_info(_bag(tmp_path / 'bag.mcap', channels))
    playable = [f'/t{k}' for k, kind in enumerate(kinds) if kind in PLAYABLE]
    if not playable:
        with pytest.raises(ValueError, match='^no topic of the bag can be played: topic /t0: '):
            topics_to_play(info)
        return
    played, skipped = topics_to_play(info)
    assert played == sorted(playable)
    assert len(skipped) == len(kinds) - len(playable)
    for line, (k, (message, schema)) in zip(skipped, [(k, kind) for k, kind in enumerate(kinds)
                                                     if kind not in PLAYABLE]):
        assert '\n' not in line and line.startswith(f'topic /t{k}: ')
        assert (f'message encoding {message!r}' if message != 'cdr'
                else f'schema encoding {schema!r}') in line
    for k, kind in enumerate(kinds):  # asked for by name: played, or refused naming it
        if kind in PLAYABLE:
            assert topics_to_play(info, [f'/t{k}']) == ([f'/t{k}'], [])
        else:
            with pytest.raises(ValueError, match=rf'^topic /t{k}: .* it cannot be played$'):
                topics_to_play(info, [f'/t{k}'])


def test_a_topic_whose_channels_disagree_on_the_encoding_is_not_played(tmp_path):
    info = bag_info(_bag(tmp_path / 'bag.mcap', [
        ('/a', 'cdr', 'ros2msg', EMPTY_ARRAY), ('/a', 'json', 'ros2msg', b'{}'),
        ('/b', 'cdr', 'ros2msg', EMPTY_ARRAY)]))
    assert info.topics['/a'].message_encoding == 'cdr, json'
    assert topics_to_play(info) == (['/b'], ["topic /a: message encoding 'cdr, json', not "
                                             "'cdr': not played"])


def test_a_topic_not_in_the_bag_is_refused_naming_it(tmp_path):
    info = bag_info(_bag(tmp_path / 'bag.mcap', [('/a', 'cdr', 'ros2msg', EMPTY_ARRAY)]))
    with pytest.raises(ValueError, match=r"^topics \['/nope'\] are not in the bag$"):
        topics_to_play(info, ['/a', '/nope'])


# -- the node -------------------------------------------------------------------------------

def _replay(bag: Path, capsys, *params: str) -> tuple[int, list[str]]:
    from rcbf_ros.ros.replay_node import main
    args = ['replay', '--ros-args', '-p', f'bag:={bag}', '-p', 'linger_s:=0.0']
    for param in params:
        args += ['-p', param]
    code = main(args)
    err = capsys.readouterr().err
    assert 'Traceback' not in err, err
    return code, [line for line in err.splitlines() if line.strip()]


def test_the_node_leaves_a_json_topic_out_before_publishing_and_plays_the_rest(
        tmp_path, capsys, monkeypatch, ros_domain_id):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    bag = _bag(tmp_path / 'bag.mcap', [('/state', 'cdr', 'ros2msg', EMPTY_ARRAY),
                                       ('/cmd_proposed', 'json', 'jsonschema', b'{"data": [1]}')])
    code, lines = _replay(bag, capsys)
    assert code == 0
    assert ("topic /cmd_proposed: message encoding 'json', not 'cdr': not played"
            in lines[0])
    assert 'replay finished: 1 messages published' in lines[-1]
    code, lines = _replay(bag, capsys, "topics:=['/cmd_proposed']")
    assert code == 2 and len(lines) == 1
    assert lines[0].endswith("topic /cmd_proposed: message encoding 'json', not 'cdr': it "
                             'cannot be played')


def test_a_message_dds_refuses_ends_the_replay_in_one_line_with_status_2(
        tmp_path, capsys, monkeypatch, ros_domain_id):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    bag = _bag(tmp_path / 'bag.mcap', [('/state', 'cdr', 'ros2msg', b'{"data": [1, 2]}')])
    code, lines = _replay(bag, capsys)
    assert code == 2
    assert len([line for line in lines if line.startswith('replay: ')]) == 1
    assert lines[-1].startswith('replay: /state: the message logged at 1000 ns not published '
                                "(DDS write on '/state' failed")
    assert lines[-1].endswith('(0 messages published)')

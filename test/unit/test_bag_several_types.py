"""A bag holding one topic under several types (channels of one name with different schemas:
a bag written by another tool, or merged from two). On DDS a topic is one type; the bag tools
say which topic, and never write one type's bytes under another's channel: ``refilter``
refuses a topic the filter reads, leaves a copied one out and names it; ``replay`` leaves
it out (asked for by name: refused)."""
from __future__ import annotations

from pathlib import Path
import tempfile

from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.writer import Writer
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from test_refilter import PARAMS_A

from rcbf_ros.bag import bag_info
from rcbf_ros.bag.playback import topics_to_play
from rcbf_ros.bag.refilter import refilter_bag, RefilterError
from rcbf_ros.messages.typestore import jazzy_typestore

ARRAY = 'std_msgs/msg/Float64MultiArray'
TWIST = 'geometry_msgs/msg/Twist'
STRING = 'std_msgs/msg/String'
STORE = jazzy_typestore()
T0 = 1_700_000_000 * 10**9


def _payload(type_name: str, label: str) -> bytes:
    if type_name == ARRAY:
        types = STORE.types
        values = [-2.4, 0.0, 0.0] if label == 'state' else [1.0, 0.05]
        message = types[ARRAY](
            layout=types['std_msgs/msg/MultiArrayLayout'](dim=[types[
                'std_msgs/msg/MultiArrayDimension'](label=label, size=len(values),
                                                     stride=len(values))], data_offset=0),
            data=np.array(values))
    elif type_name == TWIST:
        vector = STORE.types['geometry_msgs/msg/Vector3']
        message = STORE.types[TWIST](linear=vector(x=1.0, y=0.0, z=0.0),
                                     angular=vector(x=0.0, y=0.0, z=0.05))
    else:
        message = STORE.types[STRING](data='x' * 13)
    return bytes(STORE.serialize_cdr(message, type_name))


def _bag(directory: Path, extra: dict[str, list[str]]) -> Path:
    """/state and /cmd_proposed as arrays, /other as a String, each topic also recorded under
    the types ``extra`` gives it (one channel each), 5 messages per channel."""
    directory.mkdir(parents=True)
    with open(directory / 'run_0.mcap', 'wb') as stream:
        writer = Writer(stream)
        writer.start('ros2', 'test')
        schemas = {name: writer.register_schema(name, 'ros2msg',
                                                STORE.generate_msgdef(name)[0].encode())
                   for name in (ARRAY, TWIST, STRING)}
        channels = []
        for topic, first in (('/state', ARRAY), ('/cmd_proposed', ARRAY), ('/other', STRING)):
            for type_name in [first, *extra.get(topic, [])]:
                channels.append((topic, type_name, writer.register_channel(
                    topic, 'cdr', schemas[type_name])))
        for k in range(5):
            for offset, (topic, type_name, channel) in enumerate(channels):
                t = T0 + k * 10**7 + offset * 10**5
                label = 'state' if topic == '/state' else 'u'
                writer.add_message(channel, t, _payload(type_name, label), t)
        writer.finish()
    return directory


_EXTRA = st.dictionaries(st.sampled_from(['/state', '/cmd_proposed', '/other']),
                         st.lists(st.sampled_from([TWIST, STRING, ARRAY]), min_size=1,
                                  max_size=2, unique=True),
                         max_size=3)
FIRST = {'/state': ARRAY, '/cmd_proposed': ARRAY, '/other': STRING}


@settings(max_examples=25, deadline=None)
@given(extra=_EXTRA)
def test_a_topic_of_several_types_is_named_and_its_bytes_never_land_under_another(extra):
    several = {topic for topic, types in extra.items() if set(types) - {FIRST[topic]}}
    with tempfile.TemporaryDirectory() as tmp:
        source = _bag(Path(tmp) / 'run', extra)
        info = bag_info(source)
        for topic, first in FIRST.items():
            assert info.topics[topic].type_name == first
            assert info.topics[topic].other_types == tuple(
                sorted(set(extra.get(topic, [])) - {first}))
        if several == set(FIRST):
            with pytest.raises(ValueError, match='no topic of the bag can be played: topic '):
                topics_to_play(info)
        else:
            playable, left_out = topics_to_play(info)
            assert set(playable) == set(FIRST) - several
            assert len(left_out) == len(several)
            for topic in several:
                assert any(line.startswith(f'topic {topic}: recorded as ') for line in left_out)
        for topic in several:
            with pytest.raises(ValueError, match=f'topic {topic}: recorded as '):
                topics_to_play(info, [topic])
        output = Path(tmp) / 'out'
        if several & {'/state', '/cmd_proposed'}:
            with pytest.raises(RefilterError) as refused:
                refilter_bag(source, output, dict(PARAMS_A))
            assert '\n' not in str(refused.value) and 'recorded as' in str(refused.value)
            assert not output.exists()
            return
        summary = refilter_bag(source, output, dict(PARAMS_A))
        assert set(summary.not_copied) == several
        assert summary.proposals == 5 * (1 + len(extra.get('/cmd_proposed', [])))
        with AnyReader([output], default_typestore=STORE) as reader:
            assert {c.topic for c in reader.connections} >= set(FIRST) - several
            assert not several & {c.topic for c in reader.connections}
            for connection, _, raw in reader.messages():
                reader.deserialize(raw, connection.msgtype)  # each under its own type

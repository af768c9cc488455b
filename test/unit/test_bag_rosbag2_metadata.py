"""Our bags' metadata decoded the way rosbag2 Jazzy decodes it, field by field.

:func:`decode_bag_metadata` follows rosbag2_storage 0.26's ``YAML::convert<BagMetadata>``
(``include/rosbag2_storage/yaml.hpp``) and ``YAML::convert<rclcpp::QoS>``
(``src/rosbag2_storage/qos.cpp``) with yaml-cpp's conversions: a field read ``as<std::string>``
must be a scalar, ``as<uint64_t>`` a non-negative integer, and from version 9 on
``offered_qos_profiles`` must be a sequence (``decode_for_version<std::vector<rclcpp::QoS>>``
returns false for anything else: yaml-cpp's ``bad conversion``). The MCAP channel metadata stays
a string (rosbag2_storage_mcap's ``serialize_rclcpp_qos_vector``), loaded and decoded the same
way (``to_rclcpp_qos_vector``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from mcap.reader import make_reader
import pytest
import yaml

from rcbf_ros.bag import BagWriter, parse_offered_qos_profiles, RecordedQos, recover_bag
from rcbf_ros.bag.qos import INFINITE_DURATION_NS

T0 = 1_700_000_000_000_000_000
# rmw's *_from_str names (rmw/qos_string_conversions.c); anything else decodes to UNKNOWN.
HISTORY = {'system_default', 'keep_last', 'keep_all', 'unknown'}
RELIABILITY = {'system_default', 'reliable', 'best_effort', 'unknown', 'best_available'}
DURABILITY = {'system_default', 'transient_local', 'volatile', 'unknown', 'best_available'}
LIVELINESS = {'system_default', 'automatic', 'manual_by_topic', 'unknown', 'best_available'}


class BadConversion(AssertionError):
    """What yaml-cpp throws (``bad conversion``) where rosbag2 reads a field of the wrong kind."""


def _string(node: Any, where: str) -> str:
    if isinstance(node, (dict, list)) or node is None:
        raise BadConversion(f'{where}: as<std::string> of a {type(node).__name__}')
    return str(node)


def _unsigned(node: Any, where: str) -> int:
    if isinstance(node, bool) or not isinstance(node, int) or node < 0:
        raise BadConversion(f'{where}: as<uint64_t> of {node!r}')
    return node


def _boolean(node: Any, where: str) -> bool:
    if not isinstance(node, bool):
        raise BadConversion(f'{where}: as<bool> of {node!r}')
    return node


def _field(node: Any, key: str, where: str) -> Any:
    if not isinstance(node, dict) or key not in node:
        raise BadConversion(f'{where}: no {key!r}')
    return node[key]


def _duration(node: Any, where: str) -> int:
    sec = _unsigned(_field(node, 'sec', where), f'{where}.sec')
    nsec = _unsigned(_field(node, 'nsec', where), f'{where}.nsec')
    return sec * 1_000_000_000 + nsec


def decode_qos(node: Any, where: str) -> dict[str, Any]:
    """``convert<rclcpp::QoS>::decode``: version 9 names (an integer history means version 8)."""
    history = _field(node, 'history', where)
    if isinstance(history, int) and not isinstance(history, bool):
        raise BadConversion(f'{where}: version-8 integer policies in a version-9 bag')
    policies = {'history': (history, HISTORY)}
    for key, names in (('reliability', RELIABILITY), ('durability', DURABILITY),
                       ('liveliness', LIVELINESS)):
        policies[key] = (_field(node, key, where), names)
    decoded: dict[str, Any] = {}
    for key, (value, names) in policies.items():
        text = _string(value, f'{where}.{key}')
        assert text in names, f'{where}.{key}: {text!r} would decode as UNKNOWN'
        decoded[key] = text
    if decoded['history'] == 'keep_last':
        decoded['depth'] = _unsigned(_field(node, 'depth', where), f'{where}.depth')
    for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        decoded[key] = _duration(_field(node, key, where), f'{where}.{key}')
    decoded['avoid_ros_namespace_conventions'] = _boolean(
        _field(node, 'avoid_ros_namespace_conventions', where), where)
    return decoded


def decode_qos_sequence(node: Any, where: str) -> list[dict[str, Any]]:
    """``convert<std::vector<rclcpp::QoS>>::decode``: false (bad conversion) unless a sequence."""
    if not isinstance(node, list):
        raise BadConversion(f'{where}: offered_qos_profiles is a {type(node).__name__}, '
                            'not a sequence')
    return [decode_qos(item, f'{where}[{i}]') for i, item in enumerate(node)]


def decode_bag_metadata(node: Any) -> dict[str, Any]:
    """``convert<BagMetadata>::decode`` of ``rosbag2_bagfile_information`` (version 9)."""
    version = _field(node, 'version', 'metadata')
    assert version == 9
    _string(_field(node, 'storage_identifier', 'metadata'), 'storage_identifier')
    _unsigned(_field(_field(node, 'duration', 'metadata'), 'nanoseconds', 'duration'),
              'duration')
    _unsigned(_field(_field(node, 'starting_time', 'metadata'), 'nanoseconds_since_epoch',
                     'starting_time'), 'starting_time')
    _unsigned(_field(node, 'message_count', 'metadata'), 'message_count')
    topics = _field(node, 'topics_with_message_count', 'metadata')
    assert isinstance(topics, list)
    decoded_topics = {}
    for index, info in enumerate(topics):
        where = f'topics_with_message_count[{index}]'
        meta = _field(info, 'topic_metadata', where)
        name = _string(_field(meta, 'name', where), f'{where}.name')
        _string(_field(meta, 'type', where), f'{where}.type')
        _string(_field(meta, 'serialization_format', where), f'{where}.serialization_format')
        qos = decode_qos_sequence(_field(meta, 'offered_qos_profiles', where), where)
        _string(_field(meta, 'type_description_hash', where), f'{where}.type_description_hash')
        _unsigned(_field(info, 'message_count', where), f'{where}.message_count')
        decoded_topics[name] = qos
    paths = _field(node, 'relative_file_paths', 'metadata')
    assert isinstance(paths, list) and all(isinstance(p, str) for p in paths)
    _string(_field(node, 'compression_format', 'metadata'), 'compression_format')
    _string(_field(node, 'compression_mode', 'metadata'), 'compression_mode')
    for index, file in enumerate(_field(node, 'files', 'metadata')):
        _string(_field(file, 'path', 'files'), f'files[{index}].path')
        _unsigned(_field(_field(file, 'starting_time', 'files'), 'nanoseconds_since_epoch',
                         'files'), 'files.starting_time')
        _unsigned(_field(_field(file, 'duration', 'files'), 'nanoseconds', 'files'),
                  'files.duration')
        _unsigned(_field(file, 'message_count', 'files'), 'files.message_count')
    custom = _field(node, 'custom_data', 'metadata')
    assert isinstance(custom, dict)
    _string(_field(node, 'ros_distro', 'metadata'), 'ros_distro')
    return decoded_topics


def _bag(directory: Path) -> Path:
    with BagWriter(directory) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/scan', 'std_msgs/msg/String',
                      qos=[RecordedQos.sensor_data(), RecordedQos(durability='transient_local')])
        bag.add_topic('/silent', 'std_msgs/msg/Bool', qos=[])
        for i in range(5):
            bag.write_message('/state', {'data': [float(i)]}, T0 + i)
            bag.write_message('/scan', {'data': f'm{i}'}, T0 + i)
    return directory


EXPECTED = {
    '/state': [{'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
                'durability': 'volatile', 'liveliness': 'automatic',
                'deadline': INFINITE_DURATION_NS, 'lifespan': INFINITE_DURATION_NS,
                'liveliness_lease_duration': INFINITE_DURATION_NS,
                'avoid_ros_namespace_conventions': False}],
}


def _check(directory: Path) -> None:
    text = (directory / 'metadata.yaml').read_text()
    topics = decode_bag_metadata(yaml.safe_load(text)['rosbag2_bagfile_information'])
    assert topics['/state'] == EXPECTED['/state']
    assert [q['reliability'] for q in topics['/scan']] == ['best_effort', 'reliable']
    assert [q['durability'] for q in topics['/scan']] == ['volatile', 'transient_local']
    assert topics['/silent'] == []
    mcap = next(directory.glob('*.mcap'))
    with mcap.open('rb') as stream:
        reader = make_reader(stream)
        records = list(reader.iter_metadata())
        channels = reader.get_summary().channels.values()
        assert [r.name for r in records] == ['rosbag2']
        serialized = yaml.safe_load(records[0].metadata['serialized_metadata'])
        assert decode_bag_metadata(serialized) == topics
        for channel in channels:  # the channel keeps the string form
            profiles = channel.metadata['offered_qos_profiles']
            assert isinstance(profiles, str)
            assert decode_qos_sequence(yaml.safe_load(profiles), channel.topic) == \
                topics[channel.topic]


def test_written_metadata_decodes_as_rosbag2_decodes_it(tmp_path):
    _check(_bag(tmp_path / 'bag'))


def test_recovered_metadata_decodes_as_rosbag2_decodes_it(tmp_path):
    directory = _bag(tmp_path / 'bag')
    mcap = next(directory.glob('*.mcap'))
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) * 2 // 3])  # no summary, no footer: as after a kill
    (directory / 'metadata.yaml').unlink()
    recover_bag(directory, keep_original=False)
    text = (directory / 'metadata.yaml').read_text()
    decode_bag_metadata(yaml.safe_load(text)['rosbag2_bagfile_information'])


def test_a_string_offered_qos_profiles_is_what_rosbag2_refuses():
    node = {'history': 'keep_last', 'depth': 10}
    with pytest.raises(BadConversion, match='not a sequence'):
        decode_qos_sequence(yaml.safe_dump([node]), '/t')


@pytest.mark.parametrize('form', ['sequence', 'string', 'version 8'])
def test_our_reader_takes_every_form(form):
    profiles = [RecordedQos.sensor_data(), RecordedQos()]
    sequence = [p.to_yaml_dict() for p in profiles]
    if form == 'string':
        value: Any = yaml.safe_dump(sequence)
    elif form == 'version 8':
        value = yaml.safe_dump([dict(d, history=1, reliability=2 if i == 0 else 1,
                                     durability=2, liveliness=1)
                                for i, d in enumerate(sequence)])
    else:
        value = sequence
    assert parse_offered_qos_profiles(value) == profiles


@pytest.mark.parametrize('value', [{'history': 'keep_last'}, '[{history: keep_last}]', '[1'])
def test_our_reader_names_a_bad_offered_qos_profiles(value):
    with pytest.raises(ValueError, match='offered_qos_profiles'):
        parse_offered_qos_profiles(value)

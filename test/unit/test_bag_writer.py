"""BagWriter output read back by independent readers: rosbags' AnyReader, mcap_ros2's decoder,
mcap's own reader and ``pymcap-cli doctor``; and the crash-safety guarantee under SIGKILL."""
from __future__ import annotations

import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import textwrap

from mcap.reader import make_reader, NonSeekingReader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
import yaml

from rcbf_ros.bag import (
    bag_info,
    BagError,
    BagWriter,
    BagWriterConfig,
    read_bag,
    read_bag_messages,
    RecordedQos,
    reindex_bag,
)
from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.typestore import jazzy_typestore

REPO_ROOT = Path(__file__).resolve().parents[2]
PYMCAP_CLI = shutil.which('pymcap-cli') or str(Path(sys.executable).parent / 'pymcap-cli')
T0 = 1_700_000_000_000_000_000
N_STATE = 60
N_CMD = 45


def _state(i: int) -> dict:
    return {'layout': {'dim': [{'label': 'x', 'size': 3, 'stride': 3}], 'data_offset': 0},
            'data': [float(i), -0.5 * i, i * i / 7.0]}


def _cmd(i: int) -> dict:
    return {'linear': {'x': 0.1 * i, 'y': 0.0, 'z': -1.0},
            'angular': {'x': 0.0, 'y': 0.0, 'z': 1.0 + i}}


def _diag(i: int) -> dict:
    return {'header': {'stamp': {'sec': 100 + i, 'nanosec': 7}, 'frame_id': 'filter'},
            'status': [{'level': i % 3, 'name': 'rcbf_qp', 'message': f'solve {i}',
                        'hardware_id': 'cpu',
                        'values': [{'key': 'h_min', 'value': f'{0.25 * i:.3f}'},
                                   {'key': 'slack', 'value': '0'}]}]}


def _write_sample_bag(directory: Path, config: BagWriterConfig | None = None) -> Path:
    with BagWriter(directory, config=config or BagWriterConfig()) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd', 'geometry_msgs/msg/Twist', qos=RecordedQos.sensor_data())
        bag.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')
        for i in range(N_STATE):
            bag.write_message('/state', _state(i), T0 + i * 10_000_000)
            if i < N_CMD:
                # Raw CDR path, like the recorder: serialised elsewhere, written as bytes.
                cdr = serialize_message(_cmd(i), 'geometry_msgs/msg/Twist')
                bag.write('/cmd', cdr, T0 + i * 10_000_000 + 1_000,
                          publish_time_ns=T0 + i * 10_000_000)
        for i in range(3):
            bag.write_message('/diagnostics', _diag(i), T0 + i * 200_000_000 + 5)
    return directory


@pytest.fixture
def sample_bag(tmp_path: Path) -> Path:
    return _write_sample_bag(tmp_path / 'run1')


def test_layout_files_and_names(sample_bag: Path) -> None:
    assert sorted(p.name for p in sample_bag.iterdir()) == ['metadata.yaml', 'run1_0.mcap']


def test_anyreader_reads_counts_and_contents(sample_bag: Path) -> None:
    seen: dict[str, list] = {'/state': [], '/cmd': [], '/diagnostics': []}
    with AnyReader([sample_bag], default_typestore=jazzy_typestore()) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {'/state': 'std_msgs/msg/Float64MultiArray',
                         '/cmd': 'geometry_msgs/msg/Twist',
                         '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray'}
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {'/state': N_STATE, '/cmd': N_CMD, '/diagnostics': 3}
        for connection, timestamp, raw in reader.messages():
            seen[connection.topic].append((timestamp, reader.deserialize(raw, connection.msgtype)))
        # QoS and type hash survive in the form rosbags parses.
        cmd = next(c for c in reader.connections if c.topic == '/cmd')
        assert cmd.ext.offered_qos_profiles[0].reliability.name == 'BEST_EFFORT'
        assert cmd.ext.offered_qos_profiles[0].depth == 5
        assert cmd.digest == jazzy_typestore().hash_rihs01('geometry_msgs/msg/Twist')
    assert [t for t, _ in seen['/state']] == [T0 + i * 10_000_000 for i in range(N_STATE)]
    for i, (_, msg) in enumerate(seen['/state']):
        np.testing.assert_array_equal(msg.data, _state(i)['data'])
        assert msg.layout.dim[0].label == 'x' and msg.layout.dim[0].stride == 3
    for i, (_, msg) in enumerate(seen['/cmd']):
        assert (msg.linear.x, msg.linear.z, msg.angular.z) == (0.1 * i, -1.0, 1.0 + i)
    for i, (_, msg) in enumerate(seen['/diagnostics']):
        status = msg.status[0]
        assert (msg.header.stamp.sec, msg.header.frame_id) == (100 + i, 'filter')
        assert (status.level, status.name, status.message) == (i % 3, 'rcbf_qp', f'solve {i}')
        assert [(kv.key, kv.value) for kv in status.values] == [
            ('h_min', f'{0.25 * i:.3f}'), ('slack', '0')]


def test_mcap_ros2_decoder_parses_schemas_and_messages(sample_bag: Path) -> None:
    """An independent ros2msg parser (mcap_ros2) decodes with the stored schema text only."""
    decoded: dict[str, list] = {}
    with open(sample_bag / 'run1_0.mcap', 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            assert schema.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
            decoded.setdefault(channel.topic, []).append((message.log_time, msg))
    assert {k: len(v) for k, v in decoded.items()} == {
        '/state': N_STATE, '/cmd': N_CMD, '/diagnostics': 3}
    for i, (_, msg) in enumerate(decoded['/state']):
        assert list(msg.data) == _state(i)['data']
    for i, (log_time, msg) in enumerate(decoded['/cmd']):
        assert log_time == T0 + i * 10_000_000 + 1_000
        assert (msg.linear.x, msg.angular.z) == (0.1 * i, 1.0 + i)
    assert decoded['/diagnostics'][2][1].status[0].values[0].value == '0.500'


def test_mcap_records_follow_rosbag2_layout(sample_bag: Path) -> None:
    with open(sample_bag / 'run1_0.mcap', 'rb') as stream:
        reader = make_reader(stream)
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = list(reader.iter_metadata())
    assert header.profile == 'ros2'
    assert {s.name: s.encoding for s in summary.schemas.values()} == {
        'std_msgs/msg/Float64MultiArray': 'ros2msg', 'geometry_msgs/msg/Twist': 'ros2msg',
        'diagnostic_msgs/msg/DiagnosticArray': 'ros2msg'}
    diag_schema = next(s for s in summary.schemas.values()
                       if s.name == 'diagnostic_msgs/msg/DiagnosticArray').data.decode()
    # Concatenated definition: root text, then each dependency after the 80 '=' delimiter.
    assert diag_schema.startswith('std_msgs/Header header\n')
    for dep in ('std_msgs/Header', 'builtin_interfaces/Time', 'diagnostic_msgs/DiagnosticStatus',
                'diagnostic_msgs/KeyValue'):
        assert f'{"=" * 80}\nMSG: {dep}\n' in diag_schema
    for channel in summary.channels.values():
        assert channel.message_encoding == 'cdr'
        assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert profiles[0]['history'] == 'keep_last'
        assert profiles[0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    stats = summary.statistics
    assert stats.message_count == N_STATE + N_CMD + 3
    assert stats.message_start_time == T0
    assert stats.chunk_count >= 1 and summary.chunk_indexes
    assert [m.name for m in metadata] == ['rosbag2']
    serialized = yaml.safe_load(metadata[0].metadata['serialized_metadata'])
    assert serialized['message_count'] == N_STATE + N_CMD + 3
    assert serialized['storage_identifier'] == 'mcap'


def test_metadata_yaml_matches_data(sample_bag: Path) -> None:
    info = yaml.safe_load((sample_bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == ['run1_0.mcap']
    assert info['message_count'] == N_STATE + N_CMD + 3
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in info['topics_with_message_count']}
    assert counts == {'/state': N_STATE, '/cmd': N_CMD, '/diagnostics': 3}
    assert info['starting_time']['nanoseconds_since_epoch'] == T0
    last = max(T0 + (N_STATE - 1) * 10_000_000, T0 + (N_CMD - 1) * 10_000_000 + 1_000,
               T0 + 2 * 200_000_000 + 5)
    assert info['duration']['nanoseconds'] == last - T0
    assert info['files'][0]['message_count'] == N_STATE + N_CMD + 3


def test_pymcap_cli_doctor_passes(tmp_path: Path) -> None:
    # Many small chunks, so the chunk/message indexes and summary offsets get exercised.
    bag = _write_sample_bag(tmp_path / 'chunky', BagWriterConfig(chunk_size=512))
    assert bag_info(bag).files and bag_info(bag).complete
    result = subprocess.run([PYMCAP_CLI, 'doctor', str(bag / 'chunky_0.mcap')],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'passed' in result.stdout


def test_own_reader_in_log_time_order(sample_bag: Path) -> None:
    items = list(read_bag(sample_bag))
    assert len(items) == N_STATE + N_CMD + 3
    assert [m.log_time_ns for m in items] == sorted(m.log_time_ns for m in items)
    only_cmd = list(read_bag_messages(sample_bag, topics=['/cmd']))
    assert len(only_cmd) == N_CMD
    assert only_cmd[7][0].type_name == 'geometry_msgs/msg/Twist'
    assert only_cmd[7][1].angular.z == 8.0
    assert only_cmd[7][0].publish_time_ns == T0 + 7 * 10_000_000


def test_bad_input_is_named(tmp_path: Path) -> None:
    with BagWriter(tmp_path / 'bad') as bag:
        bag.add_topic('/x', 'std_msgs/msg/Float64MultiArray')
        with pytest.raises(KeyError, match='/y'):
            bag.write('/y', b'\x00\x01\x00\x00', 1)
        with pytest.raises(ValueError, match='nope/msg/Missing'):
            bag.add_topic('/z', 'nope/msg/Missing')
        with pytest.raises(ValueError, match='already registered'):
            bag.add_topic('/x', 'geometry_msgs/msg/Twist')
        with pytest.raises(ValueError, match='must be absolute'):
            bag.add_topic('relative', 'geometry_msgs/msg/Twist')
        with pytest.raises(ValueError, match='encapsulation'):
            bag.write('/x', b'\xff\xff', 1)
        with pytest.raises(ValueError, match='datta'):
            bag.write_message('/x', {'datta': [1.0]}, 1)
        with pytest.raises(ValueError, match='layout.data_offset'):
            bag.write_message('/x', {'layout': {'data_offset': 'abc'}}, 1)
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / 'bad')
    with pytest.raises(ValueError, match='chunk_size'):
        BagWriterConfig(chunk_size=0)
    with pytest.raises(ValueError, match='reliability'):
        RecordedQos(reliability='sometimes')


_KILLED_WRITER = textwrap.dedent("""
    import sys, time
    from rcbf_ros.bag import BagWriter, BagWriterConfig
    from rcbf_ros.bag.writer import max_chunk_bytes
    # The largest chunks and no timed flush: only the explicit flush() puts data on disk.
    config = BagWriterConfig(chunk_size=max_chunk_bytes(), flush_period_s=3600.0)
    bag = BagWriter(sys.argv[1], config=config)
    bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
    bag.add_topic('/cmd', 'geometry_msgs/msg/Twist')
    n_flushed, n_pending = int(sys.argv[2]), int(sys.argv[3])
    for i in range(n_flushed + n_pending):
        if i == n_flushed:
            bag.flush()
        bag.write_message('/state', {'data': [float(i)]}, 1_000 + i)
        bag.write_message('/cmd', {'linear': {'x': float(i)}}, 1_000 + i)
    print('ready', flush=True)
    time.sleep(60)
""")


def test_sigkill_after_flush_keeps_flushed_messages(tmp_path: Path) -> None:
    n_flushed, n_pending = 250, 40
    directory = tmp_path / 'killed'
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.Popen(
        [sys.executable, '-c', _KILLED_WRITER, str(directory), str(n_flushed), str(n_pending)],
        stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == 'ready'
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    mcap_path = directory / 'killed_0.mcap'
    assert not (directory / 'metadata.yaml').exists()

    # 1. mcap's non-seeking (streaming) reader, stopping at the cut.
    values: dict[str, list[float]] = {'/state': [], '/cmd': []}
    with open(mcap_path, 'rb') as stream:
        reader = NonSeekingReader(stream, decoder_factories=[DecoderFactory()])
        with pytest.raises(Exception):  # noqa: B017 - no footer: EndOfFile ends the stream
            for _, channel, _, msg in reader.iter_decoded_messages(log_time_order=False):
                values[channel.topic].append(
                    msg.data[0] if channel.topic == '/state' else msg.linear.x)
    assert values['/state'] == [float(i) for i in range(n_flushed)]
    assert values['/cmd'] == [float(i) for i in range(n_flushed)]

    # 2. pymcap-cli recover writes a complete file with exactly the flushed messages.
    recovered = tmp_path / 'recovered.mcap'
    result = subprocess.run([PYMCAP_CLI, 'recover', str(mcap_path), '-o', str(recovered),
                             '--force'], capture_output=True, text=True, timeout=120)
    assert result.returncode in (0, 3), result.stdout + result.stderr
    with open(recovered, 'rb') as stream:
        summary = make_reader(stream).get_summary()
        assert summary.statistics.message_count == 2 * n_flushed
        assert any(isinstance(s, Schema) for s in summary.schemas.values())

    # 3. Our reader refuses the cut-short file unless asked for its whole chunks; reindex (the
    # ros2 bag reindex equivalent) recovers it into a complete file with the same count.
    with pytest.raises(BagError, match='cut short'):
        list(read_bag(directory))
    assert len(list(read_bag(directory, allow_cut_short=True))) == 2 * n_flushed
    info = bag_info(directory)
    assert not info.complete and info.topics['/cmd'].message_count == n_flushed
    reindex_bag(directory)
    meta = yaml.safe_load((directory / 'metadata.yaml').read_text())
    assert meta['rosbag2_bagfile_information']['message_count'] == 2 * n_flushed
    assert bag_info(directory).complete and len(list(read_bag(directory))) == 2 * n_flushed


def test_metadata_record_is_last_before_summary(sample_bag: Path) -> None:
    """rosbag2 writes its ``rosbag2`` metadata record on close; readers find it via the index."""
    with open(sample_bag / 'run1_0.mcap', 'rb') as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert [i.name for i in summary.metadata_indexes] == ['rosbag2']
        offset = summary.metadata_indexes[0].offset
        last_chunk = max(c.chunk_start_offset for c in summary.chunk_indexes)
    assert offset > last_chunk


_TYPES = ['std_msgs/msg/Float64MultiArray', 'geometry_msgs/msg/Twist', 'nav_msgs/msg/Odometry',
          'sensor_msgs/msg/LaserScan', 'tf2_msgs/msg/TFMessage']


def _topic_names(draw_count: int, seed: int) -> list[tuple[str, str, int]]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(draw_count):
        name = '/' + '/'.join(f't{k}_' + 'x' * int(rng.integers(0, 120))
                              for _ in range(int(rng.integers(1, 4))))
        out.append((name, _TYPES[int(rng.integers(0, len(_TYPES)))], int(rng.integers(1, 4))))
    return out


@pytest.mark.parametrize('count, seed', [(1, 0), (2, 1), (7, 2), (60, 3)])
def test_the_closing_bound_covers_the_closing_records_whatever_the_topics(tmp_path, count,
                                                                          seed):
    """The bound each write checks (the closing records and metadata.yaml) is at least what
    closing writes, for topics of shared and distinct types, long names, several QoS
    profiles, before and after messages."""
    from rcbf_ros.bag.writer import _metadata_yaml_text, _widest_counts

    def check(contents):
        # the counts and times as wide as 64-bit numbers get: what the bound must cover
        actual = len(_metadata_yaml_text(writer._information(contents)))
        widest = len(_metadata_yaml_text(_widest_counts(writer._information(contents))))
        closing, yaml_size = writer._closing_bound(contents)
        assert yaml_size >= widest
        assert closing >= len(writer._closing(contents)) + (widest - actual)

    writer = BagWriter(tmp_path / 'b')
    for name, type_name, profiles in _topic_names(count, seed):
        writer.add_topic(name, type_name, [RecordedQos(depth=d + 1) for d in range(profiles)])
        check(writer._file.contents)
    first = next(iter(writer.topics))
    writer.write_message(first, b'\x00\x01\x00\x00' + bytes(8), 10**18)
    check(writer._file.contents)
    writer.close()


def test_registering_a_topic_costs_the_same_whatever_the_bag_holds(tmp_path, monkeypatch):
    """The closing bound is kept as running sums: each new topic costs a fixed number of
    YAML dumps, not one of every topic registered so far (a bag of 1,000 topics took minutes
    to register, and the refilter and recorder with it)."""
    from rcbf_ros.bag import writer as writer_module
    dumps = []
    real = writer_module.yaml.safe_dump

    def counted(data, *args, **kwargs):
        if isinstance(data, dict):
            info = data.get('rosbag2_bagfile_information', data)
            if 'topics_with_message_count' in info:
                dumps.append(len(info['topics_with_message_count']))
        return real(data, *args, **kwargs)
    monkeypatch.setattr(writer_module.yaml, 'safe_dump', counted)
    writer = BagWriter(tmp_path / 'b')
    for k in range(300):
        writer.add_topic(f'/t{k}', 'std_msgs/msg/Float64MultiArray')
    assert max(dumps) <= 1, max(dumps)   # each dump of at most one topic's information
    assert len(dumps) <= 4 * 300 + 4, len(dumps)
    monkeypatch.setattr(writer_module.yaml, 'safe_dump', real)
    writer.close()
    assert len(bag_info(tmp_path / 'b', allow_cut_short=False).topics) == 300

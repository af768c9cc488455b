"""What the bag writer writes, the bag reader reads: no chunk past the reader's limit.

The reader refuses a chunk of more than ``scan.MAX_CHUNK_BYTES`` uncompressed bytes; the writer
(and so the recorder node, the training recorder and recovery) closes a chunk before a message
would take it past that limit, and refuses a message that no chunk can hold. The properties run
with a small limit (the reader's constant patched: the writer reads the same one); the tests at
the bottom hold the real constants to the same relationship.
"""
from __future__ import annotations

from pathlib import Path
import tempfile

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
import pytest

from rcbf_ros.bag import BagWriter, BagWriterConfig, read_bag, recover_file
from rcbf_ros.bag import scan as bag_scan
from rcbf_ros.bag.recover import check_bag
from rcbf_ros.bag.writer import max_chunk_bytes, MESSAGE_RECORD_OVERHEAD, MessageTooLargeError

TYPE = 'std_msgs/msg/Float64MultiArray'
LIMIT = 4096
"""The chunk limit the properties patch in (bytes)."""


def _cdr(size: int, fill: int = 0) -> bytes:
    """``size`` bytes (>= 4) that start with a CDR encapsulation header."""
    return b'\x00\x01\x00\x00' + bytes([fill % 256]) * (size - 4)


def _chunk_sizes(path: Path) -> list[int]:
    """The uncompressed size of every chunk of a complete MCAP file."""
    with open(path, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    return [index.uncompressed_size for index in summary.chunk_indexes]


def _builder_count(bag: BagWriter) -> int:
    """Bytes in the mcap writer's open chunk, as its own chunk builder counts them."""
    return bag._writer._Writer__chunk_builder.count  # noqa: SLF001 - the oracle


near_limit = st.integers(LIMIT - MESSAGE_RECORD_OVERHEAD - 600, LIMIT)
"""Message sizes around the most a chunk can hold (schemas and channels take a few hundred)."""


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(chunk_size=st.integers(1, LIMIT),
       compression=st.sampled_from(['none', 'zstd', 'lz4']),
       writes=st.lists(st.tuples(st.integers(0, 2), st.one_of(near_limit, st.integers(4, 3000))),
                       min_size=1, max_size=12))
def test_every_bag_the_writer_writes_passes_the_check_and_reads_back_whole(
        monkeypatch, chunk_size, compression, writes):
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    topics = ['/a', '/b', '/c']
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp) / 'bag'
        written: list[tuple[str, bytes, int]] = []
        with BagWriter(directory, config=BagWriterConfig(
                chunk_size=chunk_size, compression=compression, flush_period_s=1e9)) as bag:
            for topic in topics:
                bag.add_topic(topic, TYPE)
            schemas_and_channels = _builder_count(bag)
            for k, (which, size) in enumerate(writes):
                data = _cdr(size, k)
                try:
                    bag.write(topics[which], data, 1000 + k)
                except MessageTooLargeError as exc:
                    assert f'a message of {size} bytes on {topics[which]} left out' in str(exc)
                    # refused only if a chunk without messages (the schemas and channels not
                    # yet closed in at most) is too small for it
                    assert MESSAGE_RECORD_OVERHEAD + size > LIMIT - schemas_and_channels
                else:
                    assert MESSAGE_RECORD_OVERHEAD + size <= LIMIT
                    written.append((topics[which], data, 1000 + k))
                assert bag._chunk.size == _builder_count(bag) <= LIMIT
        assert all(size <= LIMIT for size in _chunk_sizes(next(directory.glob('*.mcap'))))
        info = check_bag(directory)  # raises BagError on a chunk past the limit
        assert info.message_count == len(written)
        assert [(m.topic, m.data, m.log_time_ns) for m in read_bag(directory)] == written


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sizes=st.lists(near_limit, min_size=1, max_size=6))
def test_a_message_that_fits_an_empty_chunk_is_always_written(monkeypatch, sizes):
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    with tempfile.TemporaryDirectory() as tmp:
        with BagWriter(Path(tmp) / 'bag', config=BagWriterConfig(chunk_size=LIMIT,
                                                                     compression='none')) as bag:
            bag.add_topic('/a', TYPE)
            bag.write('/a', _cdr(4), 1)  # closes the schema and channel into the first chunk
            bag.flush()
            for k, size in enumerate(sizes):
                fits = MESSAGE_RECORD_OVERHEAD + size <= LIMIT
                try:
                    bag.write('/a', _cdr(size), 2 + k)
                except MessageTooLargeError:
                    assert not fits
                else:
                    assert fits
        assert check_bag(Path(tmp) / 'bag').message_count == 1 + sum(
            MESSAGE_RECORD_OVERHEAD + size <= LIMIT for size in sizes)


def test_a_refused_message_leaves_the_bag_open_and_unchanged(monkeypatch, tmp_path):
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    with BagWriter(tmp_path / 'bag', config=BagWriterConfig(chunk_size=LIMIT)) as bag:
        bag.add_topic('/a', TYPE)
        bag.write('/a', _cdr(100), 1)
        with pytest.raises(MessageTooLargeError, match=r'^a message of 5000 bytes on /a left '
                                                       r'out: a chunk holds at most 4096 bytes'):
            bag.write('/a', _cdr(5000), 2)
        bag.write('/a', _cdr(100, 1), 3)
        assert bag.topics['/a'].message_count == 2
    assert [m.log_time_ns for m in read_bag(tmp_path / 'bag')] == [1, 3]


def test_recovery_rechunks_within_the_limit_and_counts_what_it_drops(monkeypatch, tmp_path):
    # A bag written under a larger limit (as by an older writer) holds chunks the reader now
    # refuses: recovery leaves them out and counts their bytes.
    directory = tmp_path / 'bag'
    with BagWriter(directory, config=BagWriterConfig(chunk_size=4 * LIMIT,
                                                     compression='none')) as bag:
        bag.add_topic('/a', TYPE)
        for k in range(6):
            bag.write('/a', _cdr(1000, k), 1 + k)
        bag.flush()
        bag.write('/a', _cdr(100), 10)  # a second chunk, within the limit
    path = next(directory.glob('*.mcap'))
    with open(path, 'rb') as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    assert [c.uncompressed_size > LIMIT for c in chunks] == [True, False]
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    recovery = recover_file(path)
    assert recovery.rewritten
    # the first chunk is left out; the second is too: its channel was defined in the first
    assert recovery.dropped_bytes == sum(c.chunk_length for c in chunks)
    assert 'more than the 4096-byte limit of a chunk' in recovery.describe()
    assert check_bag(path).message_count == recovery.message_count == 0


def test_recovery_keeps_what_fits_and_counts_only_the_chunk_it_drops(monkeypatch, tmp_path):
    directory = tmp_path / 'bag'
    with BagWriter(directory, config=BagWriterConfig(chunk_size=4 * LIMIT,
                                                     compression='none')) as bag:
        bag.add_topic('/a', TYPE)
        bag.write('/a', _cdr(10), 1)
        bag.flush()
        for k in range(3):
            bag.write('/a', _cdr(2000, k), 2 + k)
        bag.flush()
        bag.write('/a', _cdr(10, 1), 9)
    path = next(directory.glob('*.mcap'))
    with open(path, 'rb') as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    assert [c.uncompressed_size > LIMIT for c in chunks] == [False, True, False]
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    recovery = recover_file(path)
    assert recovery.dropped_bytes == chunks[1].chunk_length
    assert recovery.message_count == 2
    assert [m.log_time_ns for m in read_bag(path)] == [1, 9]
    assert all(size <= LIMIT for size in _chunk_sizes(path))


def test_recovery_of_a_bag_cut_short_writes_chunks_the_reader_accepts(monkeypatch, tmp_path):
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    directory = tmp_path / 'bag'
    with BagWriter(directory, config=BagWriterConfig(chunk_size=LIMIT, compression='none',
                                                     flush_period_s=1e9)) as bag:
        bag.add_topic('/a', TYPE)
        for k in range(12):
            bag.write('/a', _cdr(1500 + k, k), 1 + k)
    path = next(directory.glob('*.mcap'))
    whole = [(m.log_time_ns, m.data) for m in read_bag(directory)]
    with open(path, 'r+b') as stream:  # the summary and footer lost, as after a kill
        stream.truncate(path.stat().st_size - 200)
    recovery = recover_file(path)
    assert recovery.rewritten and recovery.message_count == len(whole)
    assert all(size <= LIMIT for size in _chunk_sizes(path))
    assert [(m.log_time_ns, m.data) for m in read_bag(path)] == whole


def test_the_recorder_leaves_an_oversized_sample_out_says_so_once_and_goes_on(monkeypatch,
                                                                               tmp_path):
    from rcbf_ros.ros.recorder_node import Recorder
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', LIMIT)
    reports: list[str] = []
    clock = iter(range(1, 100))
    recorder = Recorder(BagWriter(tmp_path / 'bag', config=BagWriterConfig(chunk_size=LIMIT)),
                        lambda: next(clock),
                        report=reports.append)
    assert recorder.add('/a', TYPE, []) and recorder.add('/b', TYPE, [])
    for topic, size in [('/a', 8), ('/a', 9000), ('/a', 8), ('/a', 9001), ('/b', 5000),
                        ('/b', 8)]:
        recorder.on_message(topic, _cdr(size))  # never raises
    recorder.close()
    assert recorder.stopped is None
    assert recorder.oversized_samples == {'/a': 2, '/b': 1}
    assert len(reports) == 2 and all('\n' not in line for line in reports)
    assert '9000 bytes on /a' in reports[0] and '5000 bytes on /b' in reports[1]
    assert [(m.topic, len(m.data)) for m in read_bag(tmp_path / 'bag')] == [
        ('/a', 8), ('/a', 8), ('/b', 8)]


def test_the_training_recorder_leaves_an_oversized_message_out_and_goes_on(monkeypatch,
                                                                            tmp_path):
    from rcbf_ros.training.recorder import RunRecorder
    limit = BagWriterConfig().chunk_size  # it writes with the default chunk size
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', limit)
    reports: list[str] = []
    run = RunRecorder(tmp_path / 'bag', report=reports.append)
    for _ in range(2):
        run.event('/episode', {'event': 'x' * limit})
    run.event('/episode', {'event': 'end'})
    run.close()
    assert run.oversized == {'/episode': 2} and len(reports) == 1 and '/episode' in reports[0]
    assert [m.topic for m in read_bag(tmp_path / 'bag')] == ['/episode']


# -- the real constants ---------------------------------------------------------------------

def test_the_writers_bound_is_the_readers_constant(monkeypatch):
    from rcbf_ros.ros.recorder_node import MAX_CHUNK_SIZE
    assert max_chunk_bytes() == bag_scan.MAX_CHUNK_BYTES == MAX_CHUNK_SIZE
    # A compressed chunk within it is a record within the reader's record limit (zstd and lz4
    # add at most ~1/255 to incompressible data).
    assert bag_scan.MAX_CHUNK_BYTES * 256 // 255 + 1024 < bag_scan.MAX_RECORD_BYTES
    monkeypatch.setattr(bag_scan, 'MAX_CHUNK_BYTES', 12345)
    assert max_chunk_bytes() == 12345  # derived when asked, not a copy


def test_a_chunk_size_above_the_readers_limit_is_refused_naming_the_key():
    from rcbf_ros.parameters.reader import ParameterError, read_parameters
    from rcbf_ros.ros.recorder_node import RecorderConfig
    with pytest.raises(ValueError, match=r'^BagWriterConfig\.chunk_size must be <= '
                                         rf'{bag_scan.MAX_CHUNK_BYTES} '):
        BagWriterConfig(chunk_size=bag_scan.MAX_CHUNK_BYTES + 1)
    BagWriterConfig(chunk_size=bag_scan.MAX_CHUNK_BYTES)
    with pytest.raises(ParameterError, match=r'^chunk_size: must be <= '):
        read_parameters(RecorderConfig, {'output': 'bag',
                                         'chunk_size': bag_scan.MAX_CHUNK_BYTES + 1})


def test_a_message_past_the_real_limit_is_refused_before_anything_is_written(tmp_path):
    limit = bag_scan.MAX_CHUNK_BYTES
    with BagWriter(tmp_path / 'bag', config=BagWriterConfig(chunk_size=limit)) as bag:
        bag.add_topic('/big', TYPE)
        with pytest.raises(MessageTooLargeError, match=rf'^a message of {limit} bytes on /big'):
            bag.write('/big', _cdr(limit), 1)
        assert bag._chunk.size == _builder_count(bag)
        bag.write('/big', _cdr(16), 2)
    assert [m.log_time_ns for m in read_bag(tmp_path / 'bag')] == [2]

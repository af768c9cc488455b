"""Damaged, cut-short, empty, foreign and missing bags: the reader raises one BagError line that
names the file and the problem, and replay and refilter turn it into that line and exit 2."""
from __future__ import annotations

import os
from pathlib import Path
import random
import re

from mcap.reader import make_reader
import pytest

from rcbf_ros.bag import bag_info, BagError, BagWriter, BagWriterConfig, read_bag, refilter
from rcbf_ros.ros import replay_node

T0 = 1_700_000_000_000_000_000
N = 120
#: Bytes of a chunk record before its compressed data: opcode, length, start and end time,
#: uncompressed size and CRC, the compression string (length-prefixed) and the data length.
CHUNK_DATA_START = 1 + 8 + 8 + 8 + 8 + 4 + 4 + len('zstd') + 8


def _write_bag(directory: Path, compression: str = 'zstd') -> Path:
    """A small bag in several chunks: ``/state`` and ``/cmd_proposed`` (refilter's topics)."""
    config = BagWriterConfig(chunk_size=1024, compression=compression)
    with BagWriter(directory, config=config) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        for i in range(N):
            t = T0 + i * 10_000_000
            bag.write_message('/state', {'data': [0.1 * i, -0.2 * i, 0.0]}, t)
            bag.write_message('/cmd_proposed', {'data': [0.5, 0.01 * i]}, t + 1_000)
    return directory / f'{directory.name}_0.mcap'


def _chunks(mcap: Path) -> list[tuple[int, int]]:
    """(offset, record length) of each chunk, from the file's own index."""
    with open(mcap, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def _flip(path: Path, offset: int, n: int = 8) -> None:
    data = bytearray(path.read_bytes())
    for k in range(offset, offset + n):
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))


def _flip_in_chunk(mcap: Path, index: int = 1) -> int:
    """Flip 8 bytes in the middle of chunk ``index``'s compressed data; its offset."""
    offset, length = _chunks(mcap)[index]
    _flip(mcap, offset + CHUNK_DATA_START + (length - CHUNK_DATA_START) // 2)
    return offset


def _bad_bag(case: str, tmp_path: Path) -> tuple[Path, str]:
    """A bad source for ``case`` and a regex the one-line error must match."""
    if case == 'missing':
        path = tmp_path / 'no_such_bag'
        return path, f'{path}: does not exist'
    if case == 'empty':
        path = tmp_path / 'empty.mcap'
        path.write_bytes(b'')
        return path, f'{path}: empty file'
    if case == 'random':
        path = tmp_path / 'random.mcap'
        path.write_bytes(random.Random(7).randbytes(20_000))
        return path, f'{path}: not an MCAP file'
    if case in ('fifo_alone', 'fifo_in_bag', 'directory_in_bag'):
        # A FIFO would block the reader until a writer comes; a directory is no file either.
        bag = tmp_path / 'odd'
        bag.mkdir()
        _write_bag(tmp_path / 'good')
        (tmp_path / 'good' / 'good_0.mcap').rename(bag / 'good_0.mcap')
        odd = tmp_path / 'alone.mcap' if case == 'fifo_alone' else bag / 'zz_9.mcap'
        if case == 'directory_in_bag':
            odd.mkdir()
        else:
            os.mkfifo(odd)
        kind = 'a directory' if case == 'directory_in_bag' else 'a FIFO'
        return (odd if case == 'fifo_alone' else bag,
                f'{re.escape(str(odd))}: not a regular file \\({kind}\\)')
    mcap = _write_bag(tmp_path / 'bag')
    meta = mcap.parent / 'metadata.yaml'
    listed = {'listed_twice': [mcap.name, mcap.name], 'listed_absolute': [str(mcap)],
              'listed_outside': [mcap.name, f'../bag/{mcap.name}'],
              'listed_dot_twice': [mcap.name, f'./{mcap.name}']}
    if case in listed:
        # Each file once, inside the bag: else its messages count and are filtered twice.
        text = meta.read_text()
        start = text.index('relative_file_paths:')
        end = text.index('\n  files:', start)
        entries = ''.join(f'\n  - {rel}' for rel in listed[case])
        meta.write_text(text[:start] + 'relative_file_paths:' + entries + text[end:])
        shown = re.escape(repr(listed[case][-1]))
        return mcap.parent, (f'{re.escape(str(meta))}: relative_file_paths: {shown} is '
                             + ('listed twice' if 'twice' in case else 'not a file name inside'))
    if case == 'metadata_fifo':
        meta.unlink()
        os.mkfifo(meta)
        return mcap.parent, f'{re.escape(str(meta))}: not a regular file \\(a FIFO\\)'
    if case == 'linked_twice':
        os.link(mcap, mcap.parent / 'bag_1.mcap')
        meta.unlink()
        return mcap.parent, 'bag_1.mcap is the same file as bag_0.mcap'
    if case == 'flipped':
        offset = _flip_in_chunk(mcap)
        return mcap.parent, f'{mcap}: chunk at offset {offset}: '
    assert case == 'truncated'
    offset, length = _chunks(mcap)[2]
    data = mcap.read_bytes()
    (mcap.parent / 'metadata.yaml').unlink()
    mcap.write_bytes(data[:offset + length // 2])  # a copy that stopped inside a chunk
    return mcap.parent, f'{mcap}: cut short at byte {offset} .*rcbf_ros bag recover'


# A reader that opened a FIFO would wait for a writer forever: those cases fail instead.
_FIFO = pytest.mark.timeout(60)
BAD_CASES = ['flipped', 'truncated', 'empty', 'random', 'missing',
             pytest.param('fifo_alone', marks=_FIFO), pytest.param('fifo_in_bag', marks=_FIFO),
             'directory_in_bag', 'listed_twice', 'listed_absolute', 'listed_outside',
             'listed_dot_twice', 'linked_twice', pytest.param('metadata_fifo', marks=_FIFO)]


@pytest.mark.parametrize('case', BAD_CASES)
def test_reader_refuses_with_one_line(case: str, tmp_path: Path) -> None:
    path, expected = _bad_bag(case, tmp_path)
    with pytest.raises(BagError, match=expected) as raised:
        list(read_bag(path))
    assert '\n' not in str(raised.value)
    with pytest.raises(BagError, match=expected):
        bag_info(path, allow_cut_short=False)


@pytest.mark.parametrize('case', BAD_CASES)
def test_refilter_exits_2_with_one_line(case: str, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    path, expected = _bad_bag(case, tmp_path)
    output = tmp_path / 'refiltered'
    assert refilter.main([str(path), str(output), '--params-file', 'unicycle']) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith('rcbf_ros refilter: error: ')
    assert re.search(expected, err), err
    assert not output.exists()  # nothing half-written


@pytest.mark.parametrize('case', BAD_CASES)
def test_replay_exits_2_with_one_line(case: str, tmp_path: Path, ros_domain_id: int,
                                      monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    path, expected = _bad_bag(case, tmp_path)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    status = replay_node.main(['replay', '--ros-args', '-p', f'bag:={path}',
                               '-p', 'linger_s:=0.0'])
    captured = capsys.readouterr()
    assert status == 2, captured.out + captured.err
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    assert captured.err.startswith('replay: ')
    assert re.search(expected, captured.err), captured.err
    assert 'messages published' not in captured.out + captured.err


def test_uncompressed_chunk_crc_mismatch(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'plain', compression='none')
    offset, length = _chunks(mcap)[1]
    _flip(mcap, offset + length // 2)
    with pytest.raises(BagError, match=f'chunk at offset {offset}: CRC mismatch'):
        list(read_bag(mcap))


def test_data_outside_chunks_is_covered_by_the_data_crc(tmp_path: Path) -> None:
    """Bytes of a message index (after a chunk, not covered by the chunk's CRC)."""
    mcap = _write_bag(tmp_path / 'indexes')
    offset, length = _chunks(mcap)[1]
    _flip(mcap, offset + length + 9 + 2 + 4 + 8)  # inside the first index entry's fields
    with pytest.raises(BagError, match='data section CRC mismatch'):
        list(read_bag(mcap))


def test_damaged_summary_and_length(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'summary')
    intact = mcap.read_bytes()
    _flip(mcap, len(intact) - 150)
    with pytest.raises(BagError, match='summary CRC mismatch'):
        bag_info(mcap)
    mcap.write_bytes(intact)
    offset, _ = _chunks(mcap)[1]
    _flip(mcap, offset + 1)  # the chunk's record length: the file still ends with the magic
    with pytest.raises(BagError, match=f'chunk record at offset {offset} needs .* damaged '
                                       'length'):
        list(read_bag(mcap))


def test_intact_bag_reads_every_message(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'fine')
    items = list(read_bag(mcap.parent))
    assert len(items) == 2 * N
    info = bag_info(mcap.parent, allow_cut_short=False)
    assert info.complete and info.message_count == 2 * N
    assert info.topics['/state'].schema_encoding == 'ros2msg'
    assert info.topics['/state'].message_definition.startswith('std_msgs/MultiArrayLayout')


def test_cut_short_bag_reads_whole_chunks_when_asked(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'cut')
    whole = list(read_bag(mcap))
    offset, length = _chunks(mcap)[2]
    mcap.write_bytes(mcap.read_bytes()[:offset + length // 2])
    partial = list(read_bag(mcap, allow_cut_short=True))
    assert partial and partial == whole[:len(partial)]
    info = bag_info(mcap)
    assert not info.complete and info.message_count == len(partial)


def test_replay_of_a_bag_that_changes_while_it_plays_exits_2(
        tmp_path: Path, ros_domain_id: int, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The replay streams the bag after checking it: a file damaged in between stops it with
    one line naming the file, exit 2, and what was published so far."""
    mcap = _write_bag(tmp_path / 'bag')
    streamed = replay_node.iter_bag_messages

    def damaged_after_three(path: object, **kwargs: object) -> object:
        for k, message in enumerate(streamed(path, **kwargs)):
            if k == 3:
                raise BagError(f'{mcap}: chunk at offset 99: CRC mismatch')
            yield message

    monkeypatch.setattr(replay_node, 'iter_bag_messages', damaged_after_three)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    status = replay_node.main(['replay', '--ros-args', '-p', f'bag:={mcap.parent}',
                               '-p', 'rate:=1000.0', '-p', 'linger_s:=0.0'])
    captured = capsys.readouterr()
    assert status == 2, captured.out + captured.err
    assert 'Traceback' not in captured.err
    assert (f'replay: {mcap}: chunk at offset 99: CRC mismatch (3 messages published)'
            in captured.err.splitlines()), captured.err

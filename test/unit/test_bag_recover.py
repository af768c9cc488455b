"""Recovery of a bag cut short (its writer killed): a complete MCAP file that rosbags'
AnyReader, mcap_ros2's reader and ``pymcap-cli doctor`` accept, with every message of the whole
chunks; the original kept; complete, foreign and still-written files left alone."""
from __future__ import annotations

import json
import os
from pathlib import Path
import random
import shutil
import subprocess
import sys
import warnings

from mcap.reader import make_reader
import pytest
from rosbags.highlevel import AnyReader
import yaml

from rcbf_ros.bag import (
    bag_info,
    BagError,
    BagWriter,
    BagWriterConfig,
    read_bag,
    recover_bag,
    recover_file,
)
from rcbf_ros.cli import main as cli
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.reports.run_summary import summarize_run

with warnings.catch_warnings():
    warnings.simplefilter('ignore', DeprecationWarning)  # the module warns on import
    from mcap_ros2.reader import read_ros2_messages

PYMCAP_CLI = shutil.which('pymcap-cli') or str(Path(sys.executable).parent / 'pymcap-cli')
T0 = 1_700_000_000_000_000_000
N = 150


def _write_bag(directory: Path) -> Path:
    with BagWriter(directory, config=BagWriterConfig(chunk_size=1024)) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd', 'geometry_msgs/msg/Twist')
        for i in range(N):
            bag.write_message('/state', {'data': [float(i), 2.0 * i]}, T0 + i * 1_000_000)
            bag.write_message('/cmd', {'linear': {'x': float(i)}}, T0 + i * 1_000_000 + 10)
    return directory / f'{directory.name}_0.mcap'


def _chunks(mcap: Path) -> list[tuple[int, int]]:
    with open(mcap, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def _cut_like_a_kill(mcap: Path, chunk: int) -> bytes:
    """Cut the file inside chunk ``chunk`` and drop metadata.yaml; the cut bytes."""
    offset, length = _chunks(mcap)[chunk]
    data = mcap.read_bytes()[:offset + length // 2]
    mcap.write_bytes(data)
    (mcap.parent / 'metadata.yaml').unlink()
    return data


def test_recovered_bag_is_read_by_every_reader(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    mcap = _write_bag(tmp_path / 'killed')
    published = [(m.topic, m.data, m.log_time_ns) for m in read_bag(mcap)]
    cut = _cut_like_a_kill(mcap, chunk=4)
    whole_chunks = [(m.topic, m.data, m.log_time_ns)
                    for m in read_bag(mcap, allow_cut_short=True)]
    assert 0 < len(whole_chunks) < len(published)

    assert cli.main(['bag', 'recover', str(mcap.parent)]) == 0
    out = capsys.readouterr().out
    assert f'{mcap}: recovered {len(whole_chunks)} messages' in out
    assert 'original kept as killed_0.mcap.orig' in out

    # Our reader: complete now, exactly the whole chunks, a prefix of what was written.
    assert bag_info(mcap.parent, allow_cut_short=False).complete
    recovered = [(m.topic, m.data, m.log_time_ns) for m in read_bag(mcap.parent)]
    assert recovered == whole_chunks == published[:len(recovered)]
    # rosbags' AnyReader (metadata.yaml and the MCAP summary).
    with AnyReader([mcap.parent], default_typestore=jazzy_typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        decoded = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                   if c.topic == '/state']
    n_state = sum(1 for t, _, _ in recovered if t == '/state')
    assert counts == {'/state': n_state, '/cmd': len(recovered) - n_state}
    assert [list(m.data) for m in decoded] == [[float(i), 2.0 * i] for i in range(n_state)]
    # mcap_ros2's reader.
    states = [m.ros_msg.data for m in read_ros2_messages(str(mcap), topics=['/state'])]
    assert [list(d) for d in states] == [[float(i), 2.0 * i] for i in range(n_state)]
    # pymcap-cli doctor.
    doctor = subprocess.run([PYMCAP_CLI, 'doctor', str(mcap)], capture_output=True, text=True,
                            timeout=120)
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr
    assert 'passed' in doctor.stdout
    # metadata.yaml counts what the file holds; the original is kept byte for byte.
    meta = yaml.safe_load((mcap.parent / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    assert info['message_count'] == len(recovered)
    assert info['relative_file_paths'] == [mcap.name]
    assert {t['topic_metadata']['name']: t['message_count']
            for t in info['topics_with_message_count']} == counts
    assert (mcap.parent / 'killed_0.mcap.orig').read_bytes() == cut
    assert not list(mcap.parent.glob('*.recovering'))


def test_recovery_interrupted_before_its_rename_runs_again(tmp_path: Path) -> None:
    """Killed after linking the original and writing part of the new file: nothing is lost
    and a second run finishes the job."""
    mcap = _write_bag(tmp_path / 'again')
    cut = _cut_like_a_kill(mcap, chunk=3)
    (mcap.parent / 'again_0.mcap.orig').hardlink_to(mcap)
    (mcap.parent / 'again_0.mcap.recovering').write_bytes(b'\x89MCAP0\r\n half written')
    [result] = recover_bag(mcap.parent)
    assert result.rewritten and bag_info(mcap.parent, allow_cut_short=False).complete
    assert (mcap.parent / 'again_0.mcap.orig').read_bytes() == cut
    assert sorted(p.name for p in mcap.parent.iterdir()) == [
        'again_0.mcap', 'again_0.mcap.orig', 'metadata.yaml']


def test_complete_bag_is_left_as_it_is(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'fine')
    before = mcap.read_bytes()
    [result] = recover_bag(mcap.parent)
    assert not result.rewritten and result.message_count == 2 * N
    assert mcap.read_bytes() == before
    assert sorted(p.name for p in mcap.parent.iterdir()) == ['fine_0.mcap', 'metadata.yaml']


def test_damaged_chunk_is_left_out_and_reported(tmp_path: Path) -> None:
    mcap = _write_bag(tmp_path / 'damaged')
    intact = list(read_bag(mcap))
    offset, length = _chunks(mcap)[2]
    data = bytearray(mcap.read_bytes())
    for k in range(offset + length // 2, offset + length // 2 + 8):
        data[k] ^= 0xFF
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match=f'chunk at offset {offset}'):
        list(read_bag(mcap))
    result = recover_file(mcap)
    assert result.rewritten and any(f'chunk at offset {offset}' in p for p in result.problems)
    recovered = list(read_bag(mcap))
    assert 0 < len(recovered) < len(intact)
    assert set(recovered) < set(intact)  # only the damaged chunk's messages are missing
    assert (mcap.parent / 'damaged_0.mcap.orig').read_bytes() == bytes(data)


def test_foreign_file_is_refused_and_untouched(tmp_path: Path) -> None:
    path = tmp_path / 'noise.mcap'
    noise = random.Random(3).randbytes(5000)
    path.write_bytes(noise)
    with pytest.raises(BagError, match=f'{path}: not an MCAP file'):
        recover_file(path)
    assert path.read_bytes() == noise
    assert sorted(p.name for p in tmp_path.iterdir()) == ['noise.mcap']
    with pytest.raises(BagError, match='does not exist'):
        recover_bag(tmp_path / 'nothing_here')


def test_bag_still_being_written_is_refused(tmp_path: Path) -> None:
    writer = BagWriter(tmp_path / 'live', config=BagWriterConfig(chunk_size=1024))
    try:
        writer.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        for i in range(50):
            writer.write_message('/state', {'data': [float(i)]}, T0 + i)
        writer.flush()
        before = writer.mcap_path.read_bytes()
        with pytest.raises(BagError, match='being written by a running process'):
            recover_bag(writer.directory)
        assert writer.mcap_path.read_bytes() == before
    finally:
        writer.close()
    assert bag_info(writer.directory, allow_cut_short=False).message_count == 50


def test_finished_chunks_reach_the_disk_without_a_flush(tmp_path: Path) -> None:
    """A chunk is on disk as soon as it is full: a kill loses only the open chunk."""
    config = BagWriterConfig(chunk_size=1024, flush_period_s=3600.0)
    writer = BagWriter(tmp_path / 'unflushed', config=config)
    try:
        writer.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        for i in range(60):  # a few chunks of 1 KiB, a few hundred bytes each compressed
            writer.write_message('/state', {'data': [float(i), 1.0, 2.0]}, T0 + i)
        on_disk = bag_info(writer.directory).message_count
        assert 0 < on_disk < 60
        assert [m.log_time_ns for m in read_bag(writer.mcap_path, allow_cut_short=True)] == [
            T0 + i for i in range(on_disk)]
    finally:
        writer.close()


def test_check_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mcap = _write_bag(tmp_path / 'checked')
    assert cli.main(['bag', 'check', str(mcap.parent)]) == 0
    assert f'intact, {2 * N} messages on 2 topics' in capsys.readouterr().out
    _cut_like_a_kill(mcap, chunk=1)
    assert cli.main(['bag', 'check', str(mcap.parent)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'cut short' in err and 'recover' in err


@pytest.mark.timeout(60)  # opening the FIFO would wait for a writer forever
@pytest.mark.parametrize('odd', ['fifo', 'directory', 'fifo_alone'])
def test_recover_refuses_what_is_not_a_regular_file(odd: str, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Recovery reads regular files only, and names the odd one before rewriting anything."""
    mcap = _write_bag(tmp_path / 'odd')
    _cut_like_a_kill(mcap, chunk=1)
    cut = mcap.read_bytes()
    target = tmp_path / 'alone.mcap' if odd == 'fifo_alone' else mcap.parent / 'zz.mcap'
    if odd == 'directory':
        target.mkdir()
    else:
        os.mkfifo(target)
    argument = target if odd == 'fifo_alone' else mcap.parent
    assert cli.main(['bag', 'recover', str(argument)]) == 2
    err = capsys.readouterr().err
    kind = 'a directory' if odd == 'directory' else 'a FIFO'
    assert err.strip() == (f'rcbf_ros bag recover: error: {target}: not a regular file ({kind}); '
                           'a bag holds regular files only')
    assert mcap.read_bytes() == cut  # nothing rewritten
    assert not (mcap.parent / 'metadata.yaml').exists()


def test_run_summary_recovers_the_bag_of_a_killed_recorder(tmp_path: Path) -> None:
    run = tmp_path / 'run'
    (run / 'learner').mkdir(parents=True)
    (run / 'learner' / 'summary.json').write_text(json.dumps({'episodes': 1}))
    mcap = _write_bag(run / 'bag')
    _cut_like_a_kill(mcap, chunk=3)
    expected = len(list(read_bag(mcap, allow_cut_short=True)))
    text = summarize_run(run)
    assert f'({expected} messages' in text and 'recovered from whole chunks' in text
    assert bag_info(run / 'bag', allow_cut_short=False).message_count == expected
    assert 'closed cleanly' in summarize_run(run)

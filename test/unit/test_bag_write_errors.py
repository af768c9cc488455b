"""A full disk is an error, not a crash: the bag writer and the recorder under a file size limit
(``RLIMIT_FSIZE``, as ``ulimit -f``), on a full file system, and with writes that fail.

Each run writes N known messages; the bag it leaves must be read as it is (no recovery) by
rosbags' AnyReader and by ``rcbf_ros bag check``, and hold the first n messages sent, in order,
with n at least what the limit leaves room for. That bound comes from a bag written without a
limit: the limited bag writes the same chunks, and keeps every chunk that ends
``closing + COUNT_SLACK`` bytes before the limit, ``closing`` being the unlimited bag's closing
records (the summary of fewer chunks is smaller) and ``COUNT_SLACK`` what the writer keeps
beyond them for its counts and times to grow to 20 digits.
"""
from __future__ import annotations

import bisect
import contextlib
import errno
import os
from pathlib import Path
import resource
import signal
import subprocess
import sys
import textwrap

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
import pytest
from rosbags.highlevel import AnyReader

from rcbf_ros.bag import BagWriter, BagWriterConfig, read_bag_messages, recover_bag
from rcbf_ros.bag import writer as writer_module
from rcbf_ros.bag.recover import main as bag_command
from rcbf_ros.bag.writer import BagWriteError
from rcbf_ros.messages.typestore import jazzy_typestore

REPO_ROOT = Path(__file__).resolve().parents[2]
N = 400
COUNT_SLACK = 256
T0 = 1_700_000_000_000_000_000

# Writes N messages /state = [i, 2i, i/7] with a deterministic layout (1 KiB chunks, no
# compression, no timed flush), through the BagWriter ('writer') or the recorder's logic fed
# CDR samples as from DDS ('recorder'); prints 'wrote <count>' at the end if it gets there.
_CHILD = textwrap.dedent("""
    import resource, sys
    from rcbf_ros.bag import BagWriter, BagWriterConfig
    from rcbf_ros.bag.writer import BagWriteError
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.ros.recorder_node import Recorder

    T0 = 1_700_000_000_000_000_000
    TYPE = 'std_msgs/msg/Float64MultiArray'
    config = BagWriterConfig(chunk_size=1024, compression='none', flush_period_s=1e9)

    def state(i):
        return {'data': [float(i), 2.0 * i, i / 7.0]}

    def record(mode, directory, n):
        if mode == 'writer':
            try:
                bag = BagWriter(directory, config=config)
                bag.add_topic('/state', TYPE)
                for i in range(n):
                    bag.write_message('/state', state(i), T0 + i * 1000)
                bag.close()
            except BagWriteError as exc:
                print(f'error: {exc}', file=sys.stderr, flush=True)
                return 1
        else:
            try:
                bag = BagWriter(directory, config=config)
            except BagWriteError as exc:
                print(f'cannot record: {exc}', file=sys.stderr, flush=True)
                return 2
            clock = iter(range(T0, T0 + 1000 * n, 1000))
            recorder = Recorder(bag, lambda: next(clock))
            recorder.add('/state', TYPE, [])
            for i in range(n):
                recorder.on_message('/state', serialize_message(state(i), TYPE))
                if i % 97 == 96:
                    recorder.flush()
            recorder.close()
        print('wrote', n, flush=True)
        return 0

    mode, directory, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    if mode != 'sweep':
        sys.exit(record(mode, directory, n))
    # One bag per limit (argv[4:]), each written under that limit in turn.
    for k, limit in enumerate(int(a) for a in sys.argv[4:]):
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
        status = record('writer', f'{directory}/{k}/bag', n)
        resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY,) * 2)
        print('status', status, flush=True)
""")


def _limited(limit: int | None):
    """preexec_fn: SIGXFSZ ignored (a write past the limit then fails with EFBIG), the limit."""
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        if limit is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def _run(mode: str, bag: Path, limit: int | None, *limits: int,
         ) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    return subprocess.run([sys.executable, '-c', _CHILD, mode, str(bag), str(N),
                           *map(str, limits)], env=env, preexec_fn=_limited(limit),
                          capture_output=True, text=True, timeout=120)


class _Reference:
    """The bag of an unlimited run: where each chunk ends, with how many messages so far."""

    def __init__(self, bag: Path) -> None:
        (self.file,) = bag.glob('*.mcap')
        self.size = self.file.stat().st_size
        with open(self.file, 'rb') as stream:
            summary = make_reader(stream).get_summary()
        with open(self.file, 'rb') as stream:
            times = sorted(m.log_time for _, _, m in make_reader(stream).iter_messages())
        # Chunks follow each other in time (every log time is new): the messages up to the end
        # of a chunk are those logged up to its last log time.
        ends = [(index.chunk_start_offset + index.chunk_length + index.message_index_length,
                 bisect.bisect_right(times, index.message_end_time))
                for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)]
        self.chunk_ends = ends
        self.closing = self.size - ends[-1][0]
        self.header_end = min(i.chunk_start_offset for i in summary.chunk_indexes)

    def bounds(self, limit: int) -> tuple[int, int]:
        """Messages the limited bag must keep at least, and can hold at most."""
        low = max((n for end, n in self.chunk_ends
                   if end + self.closing + COUNT_SLACK <= limit), default=0)
        high = max((n for end, n in self.chunk_ends if end <= limit), default=0)
        return low, high


@pytest.fixture(scope='module')
def references(tmp_path_factory):
    """The unlimited run of each mode (the recorder's flushes make other chunks)."""
    made: dict[str, _Reference] = {}

    def of(mode: str) -> _Reference:
        if mode not in made:
            bag = tmp_path_factory.mktemp('reference') / 'bag'
            result = _run(mode, bag, None)
            assert result.returncode == 0 and not result.stderr, result.stderr
            made[mode] = _Reference(bag)
        return made[mode]
    return of


def _states(bag: Path) -> list[list[float]]:
    """Every message of ``bag`` as rosbags' AnyReader decodes it, in order."""
    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        return [list(reader.deserialize(raw, c.msgtype).data)
                for c, _, raw in reader.messages()]


def _sent(n: int) -> list[list[float]]:
    return [[float(i), 2.0 * i, i / 7.0] for i in range(n)]


def _check_bag(bag: Path, capsys) -> int:
    """``rcbf_ros bag check`` on the bag as it is; its message count."""
    capsys.readouterr()
    assert bag_command(['check', str(bag)]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    return int(out.split('intact, ')[1].split(' messages')[0])


def _assert_stopped_bag(bag: Path, limit: int, reference: _Reference, capsys) -> int:
    (mcap,) = bag.glob('*.mcap')
    assert mcap.stat().st_size <= limit
    assert (bag / 'metadata.yaml').is_file()
    states = _states(bag)
    assert states == _sent(len(states))
    low, high = reference.bounds(limit)
    assert low <= len(states) <= high, (limit, low, len(states), high)
    assert _check_bag(bag, capsys) == len(states)
    return len(states)


def _limits(reference: _Reference) -> dict[str, int]:
    first_end = reference.chunk_ends[0][0]
    middle_end = reference.chunk_ends[len(reference.chunk_ends) // 2][0]
    return {'header': 20,  # inside the header: not even a bag can start
            'first chunk': first_end - 100,
            'later chunk': middle_end + 300,
            'summary': reference.size - 40}  # every chunk fits, the whole closing does not


@pytest.mark.parametrize('where', ['header', 'first chunk', 'later chunk', 'summary'])
@pytest.mark.parametrize('mode', ['writer', 'recorder'])
def test_a_file_size_limit_stops_the_bag_with_one_line(mode, where, references, tmp_path,
                                                      capsys):
    reference = references(mode)
    limit = _limits(reference)[where]
    bag = tmp_path / 'bag'
    result = _run(mode, bag, limit)
    assert 'Traceback' not in result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    (line,) = lines
    assert 'EFBIG' in line and 'File too large' in line and str(bag / 'bag_0.mcap') in line
    if where == 'header':
        assert result.returncode == (1 if mode == 'writer' else 2)
        assert 'no bag written' in line and not list(bag.glob('*.mcap'))
        return
    if mode == 'writer':
        assert result.returncode == 1 and line.startswith('error: cannot write')
    elif where == 'summary':  # the last chunk is written when the recorder closes the bag
        assert result.returncode == 0 and result.stdout == f'wrote {N}\n'
        assert line.startswith('closing the bag failed: cannot write')
    else:  # the recorder goes on (to the end of its input) without recording
        assert result.returncode == 0 and result.stdout == f'wrote {N}\n'
        assert line.startswith('recording stopped: cannot write')
        assert line.endswith('the recorder goes on without recording')
    n = _assert_stopped_bag(bag, limit, reference, capsys)
    assert f'bag closed with the {n} messages written before the error' in line
    if where == 'first chunk':
        assert n == 0


@settings(max_examples=3, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fractions=st.lists(st.floats(min_value=0.0, max_value=1.0), min_size=8, max_size=8))
def test_any_file_size_limit_leaves_a_readable_prefix(fractions, references, tmp_path_factory,
                                                      capsys):
    """Limits anywhere from the end of the header to past the whole bag, eight bags to a
    process (each lowers its own limit for one bag, then lifts it)."""
    reference = references('writer')
    span = reference.size + 2 * COUNT_SLACK - reference.header_end
    limits = [reference.header_end + int(f * span) for f in fractions]
    out = tmp_path_factory.mktemp('limited')
    result = _run('sweep', out, None, *limits)
    assert 'Traceback' not in result.stderr and result.returncode == 0, result.stderr
    statuses = [int(line.split()[1]) for line in result.stdout.splitlines()
                if line.startswith('status')]
    errors = iter(result.stderr.splitlines())
    assert len(statuses) == len(limits)
    assert len(result.stderr.splitlines()) == sum(1 for s in statuses if s)  # one line each
    for k, (limit, status) in enumerate(zip(limits, statuses)):
        bag = out / str(k) / 'bag'
        if limit >= reference.size + COUNT_SLACK or status == 0:
            assert status == 0 and _states(bag) == _sent(N) and limit >= reference.size
            continue
        assert status == 1
        line = next(errors)
        assert 'EFBIG' in line and str(bag / 'bag_0.mcap') in line
        if 'no bag written' in line:  # not even an empty bag fits
            assert limit < reference.header_end + reference.closing + COUNT_SLACK
            assert not list(bag.glob('*.mcap'))
            continue
        _assert_stopped_bag(bag, limit, reference, capsys)


# -- a full file system ------------------------------------------------------------------------

@contextlib.contextmanager
def _small_file_system(path: Path, size: str):
    """A tmpfs of ``size`` at ``path`` (skips where mounting is not allowed)."""
    path.mkdir()
    mounted = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size}', 'tmpfs', str(path)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f'cannot mount a tmpfs here: {mounted.stderr.strip()}')
    try:
        yield path
    finally:
        subprocess.run(['umount', '-l', str(path)], capture_output=True)


@pytest.mark.parametrize('size', ['24k', '40k'])
def test_a_full_disk_closes_the_bag(size, tmp_path, capsys):
    with _small_file_system(tmp_path / 'disk', size) as disk:
        bag = disk / 'bag'
        result = _run('recorder', bag, None)
        assert 'Traceback' not in result.stderr and result.returncode == 0
        (line,) = result.stderr.splitlines()
        assert 'ENOSPC' in line and str(bag / 'bag_0.mcap') in line
        assert 'bag closed with the' in line, line
        states = _states(bag)
        assert 0 < len(states) < N and states == _sent(len(states))
        assert _check_bag(bag, capsys) == len(states)


# -- failing writes, in process ----------------------------------------------------------------

_PWRITE = os.pwrite


class _FailingDisk:
    """``os.pwrite`` failing with ``code`` past ``capacity`` bytes of the file (a short write up
    to it, then the error), every time or only ``once`` (a passing I/O error)."""

    def __init__(self, capacity: int, code: int, once: bool) -> None:
        self.capacity = capacity
        self.code = code
        self.once = once
        self.failed = False

    def pwrite(self, fd: int, data: memoryview, offset: int) -> int:
        room = self.capacity - offset
        if room <= 0 and not (self.once and self.failed):
            self.failed = True
            raise OSError(self.code, os.strerror(self.code))
        return _PWRITE(fd, data if self.failed and self.once else data[:room], offset)


def _write_until_error(bag: Path, messages: int) -> tuple[BagWriter, BagWriteError | None]:
    writer = BagWriter(bag, config=BagWriterConfig(chunk_size=1024, compression='none',
                                                   flush_period_s=1e9))
    writer.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
    try:
        for i in range(messages):
            writer.write_message('/state', {'data': _sent(i + 1)[i]}, T0 + i * 1000)
        writer.close()
    except BagWriteError as exc:
        return writer, exc
    return writer, None


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(capacity=st.integers(min_value=2_500, max_value=45_000),
       code=st.sampled_from([errno.ENOSPC, errno.EIO, errno.EFBIG]), once=st.booleans())
def test_a_failed_write_keeps_every_whole_chunk(capacity, code, once, tmp_path_factory,
                                                monkeypatch, capsys):
    """A write fails (no blocks held ahead). The closing records written over the failed
    chunk close the bag; where they fail too, the file ends at its last whole chunk (as after
    a kill) and recovery gives the same messages."""
    disk = _FailingDisk(capacity, code, once)
    bag = tmp_path_factory.mktemp('failing') / 'bag'
    with monkeypatch.context() as patch:
        patch.setattr(writer_module, '_fallocate_keep_size', lambda: None)
        patch.setattr(writer_module.os, 'pwrite', disk.pwrite)
        writer, error = _write_until_error(bag, 500)
    assert error is not None and error.errno == code
    text = str(error)
    assert '\n' not in text and errno.errorcode[code] in text and str(writer.mcap_path) in text
    with pytest.raises(BagWriteError) as again:
        writer.write_message('/state', {'data': [0.0]}, T0)
    assert again.value is error
    writer.close()  # nothing more to do, and no second error
    n = writer.message_count
    assert 'bag closed with' in text or not once  # a passing error: the closing fits
    if 'bag closed with' in text:
        assert _states(bag) == _sent(n) and _check_bag(bag, capsys) == n
    else:
        assert 'rcbf_ros bag recover' in text and not (bag / 'metadata.yaml').exists()
        recover_bag(bag)
        assert [list(m.data) for _, m in read_bag_messages(bag)] == _sent(n)
    assert n > 0 or capacity < 4_000

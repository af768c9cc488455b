"""A console that cannot take a line (a full disk, a closed pipe, no stderr at all) never stops a
node: its log lines go on to /rosout, its callbacks go on, and a program that stops on bad input
keeps its exit status 2, as rcutils' console handler drops a line it cannot write."""
from __future__ import annotations

import errno
import io
import os
from pathlib import Path
import shutil
import subprocess
import sys
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.ros.console import console_line, run_writing_stdout
from rcbf_ros.ros.dds.log import Logger
from rcbf_ros.ros.node_main import run_node

REPO = Path(__file__).resolve().parents[2]


class _BrokenStream(io.TextIOBase):
    """A stderr whose write or flush raises ``error`` (the bytes never reach a file)."""

    def __init__(self, error: BaseException, at: str) -> None:
        self.error, self.at, self.calls = error, at, 0

    def write(self, text: str) -> int:
        self.calls += 1
        if self.at == 'write':
            raise self.error
        return len(text)

    def flush(self) -> None:
        if self.at == 'flush':
            raise self.error


class _Rosout:
    """A /rosout writer that keeps each line."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, *, msg: str, **_: Any) -> None:
        self.lines.append(msg)


_ERRORS = st.one_of(
    st.sampled_from([errno.ENOSPC, errno.EPIPE, errno.EIO, errno.EBADF, errno.EFBIG,
                     errno.EAGAIN]).map(lambda code: OSError(code, 'console')),
    st.just(BrokenPipeError(errno.EPIPE, 'Broken pipe')),
    st.just(ValueError('I/O operation on closed file.')),
    st.just(UnicodeEncodeError('ascii', 'é', 0, 1, 'ordinal not in range(128)')))


@settings(max_examples=60, deadline=None)
@given(error=_ERRORS, at=st.sampled_from(['write', 'flush', 'none']),
       message=st.text(max_size=200))
def test_a_console_that_cannot_take_a_line_drops_it_and_the_log_goes_on(error, at, message):
    stream = None if at == 'none' else _BrokenStream(error, at)
    rosout = _Rosout()
    logger = Logger('probe', rosout=rosout)
    previous, sys.stderr = sys.stderr, stream
    try:
        assert console_line(message) is False
        for log in (logger.info, logger.warning, logger.error):
            assert log(message) is True
    finally:
        sys.stderr = previous
    assert rosout.lines == [message] * 3


def test_a_console_that_takes_the_line_gets_it_whole(capsys):
    assert console_line('one line') is True
    assert capsys.readouterr().err == 'one line\n'


def _refused_node() -> Any:
    raise ValueError('alpha: must be > 0, got -2.0')


def test_a_node_refusing_its_parameters_exits_2_whatever_stderr_is(ros_domain_id, monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    for error in (OSError(errno.ENOSPC, 'No space left on device'), BrokenPipeError()):
        monkeypatch.setattr(sys, 'stderr', _BrokenStream(error, 'write'))
        assert run_node('probe', _refused_node, ['probe'], setup_errors=(ValueError,)) == 2
    monkeypatch.setattr(sys, 'stderr', None)
    assert run_node('probe', _refused_node, ['probe'], setup_errors=(ValueError,)) == 2


@pytest.mark.skipif(not Path('/dev/full').exists(), reason='no /dev/full on this system')
def test_the_filter_node_refusing_a_parameter_exits_2_with_stderr_on_a_full_disk(ros_domain_id):
    from rcbf_ros.ros.loopback import ensure_loopback
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')]))
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONPATH=path)
    ensure_loopback(env, force=True)
    with open('/dev/full', 'w') as full:
        done = subprocess.run(
            [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
             '--params-file', str(REPO / 'config' / 'unicycle.yaml'), '-p', 'alpha:=-2.0'],
            env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=full, timeout=120)
    assert done.returncode == 2


@pytest.mark.parametrize('module, params, key', [
    ('rcbf_ros.ros.safety_filter_node', 'unicycle', 'osqp.max_iter:=2.0'),   # refused building
    ('rcbf_ros.ros.safety_filter_node', 'unicycle', 'alpha:=-2.0'),          # at declaring
    ('rcbf_ros.ros.scene_node', 'unicycle', 'rate_hz:=-1.0'),
    ('rcbf_ros.ros.scene_node', 'car_following', 'state_type:=odometry')])
def test_a_node_refusing_a_parameter_says_so_in_one_line(ros_domain_id, module, params, key):
    """The process's exit line says it (node_main.run_node), not also the node's log."""
    from rcbf_ros.ros.loopback import ensure_loopback
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')]))
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONPATH=path)
    ensure_loopback(env, force=True)
    done = subprocess.run(
        [sys.executable, '-m', module, '--ros-args', '--params-file',
         str(REPO / 'config' / f'{params}.yaml'), '-p', key],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=120)
    lines = done.stderr.splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert ': invalid parameters: ' in lines[0] and key.split(':=')[0] in lines[0], lines


# --- a command's stdout ------------------------------------------------------------------------

class _FailingStdout(io.TextIOBase):
    """A stdout that takes ``good`` writes or flushes, then raises ``error`` at each."""

    def __init__(self, error: OSError, good: int) -> None:
        self.error, self.good, self.text = error, good, ''

    def _use(self) -> None:
        if self.good <= 0:
            raise self.error
        self.good -= 1

    def write(self, text: str) -> int:
        self._use()
        self.text += text
        return len(text)

    def flush(self) -> None:
        self._use()


@given(error=st.sampled_from([BrokenPipeError(errno.EPIPE, 'Broken pipe'),
                              OSError(errno.ENOSPC, 'No space left on device'),
                              OSError(errno.EIO, 'Input/output error')]),
       good=st.integers(0, 12), lines=st.integers(0, 5), status=st.sampled_from([0, 2]))
def test_a_command_goes_on_past_a_stdout_that_fails_and_says_so_unless_the_reader_left(
        error, good, lines, status):
    stream, done = _FailingStdout(error, good), []

    def command() -> int:
        for k in range(lines):
            print(f'line {k}')
            done.append(k)
        return status
    previous, sys.stdout = sys.stdout, stream
    err = io.StringIO()
    previous_err, sys.stderr = sys.stderr, err
    try:
        code = run_writing_stdout('probe', command)
        assert sys.stdout is stream
    finally:
        sys.stdout, sys.stderr = previous, previous_err
    assert done == list(range(lines))  # the work went on
    failed = good < 2 * lines + 1  # a print is two writes; one flush at the end
    if not failed or isinstance(error, BrokenPipeError):
        assert code == status and err.getvalue() == ''
    else:
        assert code == (status or 1)
        assert err.getvalue() == f'probe: stdout: {error.strerror}; what it holds is incomplete\n'
    assert set(stream.text.splitlines()) <= {f'line {k}' for k in range(lines)}


def _bag(path: Path) -> Path:
    from rcbf_ros.bag import BagWriter

    def sections(label: str, values: list[float]) -> dict:
        return {'layout': {'dim': [{'label': label, 'size': len(values), 'stride': len(values)}],
                           'data_offset': 0}, 'data': values}
    with BagWriter(path) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        for k in range(5):
            t = 1_700_000_000 * 10**9 + k * 10**7
            bag.write_message('/state', sections('state', [-2.4, 0.0, 0.0]), t)
            bag.write_message('/cmd_proposed', sections('u', [1.0, 0.0]), t + 10**6)
    return path


def _run(args: list[str], stdout: Any) -> subprocess.CompletedProcess:
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')]))
    return subprocess.run([sys.executable, *args], cwd=REPO, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=path))


@pytest.mark.parametrize('command', ['--help', 'bag check', 'refilter', 'node --help'])
def test_a_command_whose_reader_left_does_its_work_without_a_word(tmp_path, command):
    bag = _bag(tmp_path / 'run')
    args = {'--help': ['-m', 'rcbf_ros', '--help'],
            'bag check': ['-m', 'rcbf_ros', 'bag', 'check', str(bag)],
            'refilter': ['-m', 'rcbf_ros', 'refilter', str(bag), str(tmp_path / 'out'),
                         '--params-file', str(REPO / 'config' / 'unicycle.yaml')],
            'node --help': ['-m', 'rcbf_ros.ros.safety_filter_node', '--help']}[command]
    read, write = os.pipe()
    os.close(read)  # the reader has left before the first line
    try:
        done = _run(args, write)
    finally:
        os.close(write)
    assert (done.returncode, done.stderr) == (0, '')
    if command == 'refilter':  # the bag written whole
        assert (tmp_path / 'out' / 'metadata.yaml').exists()
        shutil.rmtree(tmp_path / 'out')
    if Path('/dev/full').exists():
        with open('/dev/full', 'w') as full:
            done = _run(args, full)
        program = 'safety_filter' if command == 'node --help' else 'rcbf_ros'
        assert done.returncode == 1
        assert done.stderr == (f'{program}: stdout: No space left on device; what it holds is '
                               'incomplete\n')

"""A params file that cannot be read as one is refused in one line naming the file (and the
line and column for YAML), the same through every reader: ``refilter --params-file``,
``train --config`` and a node's ``--params-file``; a FIFO, a device or a directory is refused
as not a regular file, before a byte of it is read."""
from __future__ import annotations

import os
from pathlib import Path

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.bag import BagWriter, refilter
from rcbf_ros.cli import main as cli
from rcbf_ros.parameters.rules import load_params, ParamsFileError

REPO = Path(__file__).resolve().parents[2]
UNICYCLE = (REPO / 'config' / 'unicycle.yaml').read_text()
NOT_YAML = 'safety_filter:\n  ros__parameters:\n    system: [unicycle\n'


def _params_file(case: str, tmp_path: Path) -> tuple[str, str]:
    """A bad params file for ``case`` and what its one line must say after the file name."""
    path = tmp_path / f'{case}.yaml'
    if case == 'not_yaml':
        path.write_text(NOT_YAML)
        return str(path), ("not valid YAML at line 4, column 1: expected ',' or ']', but got "
                           "'<stream end>'")
    if case == 'not_utf8':
        path.write_bytes(b'safety_filter:\n  ros__parameters:\n    system: \xff\xfe\n')
        return str(path), 'not UTF-8 text (invalid start byte at byte 46)'
    if case == 'fifo':
        os.mkfifo(path)
        return str(path), 'not a regular file (a FIFO)'
    if case == 'directory':
        path.mkdir()
        return str(path), 'not a regular file (a directory)'
    assert case == 'device'
    return '/dev/zero', 'not a regular file (a character device)'


CASES = ['not_yaml', 'not_utf8', pytest.param('fifo', marks=pytest.mark.timeout(60)),
         'directory', 'device']
"""(Opening a FIFO for reading waits for a writer: a reader that did would hang, and fail.)"""


def _one_line(err: str, path: str, expected: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert 'Traceback' not in err
    assert f"'{path}'" in lines[0] and lines[0].endswith(expected), err
    return lines[0]


@pytest.mark.parametrize('case', CASES)
def test_refilter_params_file_is_refused_in_one_line(case: str, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        writer.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        writer.write_message('/cmd_proposed', {'data': [0.0, 0.0]}, 1_000)
    path, expected = _params_file(case, tmp_path)
    output = tmp_path / 'out'
    assert refilter.main([str(bag), str(output), '--params-file', path]) == 2
    line = _one_line(capsys.readouterr().err, path, expected)
    assert line.startswith('rcbf_ros refilter: error: params file')
    assert not output.exists()


@pytest.mark.parametrize('case', CASES)
def test_train_config_is_refused_in_one_line(case: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    path, expected = _params_file(case, tmp_path)
    out = tmp_path / 'run'
    assert cli.main(['train', '--system', 'unicycle', '--mode', 'unconstrained',
                     '--episodes', '1', '--out', str(out), '--config', path]) == 2
    captured = capsys.readouterr()
    line = _one_line(captured.err, path, expected)
    assert line.startswith('error: ')
    assert not out.exists()


@pytest.mark.parametrize('case', CASES)
def test_node_params_file_says_the_same(case: str, tmp_path: Path) -> None:
    """The node's command line reads the file with the same reader, in the same words."""
    from rcbf_ros.parameters.arguments import parse_ros_arguments, RosArgumentError
    path, expected = _params_file(case, tmp_path)
    with pytest.raises(RosArgumentError) as raised:
        parse_ros_arguments(['--ros-args', '--params-file', path])
    assert str(raised.value) == f'--params-file {path!r}: {expected}'


_MANGLING = st.text(alphabet=list('[]{}:,-&*!|>"\'#%@`? \t\n\\') + ['\x00', '\ufeff', 'é'],
                    max_size=6)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, len(UNICYCLE)), at=st.integers(0, len(UNICYCLE)), insert=_MANGLING,
       raw=st.binary(max_size=4))
def test_a_mangled_params_file_is_read_or_refused_in_one_line(
        cut: int, at: int, insert: str, raw: bytes, tmp_path: Path) -> None:
    """A packaged params file cut short, with characters inserted and bytes appended: either it
    is still a params file, or the reader refuses it in one line naming the file."""
    text = UNICYCLE[:at] + insert + UNICYCLE[at:]
    path = tmp_path / 'mangled.yaml'
    path.write_bytes(text[:cut].encode() + raw)
    try:
        load_params(path, 'safety_filter')
    except ParamsFileError as exc:
        message = str(exc)
        assert '\n' not in message, message
        assert repr(str(path)) in message or str(path) in message, message

"""``rcbf_ros summary`` over damaged learner files: one line naming the file (and the line or
field) and exit 2, or, for a metrics row cut short by a kill mid-append, that row skipped with
one warning line; never a traceback."""
from __future__ import annotations

import json
from pathlib import Path

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.cli import main as cli

SUMMARY = {'episodes': 2, 'env_steps': 40, 'final_return': 1.5, 'best_return': 2.0,
           'goals_reached': 1, 'safety_violations': 0, 'steps_per_s': 123.4}
ROWS = [{'episode': 0, 'ret': 2.0, 'steps': 20}, {'episode': 1, 'ret': 1.5, 'steps': 20}]


def _run(tmp_path: Path, summary: bytes | None, metrics: bytes | None) -> Path:
    learner = tmp_path / 'run' / 'learner'
    learner.mkdir(parents=True, exist_ok=True)
    for name, data in (('summary.json', summary), ('metrics.jsonl', metrics)):
        if data is not None:
            (learner / name).write_bytes(data)
    return learner.parent


def _jsonl(rows: list[dict]) -> bytes:
    return ''.join(json.dumps(row) + '\n' for row in rows).encode()


def _summary(run: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    status = cli.main(['summary', str(run)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_an_intact_run_is_summarized(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, out, err = _summary(_run(tmp_path, json.dumps(SUMMARY).encode(), _jsonl(ROWS)),
                                capsys)
    assert (status, err) == (0, '')
    assert 'returns per episode: 2.00, 1.50' in out and 'steps/s: 123.4' in out


def test_a_metrics_row_cut_short_is_skipped_with_one_warning(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    whole = _jsonl(ROWS)
    run = _run(tmp_path, json.dumps(SUMMARY).encode(), whole[:-12])  # killed mid-append
    status, out, err = _summary(run, capsys)
    metrics = run / 'learner' / 'metrics.jsonl'
    assert status == 0
    assert err == (f'rcbf_ros summary: warning: {metrics}: line 2 is cut short (a run killed '
                   'while writing it); skipped\n')
    assert 'returns per episode: 2.00\n' in out


BAD = {
    'summary_not_json': ({'summary': b'{"episodes": 2,\n'},
                         'summary.json: line 2, column 1: not JSON'),
    'summary_a_list': ({'summary': b'[1, 2]'}, 'summary.json: not a JSON object but a list'),
    'summary_rate_a_word': ({'summary': b'{"steps_per_s": "fast"}'},
                            "summary.json: steps_per_s: not a number ('fast')"),
    'summary_count_a_bool': ({'summary': b'{"episodes": true}'},
                             'summary.json: episodes: not an integer'),
    'summary_not_utf8': ({'summary': b'{"a": "\xff"}'},
                         'summary.json: line 1: not UTF-8 text (invalid start byte at byte 7)'),
    'summary_a_directory': ({'summary': 'dir'},
                            'summary.json: not a regular file (a directory)'),
    'row_without_ret': ({'metrics': b'{"episode": 0}\n'},
                        'metrics.jsonl: line 1: no ret (the episode return)'),
    'row_ret_a_word': ({'metrics': b'{"ret": 1}\n{"ret": "x"}\n'},
                       "metrics.jsonl: line 2: ret: not a number ('x')"),
    'row_broken_inside': ({'metrics': b'{"ret": 1}\n{"re\n{"ret": 2}\n'},
                          'metrics.jsonl: line 2: not JSON'),
    'row_a_list': ({'metrics': b'[1]\n'}, 'metrics.jsonl: line 1: not a JSON object'),
    'metrics_not_utf8': ({'metrics': b'{"ret": 1}\n{"ret": 2, "x": "\xfe"}\n'},
                         'metrics.jsonl: line 2: not UTF-8 text'),
}


@pytest.mark.parametrize('case', sorted(BAD))
def test_a_damaged_learner_file_is_one_line_and_exit_2(
        case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    files, expected = BAD[case]
    summary = files.get('summary', json.dumps(SUMMARY).encode())
    metrics = files.get('metrics', _jsonl(ROWS))
    run = _run(tmp_path, None if summary == 'dir' else summary, metrics)
    if summary == 'dir':
        (run / 'learner' / 'summary.json').mkdir()
    status, out, err = _summary(run, capsys)
    assert status == 2, out + err
    assert out == ''
    assert err.count('\n') == 1 and 'Traceback' not in err, err
    assert err.startswith(f'rcbf_ros summary: error: {run / "learner"}/'), err
    assert expected in err, err


def _mangled(data: bytes, draw: st.DrawFn) -> bytes:
    """``data`` cut, with bytes flipped and bytes inserted."""
    data = bytearray(data[:draw(st.integers(0, len(data)))])
    for _ in range(draw(st.integers(0, 3))):
        if data:
            at = draw(st.integers(0, len(data) - 1))
            data[at] = draw(st.sampled_from(b'{}[]",:\n\xff\x00 0a-'))
    at = draw(st.integers(0, len(data)))
    return bytes(data[:at]) + draw(st.binary(max_size=4)) + bytes(data[at:])


@st.composite
def _learner_files(draw: st.DrawFn) -> tuple[bytes, bytes]:
    summary = dict(SUMMARY)
    for key in draw(st.lists(st.sampled_from(sorted(SUMMARY)), max_size=3)):
        summary[key] = draw(st.one_of(st.none(), st.booleans(), st.text(max_size=3),
                                      st.floats(), st.integers(), st.lists(st.integers(),
                                                                           max_size=2)))
    rows = [dict(row) for row in ROWS]
    if draw(st.booleans()):
        rows[draw(st.integers(0, 1))]['ret'] = draw(st.one_of(
            st.none(), st.text(max_size=2), st.floats(), st.booleans()))
    summary_bytes = json.dumps(summary).encode()
    metrics_bytes = _jsonl(rows)
    if draw(st.booleans()):
        summary_bytes = _mangled(summary_bytes, draw)
    if draw(st.booleans()):
        metrics_bytes = _mangled(metrics_bytes, draw)
    return summary_bytes, metrics_bytes


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(files=_learner_files())
def test_mangled_learner_files_never_raise(files: tuple[bytes, bytes], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Whatever the two files hold: a summary (with at most one warning line), or one error
    line naming one of them, exit 2."""
    summary, metrics = files
    run = _run(tmp_path, summary, metrics)
    status, out, err = _summary(run, capsys)
    learner = run / 'learner'
    if status == 0:
        assert out.startswith(f'run: {run}\n')
        assert err == '' or (err.count('\n') == 1 and err.startswith(
            f'rcbf_ros summary: warning: {learner / "metrics.jsonl"}: line ')), err
    else:
        assert status == 2 and out == ''
        assert err.count('\n') == 1, err
        assert err.startswith((f'rcbf_ros summary: error: {learner / "summary.json"}: ',
                               f'rcbf_ros summary: error: {learner / "metrics.jsonl"}: ')), err


@pytest.mark.parametrize('odd', ['directory', 'device'])
def test_a_params_file_that_is_no_regular_file_is_one_line(odd: str, tmp_path: Path) -> None:
    """The layout's params file is read by the one params reader: a directory or a device
    is said to be no regular file, and the trajectories are not drawn."""
    from rcbf_ros.bag import BagWriter
    from rcbf_ros.reports.run_summary import trajectory_line
    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        writer.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        writer.write_message('/state', {'data': [0.0, 0.0, 0.0]}, 1_000)
    params = tmp_path / 'layout' if odd == 'directory' else Path('/dev/zero')
    if odd == 'directory':
        params.mkdir()
    kind = 'a directory' if odd == 'directory' else 'a character device'
    assert trajectory_line(bag, tmp_path / 't.png', params_file=str(params)) == (
        f'trajectories: not drawn: {params}: not a regular file ({kind})')

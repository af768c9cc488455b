"""The reference driver's parsing and timing arithmetic (benchmarks/_reference.py)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
import re
import sys

from benchmark_modules import load_benchmark
import pytest

ref = load_benchmark('_reference')


def test_steady_rate_takes_out_a_refit_inside_the_window():
    # 6 stamps = 5 iterations of 0.1 s; the refit of 2 s ran after step 3 (iteration 2)
    stamps = [0.0, 0.1, 0.2, 2.3, 2.4, 2.5]
    refit = ref.Refit(after_step=3, seconds=2.0, cpu_seconds=1.5, points=200)
    assert ref.steady_rate(stamps=stamps, refits=[refit], first=0) == pytest.approx(10.0)
    assert ref.steady_rate(stamps=stamps, refits=[], first=0) == pytest.approx(2.0)


def test_steady_rate_ignores_refits_before_the_window():
    # the refit after step 2 lies in iteration 1, before the window starting at stamp 2
    stamps = [0.0, 0.1, 5.2, 5.3, 5.4]
    refit = ref.Refit(after_step=2, seconds=5.0, cpu_seconds=5.0, points=200)
    assert ref.steady_rate(stamps=stamps, refits=[refit], first=2) == pytest.approx(10.0)


def test_steady_rate_on_cpu_stamps_takes_out_the_refits_cpu_seconds():
    stamps = [0.0, 0.1, 1.7, 1.8]
    refit = ref.Refit(after_step=2, seconds=9.0, cpu_seconds=1.5, points=200)
    assert ref.steady_rate(stamps=stamps, refits=[refit], first=0,
                           cpu=True) == pytest.approx(10.0)


@pytest.mark.parametrize('first', [-1, 3, 10])
def test_steady_rate_rejects_a_window_outside_the_stamps(first):
    with pytest.raises(ValueError, match='first'):
        ref.steady_rate(stamps=[0.0, 1.0, 2.0, 3.0], refits=[], first=first)


def test_amortized_rate_spreads_the_refit_over_its_interval():
    # 10 steps/s = 0.1 s a step; a 4 s refit every 400 steps adds 0.01 s a step
    assert ref.amortized_rate(steps_per_s=10.0, refit_s=4.0,
                              every_steps=400) == pytest.approx(1 / 0.11)
    assert ref.amortized_rate(steps_per_s=10.0, refit_s=0.0, every_steps=400) == 10.0


def _result(**overrides) -> dict:
    result = {'stamps': [0.0, 1.0], 'cpu_stamps': [0.0, 0.5],
              'refits': [{'after_step': 1, 'seconds': 2.0, 'cpu_seconds': 1.0, 'points': 200}],
              'updates': [0.1], 'filter_calls': [[0.01, 0.01]]}
    result.update(overrides)
    return result


def test_parse_result_reads_the_last_tagged_line_among_other_output():
    stdout = ('Episode 0 - step 10\n' + ref.RESULT_TAG + json.dumps(_result(updates=[9.0]))
              + '\nnoise\n' + ref.RESULT_TAG + json.dumps(_result()) + '\n')
    parsed = ref.parse_result(stdout)
    assert parsed['updates'] == [0.1]
    assert parsed['refits'] == [ref.Refit(after_step=1, seconds=2.0, cpu_seconds=1.0,
                                          points=200)]


@pytest.mark.parametrize('stdout, message', [
    ('Episode 0\n', 'no result line'),
    (ref.RESULT_TAG + '{not json', 'not JSON'),
    (ref.RESULT_TAG + json.dumps({'stamps': []}), "lacks 'cpu_stamps'"),
])
def test_parse_result_fails_with_one_line_saying_why(stdout, message):
    with pytest.raises(ref.ReferenceError, match=message):
        ref.parse_result(stdout)


def test_check_reference_names_the_bad_argument(tmp_path):
    with pytest.raises(ref.ReferenceError, match='--reference: .* no main.py'):
        ref.check_reference(directory=tmp_path, python=Path(sys.executable))
    (tmp_path / 'main.py').write_text('')
    (tmp_path / 'rcbf_sac').mkdir()
    with pytest.raises(ref.ReferenceError, match='--reference-python'):
        ref.check_reference(directory=tmp_path, python=tmp_path / 'missing-python')
    ref.check_reference(directory=tmp_path, python=Path(sys.executable))


def _fake_python(tmp_path: Path, script: str) -> Path:
    """A reference tree and an 'interpreter' that runs ``script`` (sh) instead of the driver."""
    (tmp_path / 'main.py').write_text('')
    (tmp_path / 'rcbf_sac').mkdir(exist_ok=True)
    python = tmp_path / 'python'
    python.write_text('#!/bin/sh\n' + script)
    python.chmod(0o755)
    return python


def test_run_reference_reports_a_failing_run_in_one_line(tmp_path):
    python = _fake_python(tmp_path, 'echo "Traceback" >&2\necho "qpth: broken" >&2\nexit 3\n')
    with pytest.raises(ref.ReferenceError, match=r'exited 3: qpth: broken$'):
        ref.run_reference(directory=tmp_path, python=python, system='unicycle', mode='diff',
                          warmup=1, steps=1, timeout_s=60)


def test_run_reference_passes_the_mapped_names_and_parses_the_result(tmp_path):
    line = ref.RESULT_TAG + json.dumps(_result())
    python = _fake_python(tmp_path, f'echo "$@" > "{tmp_path}/args"\necho \'{line}\'\n')
    out = ref.run_reference(directory=tmp_path, python=python, system='car_following',
                            mode='modular', warmup=400, steps=150, timeout_s=60)
    assert out['stamps'] == [0.0, 1.0]
    args = (tmp_path / 'args').read_text().split()
    assert args[args.index('--env') + 1] == 'SimulatedCars'
    assert args[args.index('--cbf-mode') + 1] == 'mod'
    assert args[args.index('--warmup') + 1] == '400'


def test_run_reference_rejects_a_row_without_counterpart(tmp_path):
    python = _fake_python(tmp_path, 'exit 0\n')
    with pytest.raises(ref.ReferenceError, match='mode: .*unconstrained'):
        ref.run_reference(directory=tmp_path, python=python, system='unicycle',
                          mode='unconstrained', warmup=1, steps=1)


def test_the_mode_and_system_maps_cover_the_compared_rows():
    assert ref.CBF_MODES == {'baseline': 'baseline', 'modular': 'mod', 'diff': 'full'}
    assert set(ref.ENV_NAMES) == {'unicycle', 'car_following', 'pvtol'}


def _bench_training():
    return load_benchmark('bench_training')


def _run(rate: float) -> dict:
    return {'steps_per_s': rate, 'cpu_steps_per_s': rate, 'refit_s': 1.0}


def test_comparison_row_leaves_the_reference_columns_empty_without_reference_runs():
    row = _bench_training().comparison_row('unicycle', 'baseline', [_run(30.0)], [])
    cells = [c.strip() for c in row.strip('|').split('|')]
    assert cells[:3] == ['unicycle', 'baseline <- baseline', '30.0']
    assert cells[3:8] == ['', '', '', '', '']
    assert cells[8:] == ['>= 2.5x', '']


@pytest.mark.parametrize('ours, verdict', [(30.0, 'met'), (20.0, 'not met')])
def test_comparison_row_judges_the_median_ratio_against_the_target(ours, verdict):
    bench = _bench_training()
    row = bench.comparison_row('car_following', 'diff', [_run(ours), _run(ours)],
                               [_run(5.0), _run(5.0)])
    cells = [c.strip() for c in row.strip('|').split('|')]
    assert cells[3] == '5.0'
    assert cells[4].startswith(f'{ours / 5:.1f}x')
    assert cells[8:] == ['>= 6x', verdict]


def _reference_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='bench')
    ref.add_reference_arguments(parser)
    parser.add_argument('--reference-calls', type=int, default=400)
    return parser


def test_no_reference_skips_the_comparison_and_says_so(capsys):
    parser = _reference_parser()
    assert not ref.reference_requested(parser, parser.parse_args([]))
    assert capsys.readouterr().out == 'Reference comparison skipped: no --reference DIR given.\n'


@pytest.mark.parametrize('extra, message', [
    ([], '--reference needs --reference-python'),
    (['--reference-python', '{python}', '--reference-calls', '3'],
     '--reference-calls: at least one call per round'),
    (['--reference-python', '{missing}'], '--reference-python: .* is not an executable'),
])
def test_a_reference_that_cannot_run_ends_the_benchmark_in_one_line(tmp_path, capsys, extra,
                                                                     message):
    python = _fake_python(tmp_path, 'exit 0\n')
    parser = _reference_parser()
    args = parser.parse_args(['--reference', str(tmp_path)] + [
        part.format(python=python, missing=tmp_path / 'missing') for part in extra])
    with pytest.raises(SystemExit) as exit_info:
        ref.reference_requested(parser, args, minimums=[
            (args.reference_calls, 4, '--reference-calls: at least one call per round')])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.splitlines()[-1]
    assert re.fullmatch(f'bench: error: {message}.*', error), error


def test_a_usable_reference_is_requested(tmp_path):
    parser = _reference_parser()
    python = _fake_python(tmp_path, 'exit 0\n')
    args = parser.parse_args(['--reference', str(tmp_path), '--reference-python', str(python)])
    assert ref.reference_requested(parser, args, minimums=[(args.reference_calls, 4, 'calls')])

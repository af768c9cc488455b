"""The memo-pass benchmark (benchmarks/bench_fill_pass.py): its quick run, on a fitted GP
and a full buffer, predicts the same with either kernel; and its refusals of bad arguments."""
from __future__ import annotations

from benchmark_modules import load_benchmark
import pytest

bench = load_benchmark('bench_fill_pass')


def test_the_quick_run_times_both_kernels_and_they_predict_the_same():
    quick = bench.QUICK
    result = bench.measure('unicycle', 'diff', buffer=quick['buffer'],
                           refit_interval=quick['refit_interval'],
                           batch_size=quick['batch_size'], repeats=1)
    assert set(result['seconds']) == set(bench.WAYS)
    assert all(len(values) == 1 and values[0] > 0 for values in result['seconds'].values())
    assert result['states'] >= quick['buffer']  # every stored state, next states copied
    # The same computation to round-off (the std's bound subtracts terms near its size).
    assert result['mean_gap'] <= 1e-10 and result['std_gap'] <= 1e-7
    row = bench.row_text('unicycle', 'diff', result)
    assert row.startswith('| unicycle | diff |') and row.count('|') == 11


@pytest.mark.parametrize('argv, message', [
    (['--rows', 'unicycle'], "--rows: 'unicycle' is not SYSTEM/MODE"),
    (['--quick', '--buffer', '50'], '--buffer at least'),
    (['--repeats', '0'], '--repeats >= 1'),
])
def test_bad_arguments_end_it_in_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(argv + ['--no-write'])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]

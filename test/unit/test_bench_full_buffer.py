"""The full-buffer training benchmark (benchmarks/bench_training_full_buffer.py): its quick
smoke run, and its refusals of bad arguments."""
from __future__ import annotations

from benchmark_modules import load_benchmark
import pytest

bench = load_benchmark('bench_training_full_buffer')


def test_the_quick_run_times_both_periods_of_each_way():
    """Both ways run both periods; only the learner's own way runs the one-pass fill of the
    memo after a refit, and the full period runs with the buffer filled to its size."""
    quick = bench.QUICK
    runs = {way: bench.measure('unicycle', 'diff', way, buffer=quick['buffer'],
                               refit_interval=quick['refit_interval'],
                               batch_size=quick['batch_size']) for way in bench.WAYS}
    for run in runs.values():
        assert run['stored'] == (quick['refit_interval'], quick['buffer'])
        assert run['through_layer']
        for period in (run['first'], run['full']):
            assert len(period.stamps) == quick['refit_interval'] + 1
            assert period.mean_step_ms() > 0 and period.refit_s > 0
    assert runs['pass']['full'].fill_s > 0 and runs['demand']['full'].fill_s == 0
    # The pass predicts every stored state once; on demand only the drawn ones.
    assert runs['pass']['full'].predicted >= quick['buffer']
    row = bench.row_text('unicycle', 'diff', 'pass', [runs['pass']])
    assert row.startswith('| unicycle | diff | pass |') and row.count('|') == 15


@pytest.mark.parametrize('argv, message', [
    (['--rows', 'unicycle'], "--rows: 'unicycle' is not SYSTEM/MODE"),
    (['--rows', 'boat/diff'], "--rows: 'boat/diff' is not SYSTEM/MODE"),
    (['--quick', '--buffer', '100'], '--buffer must be at least'),
    (['--refit-interval', '5'], '--refit-interval must be >= 20'),
    (['--ways'], '--ways not empty'),
])
def test_bad_arguments_end_it_in_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(argv + ['--no-write'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]

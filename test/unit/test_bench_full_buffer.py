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
            assert len(period.cpu_stamps) == len(period.stamps)
            assert period.mean_step_cpu_ms() > 0
    assert runs['pass']['full'].fill_s > 0 and runs['demand']['full'].fill_s == 0
    # The pass predicts every stored state once; on demand only the drawn ones.
    assert runs['pass']['full'].predicted >= quick['buffer']
    row = bench.row_text('unicycle', 'diff', 'pass', [runs['pass']], capacity=quick['buffer'])
    assert row.startswith('| unicycle | diff | pass |') and row.count('|') == 17


def test_run_hours_grow_the_step_with_the_stored_count():
    """Until the buffer is full the step is the mean of its two ends; beyond, the full one
    takes the remaining steps."""
    assert bench.run_hours(first_ms=10.0, full_ms=10.0, steps=360_000,
                           capacity=1000) == pytest.approx(1.0)
    # 200,000 steps filling a 200,000 buffer: the mean of 10 and 20 ms.
    assert bench.run_hours(first_ms=10.0, full_ms=20.0, steps=200_000,
                           capacity=200_000) == pytest.approx(200_000 * 15e-3 / 3600)
    # 400,000 steps: 200,000 at a mean of 15 ms, then 200,000 at 20 ms.
    assert bench.run_hours(first_ms=10.0, full_ms=20.0, steps=400_000,
                           capacity=200_000) == pytest.approx(200_000 * 35e-3 / 3600)
    with pytest.raises(ValueError, match='steps'):
        bench.run_hours(first_ms=1.0, full_ms=1.0, steps=0, capacity=1)


@pytest.mark.parametrize('argv, message', [
    (['--rows', 'unicycle'], "--rows: 'unicycle' is not SYSTEM/MODE"),
    (['--rows', 'boat/diff'], "--rows: 'boat/diff' is not SYSTEM/MODE"),
    (['--quick', '--buffer', '50'], '--buffer must be at least'),
    (['--refit-interval', '5'], '--refit-interval must be >= 20'),
    (['--ways'], '--ways not empty'),
])
def test_bad_arguments_end_it_in_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(argv + ['--no-write'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]

"""benchmarks/bench_obstacle_scale.py: its worlds and its reading of the targets (the timing
itself is the benchmark's, not a test's)."""
from __future__ import annotations

from benchmark_modules import load_benchmark
import numpy as np

bench = load_benchmark('bench_obstacle_scale')


def test_half_the_decisions_start_next_to_an_obstacle_driving_at_it():
    params = bench.world(200)
    centres = np.column_stack([params['obstacles.x'], params['obstacles.y']])
    reach = np.array(params['obstacles.radius']) + params['obstacles.margin']
    for index, (state, proposal, _, std) in enumerate(bench.calls(200, 40)):
        gap = np.hypot(*(centres - state[:2]).T) - reach
        assert min(std) >= 0.0
        if index % 2 == 0:
            assert np.any((gap > 0.0) & (gap <= 0.6 * reach)) and proposal[0] >= 1.0


def test_the_targets_are_read_from_the_corrected_medians_of_this_tree():
    header = ['| circles | path | build | held | median | p99 | corrected | median, corrected '
              '| p99, corrected | rows |', '|---|']
    table = header + [
        '| 360 | per row (closed_form) | 1 | 0.1 | 300 | 900 | 50% | 900 | 990 | all |',
        '| 360 | this tree (vectorised) | 1 | 0.1 | 100 | 900 | 50% | 150 | 990 | 1.7 |',
        '| 2,000 | this tree (vectorised) | 1 | 0.1 | 100 | 900 | 50% | 301 | 990 | 1.7 |']
    text = bench.targets(table)
    assert '360 circles 150 us' in text and '(target 150 us: met)' in text
    assert '2,000 circles 301 us' in text and '(target 300 us: not met)' in text

"""Unicycle filter: the look-ahead point following the direction of travel vs always ahead.

    python benchmarks/bench_lookahead_direction.py [--calls 3000] [--no-write]

``obstacles.speed_input: 0`` (config/unicycle.yaml) evaluates the obstacle barriers at both
points (one autograd pass over 2k rows) and picks per proposal; ``-1`` is the reference's point
always ahead. Same states and proposals for both, calls interleaved in random order so that
load on the machine hits both alike; proposals U[-2.5, 2.5]^2 (half of them reversing), states
uniform over the arena. Whole ``SafetyFilter.filter()`` calls, eager and compiled assembly.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import time

import numpy as np
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.parameters.rules import find_config, load_params

torch.set_num_threads(1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=3000)
    parser.add_argument('--no-write', action='store_true', help='do not update RESULTS.md')
    args = parser.parse_args()
    base = load_params(find_config('unicycle'), 'safety_filter')
    variants = {'point ahead always (speed_input -1, the reference)': -1,
                'point follows travel (speed_input 0, ours)': 0}
    rng = np.random.default_rng(0)
    states = np.c_[rng.uniform(-3.0, 3.0, (args.calls, 2)),
                   rng.uniform(-np.pi, np.pi, args.calls)]
    proposals = rng.uniform(-2.5, 2.5, (args.calls, 2))
    lines = []
    for compiled in (False, True):
        filters = {name: SafetyFilter(filter_config_from_params(
            {**base, 'obstacles.speed_input': value}).problem, compile_assembly=compiled)
            for name, value in variants.items()}
        times: dict[str, list[float]] = {name: [] for name in filters}
        names = list(filters)
        for x, u in zip(states, proposals):
            for name in rng.permutation(names):
                start = time.perf_counter()
                filters[name].filter(x, u)
                times[name].append(time.perf_counter() - start)
        reference = float(np.median(times[names[0]]))
        for name in names:
            arr = 1e6 * np.asarray(times[name])
            lines.append(f"| {name} | {'compiled' if compiled else 'eager'} | "
                         f'{np.median(arr):.1f} | {np.percentile(arr, 99):.1f} | '
                         f'{np.median(times[name]) / reference:.2f}x |')
    table = '\n'.join(['| filter | assembly | median us | p99 us | median / reference |',
                       '|---|---|---:|---:|---:|', *lines])
    print(table)
    if not args.no_write:
        from _results import machine_line, write_section
        write_section('Look-ahead point: direction of travel vs always ahead', (
            'Command: `python benchmarks/bench_lookahead_direction.py`. ' + machine_line()
            + f'. {args.calls} calls per variant, interleaved.\n\n' + table))


if __name__ == '__main__':
    main()

"""The safety filter's decision time against the number of circle obstacles.

    python benchmarks/bench_obstacle_scale.py [--calls 2000] [--no-write]

One :meth:`SafetyFilter.filter` call per decision (config/unicycle.yaml: look-ahead point with
the direction-of-travel switch, input limits; a disturbance box), in worlds of 10 to 10,000
random circles at a constant density (one per 16 m^2, radii 0.05-0.4 m), at random states and
proposals within the limits. Two paths:

- ``per row``: the closed form generated as code per row (the only path before the rows over
  arrays; still the path below ``VECTOR_ROWS`` obstacles), built where it can be: Python's
  compiler refuses its code past about 750 rows, so 2,000 and 10,000 have no figure;
- ``this tree``: what ``SafetyFilter`` chooses (per row below 64 obstacles, else the rows over
  arrays and a QP of the rows that can bind).

Nav2 collision_monitor's figures from its README are printed beside ours as a reference,
not re-measured here (another machine, and a stop/slow-down check, not a QP).
"""
from __future__ import annotations

import argparse
import gc
from pathlib import Path
import sys
import time
import tracemalloc

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rcbf_ros.core.config import filter_config_from_params  # noqa: E402
from rcbf_ros.core.filter import SafetyFilter  # noqa: E402
from rcbf_ros.core.rcbf import RCBFProblem  # noqa: E402
from rcbf_ros.parameters.rules import find_config, load_params  # noqa: E402

TITLE = 'Many obstacles: decision time against the number of circles'
COUNTS = (10, 100, 360, 512, 2_000, 10_000)
PER_ROW_MOST = 512
"""The most rows the per-row path is built for here (it was the limit; ~750 fails)."""
COLLISION_MONITOR = [
    '| Nav2 collision_monitor (its README, not re-measured here) | per frame |',
    '|---|---|',
    '| LaserScan, 360 points | 4.45-4.93 ms |',
    '| PointCloud2, 24k points | 4.1-20.7 ms |',
]


def world(count: int, seed: int = 0) -> dict:
    """config/unicycle.yaml's safety_filter parameters with ``count`` random circles."""
    rng = np.random.default_rng(seed)
    half = 2.0 * np.sqrt(count)  # one obstacle per 16 m^2
    params = load_params(find_config('unicycle'), 'safety_filter')
    params.update({'obstacles.x': rng.uniform(-half, half, count).tolist(),
                   'obstacles.y': rng.uniform(-half, half, count).tolist(),
                   'obstacles.radius': rng.uniform(0.05, 0.4, count).tolist(),
                   'obstacles.speed_input': 0})
    return params


def calls(count: int, number: int, seed: int = 1) -> list[tuple[list[float], ...]]:
    """``number`` (state, proposal, mean, std) within the world of ``count`` circles: half at
    random, half next to an obstacle and driving at it (the filter corrects those)."""
    rng = np.random.default_rng(seed)
    params = world(count)
    centres = np.column_stack([params['obstacles.x'], params['obstacles.y']])
    reach = np.array(params['obstacles.radius']) + params['obstacles.margin']
    half = 2.0 * np.sqrt(count)
    out = []
    for index in range(number):
        box = (rng.normal(0.0, 0.02, 3).tolist(), rng.uniform(0.0, 0.05, 3).tolist())
        if index % 2:
            out.append(([*rng.uniform(-half, half, 2), rng.uniform(-np.pi, np.pi)],
                        rng.uniform(-2.5, 2.5, 2).tolist(), *box))
            continue
        o = int(rng.integers(count))
        angle = rng.uniform(-np.pi, np.pi)
        position = centres[o] + reach[o] * rng.uniform(1.05, 1.6) * np.array(
            [np.cos(angle), np.sin(angle)])
        heading = angle + np.pi + rng.normal(0.0, 0.3)  # towards the obstacle
        out.append(([*position, heading], [rng.uniform(1.0, 2.5), rng.uniform(-0.5, 0.5)],
                    *box))
    return out


def measure(safety_filter: SafetyFilter, inputs: list) -> dict:
    """Median and p99 of one decision (us), over all and over the corrected answers; the
    share of corrected answers; the mean number of RCBF rows in their QP."""
    for call in inputs[:50]:
        safety_filter.filter(*call)
    times, corrected, rows = [], [], []
    gc.collect()
    for call in inputs:
        start = time.perf_counter()
        result = safety_filter.filter(*call)
        elapsed = time.perf_counter() - start
        times.append(elapsed)
        if result.active:
            corrected.append(elapsed)
            if safety_filter.assembly == 'vectorised':
                rows.append(safety_filter.n_barriers - safety_filter._pruned)
    times_us, corrected_us = np.array(times) * 1e6, np.array(corrected or [np.nan]) * 1e6
    return {'median': float(np.median(times_us)), 'p99': float(np.percentile(times_us, 99)),
            'corrected median': float(np.median(corrected_us)),
            'corrected p99': float(np.percentile(corrected_us, 99)),
            'active': len(corrected) / len(inputs),
            'rows': float(np.mean(rows)) if rows else float('nan')}


def held_mb(problem: RCBFProblem, options: dict, inputs: list) -> float:
    """The memory (MB, tracemalloc) a filter of ``problem`` holds after a few decisions: its
    construction and its per-call allocations that stay (none should)."""
    gc.collect()
    tracemalloc.start()
    try:
        safety_filter = SafetyFilter(problem, slack_tolerance=1e-4, **options)
        for call in inputs:
            safety_filter.filter(*call)
        held = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return held / 1e6


def run(number: int) -> list[str]:
    lines = ['| circles | path | build (ms) | held (MB) | median (us) | p99 (us) | corrected | '
             'median, corrected (us) | p99, corrected (us) | rows in the QP (mean) |',
             '|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|']
    for count in COUNTS:
        problem = filter_config_from_params(world(count)).problem
        inputs = calls(count, number)
        paths = [('this tree', {})]
        if count <= PER_ROW_MOST:
            paths.insert(0, ('per row', {'vector_rows': 10 ** 9}))
        else:
            lines.append(f'| {count:,} | per row | - | - | - | - | - | - | - | not built: the '
                         'generated code passes what Python compiles (~750 rows) |')
        for name, options in paths:
            start = time.perf_counter()
            safety_filter = SafetyFilter(problem, slack_tolerance=1e-4, **options)
            build_ms = (time.perf_counter() - start) * 1e3
            held = held_mb(problem, options, inputs[:20])
            figures = measure(safety_filter, inputs)
            shown = f'{figures["rows"]:.1f}' if figures['rows'] == figures['rows'] else 'all'
            lines.append(f'| {count:,} | {name} ({safety_filter.assembly}) | {build_ms:.0f} | '
                         f'{held:.1f} | '
                         f'{figures["median"]:.0f} | {figures["p99"]:.0f} | '
                         f'{figures["active"]:.0%} | {figures["corrected median"]:.0f} | '
                         f'{figures["corrected p99"]:.0f} | {shown} |')
            print(lines[-1], flush=True)
    return lines


def targets(table: list[str]) -> str:
    """Where this tree stands against the scan targets (median per decision) at the same
    counts of circles."""
    medians = {}
    for line in table[2:]:
        cells = [c.strip() for c in line.strip('|').split('|')]
        if cells[1].startswith('this tree'):
            medians[int(cells[0].replace(',', ''))] = float(cells[7])
    parts = [f'{count:,} circles {medians[count]:.0f} us median over the corrected answers '
             f'(target {goal} us: '
             f'{"met" if medians[count] <= goal else "not met"})'
             for count, goal in ((360, 150), (2_000, 300)) if count in medians]
    return ('The scan targets (a LaserScan of 360 points <= 150 us per decision, 2,000 points '
            '<= 300 us, sources to command) at the same counts of circles, the filter call '
            'only: ' + '; '.join(parts) + '.')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=2000,
                        help='decisions timed per count and path (default 2000)')
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.calls < 1:
        parser.error('--calls must be >= 1')
    table = run(args.calls)
    from benchmarks._results import load_averages, publish_section
    publish_section(
        TITLE, script='bench_obstacle_scale.py'
        + (f' --calls {args.calls}' if args.calls != 2000 else ''),
        conditions=f'; {load_averages()}',
        write=args.write, blocks=[
            'One `SafetyFilter.filter` call per decision (config/unicycle.yaml with random '
            'circles at one per 16 m^2, radii 0.05-0.4 m; half the states at random, half '
            'next to an obstacle driving at it; proposals within the limits and a small '
            'disturbance box; `--calls` decisions per row of the table, after 50 unmeasured; '
            '"held": what the filter keeps, by tracemalloc; '
            '"corrected": the answers that changed the proposal, the costly ones). "per row" '
            'is the closed form generated as code per row, the '
            'only path before and kept below 64 obstacles; "this tree" is what the filter '
            'chooses. "rows in the QP": the RCBF rows the exact solve carried in the corrected '
            'answers (the rest were shown unable to bind; every row is checked at the answer).',
            table, targets(table), COLLISION_MONITOR,
            'Caveats: the machine (2 cores) was shared with other jobs, which moves the p99 '
            'most; the filter call only (no message decoding or publishing; a LaserScan or '
            "PointCloud2 source adds its own conversion); collision_monitor's figures come "
            'from its README, another machine and a different check (stop / slow-down zones, '
            'no QP), printed as a reference only.'])
    return 0


if __name__ == '__main__':
    sys.exit(main())

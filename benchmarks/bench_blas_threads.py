"""numpy's OpenBLAS threads: the policy's one-state product with the default and with one thread.

    python benchmarks/bench_blas_threads.py [--calls 3000] [--no-write]

A (1, 256) x (256, 256) float64 product (the actor's hidden layer, as the numpy acting path
computes it) timed in child processes that import numpy with ``OPENBLAS_NUM_THREADS`` unset
(OpenBLAS's default: a thread per core) and set to 1 (what ``import rcbf_ros`` sets), first on
an otherwise idle machine, then with one busy-looping process per core beside it (like two
training runs side by side, or the simulator, filter and recorder nodes).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
from pathlib import Path
import subprocess
import sys

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CHILD = r"""
import json, statistics, sys, time
import numpy as np
rng = np.random.default_rng(0)
w, x = rng.standard_normal((256, 256)), rng.standard_normal((1, 256))
for _ in range(200):
    x @ w
times = []
for _ in range(int(sys.argv[1])):
    start = time.perf_counter()
    x @ w
    times.append(time.perf_counter() - start)
times.sort()
print(json.dumps({'median': 1e6 * statistics.median(times),
                  'p99': 1e6 * times[int(0.99 * len(times))], 'max': 1e6 * times[-1]}))
"""


def child(calls: int, one_thread: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k != 'OPENBLAS_NUM_THREADS'}
    if one_thread:
        env['OPENBLAS_NUM_THREADS'] = '1'
    out = subprocess.run([sys.executable, '-c', CHILD, str(calls)], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def spin(stop) -> None:
    while not stop.is_set():
        pass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=3000)
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args()
    rows = ['| load | OpenBLAS threads | median us | p99 us | max us | p99 default / p99 one |',
            '|---|---|---:|---:|---:|---:|']
    for load in ('idle', 'one busy process per core'):
        stop = multiprocessing.Event()
        busy = []
        if load != 'idle':
            busy = [multiprocessing.Process(target=spin, args=(stop,))
                    for _ in range(os.cpu_count() or 2)]
            for proc in busy:
                proc.start()
        try:
            default, one = child(args.calls, False), child(args.calls, True)
        finally:
            stop.set()
            for proc in busy:
                proc.join()
        ratio = default['p99'] / one['p99']
        for name, result in (('default (one per core)', default), ('1', one)):
            rows.append(f"| {load} | {name} | {result['median']:.1f} | {result['p99']:.1f} "
                        f"| {result['max']:.0f} | {f'{ratio:.1f}x' if name == '1' else ''} |")
            print(rows[-1], flush=True)
    table = '\n'.join(rows)
    print(table)
    if not args.no_write:
        from benchmarks._results import machine_line, write_section
        write_section('numpy BLAS threads', (
            f'Command: `python benchmarks/bench_blas_threads.py --calls {args.calls}` (one '
            f'run; {machine_line()}). One (1, 256) x (256, 256) float64 product per call (the '
            "numpy acting path's hidden layer), in child processes with OPENBLAS_NUM_THREADS "
            'unset and set to 1 (what `import rcbf_ros` sets unless the variable is already '
            'set).\n\n' + table))


if __name__ == '__main__':
    main()

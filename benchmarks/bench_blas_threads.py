"""numpy's OpenBLAS as ``import rcbf_ros`` sets it up, against OpenBLAS's own defaults.

    python benchmarks/bench_blas_threads.py [--calls 3000] [--no-write]

Two settings of numpy's OpenBLAS, each timed in child processes that import numpy with the
environment variable under test (rcbf_ros/__init__.py says why each is set):

- **Threads**: a (1, 256) x (256, 256) float64 product (the actor's hidden layer, as the numpy
  acting path computes it) with ``OPENBLAS_NUM_THREADS`` unset (OpenBLAS's default: a thread
  per core) and set to 1, first on an otherwise idle machine, then with one busy-looping
  process per core beside it (like two training runs side by side, or the simulator, filter and
  recorder nodes). Both with the kernel rcbf_ros chooses.
- **Kernel**: the per-step products with ``OPENBLAS_CORETYPE`` unset (OpenBLAS picks by the
  CPU's model number) and set to what :func:`rcbf_ros.coretype_for` picks from the
  CPU's flags, one thread, interleaved over several child processes each. The kernel each
  child's OpenBLAS reports is printed (threadpoolctl).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
from pathlib import Path
import statistics
import subprocess
import sys

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rcbf_ros import coretype_for, cpu_flags  # noqa: E402

CHILD = r"""
import json, statistics, sys, time
import numpy as np
import threadpoolctl
calls = int(sys.argv[1])
rng = np.random.default_rng(0)
cases = {
    'policy layer, (1, 256) x (256, 256) float64':
        (rng.standard_normal((1, 256)), rng.standard_normal((256, 256))),
    'policy layer, (256,) x (256, 256) float32 (matrix-vector)':
        (rng.standard_normal((256, 256)).astype(np.float32),
         rng.standard_normal(256).astype(np.float32)),
    'GP variance, (1, 512) x (512, 495) float64':
        (rng.standard_normal((1, 512)), rng.standard_normal((512, 495))),
    'minibatch layer, (256, 256) x (256, 256) float32':
        (rng.standard_normal((256, 256)).astype(np.float32),
         rng.standard_normal((256, 256)).astype(np.float32)),
}
out = {'kernel': next((info.get('architecture') for info in threadpoolctl.threadpool_info()
                       if info.get('internal_api') == 'openblas'), None)}
for name, (a, b) in cases.items():
    for _ in range(50):
        a @ b
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - start)
    times.sort()
    out[name] = {'median': 1e6 * statistics.median(times),
                 'p99': 1e6 * times[int(0.99 * len(times))], 'max': 1e6 * times[-1]}
print(json.dumps(out))
"""
THREADS_CASE = 'policy layer, (1, 256) x (256, 256) float64'


def child(calls: int, *, one_thread: bool, coretype: str | None) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ('OPENBLAS_NUM_THREADS', 'OPENBLAS_CORETYPE')}
    if one_thread:
        env['OPENBLAS_NUM_THREADS'] = '1'
    if coretype is not None:
        env['OPENBLAS_CORETYPE'] = coretype
    out = subprocess.run([sys.executable, '-c', CHILD, str(calls)], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def spin(stop) -> None:
    while not stop.is_set():
        pass


def threads_table(calls: int, coretype: str | None) -> str:
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
            default = child(calls, one_thread=False, coretype=coretype)[THREADS_CASE]
            one = child(calls, one_thread=True, coretype=coretype)[THREADS_CASE]
        finally:
            stop.set()
            for proc in busy:
                proc.join()
        ratio = default['p99'] / one['p99']
        for name, result in (('default (one per core)', default), ('1', one)):
            rows.append(f"| {load} | {name} | {result['median']:.1f} | {result['p99']:.1f} "
                        f"| {result['max']:.0f} | {f'{ratio:.1f}x' if name == '1' else ''} |")
            print(rows[-1], flush=True)
    return '\n'.join(rows)


def kernel_table(calls: int, coretype: str | None, repeats: int) -> tuple[str, list[str]]:
    """Medians over ``repeats`` interleaved children per setting (each a median of
    ``calls``)."""
    runs: dict[str, list[dict]] = {'own': [], 'chosen': []}
    for _ in range(repeats):
        runs['own'].append(child(calls, one_thread=True, coretype=None))
        runs['chosen'].append(child(calls, one_thread=True, coretype=coretype))
    kernels = {key: sorted({str(run['kernel']) for run in value}) for key, value in runs.items()}
    cases = [key for key in runs['own'][0] if key != 'kernel']
    rows = [f"| product | OpenBLAS's own choice ({', '.join(kernels['own'])}), median us "
            f"| rcbf_ros's ({', '.join(kernels['chosen'])}), median us | own / rcbf_ros's |",
            '|---|---:|---:|---:|']
    for case in cases:
        own = statistics.median(run[case]['median'] for run in runs['own'])
        chosen = statistics.median(run[case]['median'] for run in runs['chosen'])
        rows.append(f'| {case} | {own:.1f} | {chosen:.1f} | {own / chosen:.1f}x |')
        print(rows[-1], flush=True)
    return '\n'.join(rows), kernels['own']


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=3000)
    parser.add_argument('--repeats', type=int, default=5,
                        help='child processes per kernel setting, interleaved')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args()
    coretype = coretype_for(cpu_flags())
    print(f'rcbf_ros chooses OPENBLAS_CORETYPE={coretype}', flush=True)
    threads = threads_table(args.calls, coretype)
    if coretype is None:
        kernels = ('The kernel comparison was skipped: rcbf_ros leaves the kernel to OpenBLAS on '
                   'this CPU (no AVX2 + FMA flags, or no /proc/cpuinfo).')
    else:
        table, own = kernel_table(args.calls, coretype, args.repeats)
        kernels = (f'One thread, idle; {args.repeats} child processes per setting, '
                   'interleaved; the median of their medians. OpenBLAS picks its kernels from '
                   f"the CPU's model number; on this CPU it picked {', '.join(own)}; rcbf_ros "
                   f"sets OPENBLAS_CORETYPE={coretype} from the CPU's instruction set flags. "
                   'The products are the per-step ones (policy, GP variance at one state) and '
                   'one of minibatch size for scale (the SAC update itself runs in torch, '
                   "whose BLAS is its own).\n\n" + table)
    print(threads)
    print(kernels)
    if not args.no_write:
        from benchmarks._results import machine_line, write_section
        write_section('numpy BLAS: threads and kernel', (
            f'Command: `python benchmarks/bench_blas_threads.py --calls {args.calls} '
            f'--repeats {args.repeats}` (one run; {machine_line()}). What `import rcbf_ros` '
            'sets before numpy loads, unless the environment already sets it: '
            "OPENBLAS_NUM_THREADS=1 and OPENBLAS_CORETYPE from the CPU's flags "
            '(rcbf_ros/__init__.py).\n\n'
            '**Threads.** One (1, 256) x (256, 256) float64 product per call (the numpy '
            "acting path's hidden layer), in child processes with OPENBLAS_NUM_THREADS unset "
            f'and set to 1, both with OPENBLAS_CORETYPE={coretype}.\n\n' + threads
            + '\n\n**Kernel.** ' + kernels))


if __name__ == '__main__':
    main()

"""Experiment runner: the same runs sequentially and as Ray tasks, on a machine with other work.

    python benchmarks/bench_ray.py [--runs 2] [--episodes 1] [--load 2] [--no-write]

Trains ``runs`` Unicycle Modular runs (seeds 0..runs-1; 256x256 SAC, batch 256, episodes of
200 steps, updates from step 100) three ways, each in a fresh process while ``load`` busy
processes (pure Python loops at the caller's priority) stand for the other work of the machine
(the simulator and filter nodes, another experiment):

- sequential: ``run_all`` in the calling process;
- Ray, ours: a local instance with 2 CPUs as ``rcbf_ros experiment --ray --num-cpus 2`` starts
  it (``LOCAL_RAY_ENV``: loopback, workers at the caller's priority);
- Ray, default niceness: the same with Ray's own worker niceness (15).

The wall time of each includes starting Ray and the workers' imports. Every way trains the
same runs (the returns are compared: equal to the last bit). Writes the ``## Experiment runner,
sequential vs Ray`` section of benchmarks/RESULTS.md.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from benchmarks._results import publish_section  # noqa: E402

torch.set_num_threads(1)  # as in every run (RunConfig.threads); machine_line reports it

CHILD = r"""
import json, sys, time
from rcbf_ros.experiments.definitions import Budget, RunSpec
from rcbf_ros.experiments.runner import run_all
runs, episodes, backend, root = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
budget = Budget(name='bench', episodes={'unicycle': episodes}, max_steps={'unicycle': 200},
                start_steps=100, update_after=100, batch_size=256, gp_refit_interval=200,
                hidden_sizes=(256, 256), record_bag=False)
specs = [RunSpec('unicycle', 'modular', seed, budget) for seed in range(runs)]
start = time.perf_counter()
results = run_all(specs, root, backend=backend, num_cpus=2, log=lambda _: None)
wall = time.perf_counter() - start
returns = [[row['ret'] for row in map(json.loads, open(s.run_dir(root) / 'metrics.jsonl'))]
           for s in specs]
print(json.dumps({'wall_s': wall, 'returns': returns,
                  'run_wall_s': [r['wall_s'] for r in results]}))
"""


def measure(backend: str, niceness: str | None, args: argparse.Namespace) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS='1', MKL_NUM_THREADS='1')
    if niceness is not None:
        env['RAY_worker_niceness'] = niceness
    with tempfile.TemporaryDirectory() as root:
        out = subprocess.run([sys.executable, '-c', CHILD, str(args.runs), str(args.episodes),
                              backend, root], env=env, capture_output=True, text=True,
                             check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=2, help='training runs per way')
    parser.add_argument('--episodes', type=int, default=1, help='episodes per run')
    parser.add_argument('--load', type=int, default=2, help='busy processes beside')
    parser.add_argument('--no-write', action='store_true', help='do not touch RESULTS.md')
    args = parser.parse_args()

    load = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
            for _ in range(args.load)]
    try:
        ways = {'sequential': measure('sequential', None, args),
                'Ray, ours (workers at niceness 0)': measure('ray', None, args),
                "Ray, Ray's default (workers at niceness 15)": measure('ray', '15', args)}
    finally:
        for process in load:
            process.kill()
            process.wait()
    reference = ways['sequential']
    rows = ['| way | wall (s) | per run, median (s) | ratio to sequential | returns equal |',
            '|---|---:|---:|---:|---|']
    for name, result in ways.items():
        per_run = sorted(result['run_wall_s'])[len(result['run_wall_s']) // 2]
        rows.append(f"| {name} | {result['wall_s']:.1f} | {per_run:.1f} "
                    f"| {result['wall_s'] / reference['wall_s']:.2f}x "
                    f"| {result['returns'] == reference['returns']} |")
        print(rows[-1], flush=True)
    blocks = [
        f'{args.runs} Unicycle Modular runs of {args.episodes} episodes x 200 steps (256x256 '
        'SAC, batch 256, updates from step 100) per way, each way in a fresh process, wall time '
        "including Ray's start and the workers' imports; ratio = wall / sequential wall. "
        'Ray: a local instance with 2 CPUs. Runs this short show the cost of starting Ray '
        "(about 10 s) more than its parallelism; the niceness row is the point: Ray's default "
        'starves its workers on a machine with other work.', rows]
    publish_section('Experiment runner, sequential vs Ray', script='bench_ray.py', blocks=blocks,
                    write=not args.no_write,
                    conditions=f'; {args.load} busy processes beside')


if __name__ == '__main__':
    main()

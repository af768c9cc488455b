"""The pass that fills the replay buffer's memo after a GP refit, at a full buffer: its CPU time
with the kernel from the squared differences (in calls of 128 states) against the kernel on the
GEMM path (``gp_bounds.kernel_batch``, in calls of ``PREDICT_CHUNK``), and how far apart the two
passes' predictions are.

    python benchmarks/bench_fill_pass.py [--rows pvtol/modular ...] [--buffer 200000]
        [--refit-interval 1000] [--repeats 3] [--quick] [--no-write]

Per row, one process: the run of benchmarks/bench_training_full_buffer.py up to its full-buffer
refit (2 R - 1 steps, the first refit and R - 1 updates; the buffer and the GP's pairs tiled to
``--buffer``; the refit), then ``ReplayBuffer.fill_predictions`` over every stored transition,
the two ways alternating ``--repeats`` times, each on a new model version (nothing memoised).
CPU time of the process (1 thread), steadier than the wall clock on a shared machine; the
median over the repeats. The predictions of the last pass of each way are compared: the largest
difference of the mean relative to the largest |mean|, and of the std relative to itself.
``--quick``: bench_training_full_buffer's quick sizes, a smoke test.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import os
import statistics
import time

from bench_training_full_buffer import build, fill_to, MODES, QUICK, SYSTEMS
import torch

from rcbf_ros.learning import gp_bounds
from rcbf_ros.learning.buffers import PREDICT_CHUNK

torch.set_num_threads(1)

WAYS = {'squared differences, 128': (1 << 62, 128),
        f'GEMM, {PREDICT_CHUNK}': (gp_bounds.GEMM_BATCH, PREDICT_CHUNK)}
"""Way -> (``gp_bounds.GEMM_BATCH`` during the pass, states per call)."""


def measure(system: str, mode: str, *, buffer: int, refit_interval: int, batch_size: int,
            repeats: int) -> dict:
    """Both ways' CPU seconds per pass (lists) and their predictions' distance."""
    env, filt, learner = build(system, mode, buffer=buffer, refit_interval=refit_interval,
                               batch_size=batch_size)
    torch.set_num_threads(1)
    obs, info = env.reset(seed=0)
    state = info['state']
    for step in range(2 * refit_interval):
        if step == 2 * refit_interval - 1:
            fill_to(learner, buffer)  # the next step refits
        proposal = learner.propose(obs, state)
        u_safe = proposal.u_proposed
        if filt is not None:
            u_safe = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std).u_safe
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe, reward=reward,
                        next_obs=next_obs, next_state=info['state'], terminated=terminated)
        learner.after_step()
        obs, state = next_obs, info['state']
        if terminated or truncated:
            obs, info = env.reset()
            state = info['state']
    memo = learner.buffer
    seconds: dict[str, list[float]] = {way: [] for way in WAYS}
    last: dict[str, torch.Tensor] = {}
    version = learner.gp.version + 1
    default = gp_bounds.GEMM_BATCH
    try:
        for _ in range(repeats):
            for way, (gemm_batch, chunk) in WAYS.items():
                gp_bounds.GEMM_BATCH = gemm_batch
                start = time.process_time()
                states = memo.fill_predictions(version=version, predict=learner.disturbance,
                                               chunk=chunk)
                seconds[way].append(time.process_time() - start)
                last[way] = memo.predictions(torch.arange(len(memo)), version=version,
                                             predict=learner.disturbance).state.clone()
                version += 1
    finally:
        gp_bounds.GEMM_BATCH = default
    first, second = last.values()  # (N, 2 [mean, std], n_x)
    mean_gap = float((first[:, 0] - second[:, 0]).abs().max()
                     / first[:, 0].abs().max().clamp_min(1e-300))
    std_gap = float(((first[:, 1] - second[:, 1]).abs()
                     / first[:, 1].abs().clamp_min(1e-300)).max())
    return {'seconds': seconds, 'states': states, 'mean_gap': mean_gap, 'std_gap': std_gap,
            'bound': learner.gp.variance_bound}


def row_text(system: str, mode: str, result: dict) -> str:
    median = {way: statistics.median(values) for way, values in result['seconds'].items()}
    before, after = median.values()
    bound = result['bound']
    names = ', '.join(f"{kind.replace('_', ' ')} {rank}"
                      for kind, rank in zip(bound['bound'], bound['rank'].tolist()))
    return (f"| {system} | {mode} | {names} | {result['states']} | {before:.2f} | {after:.2f} "
            f"| {before / after:.2f}x | {1e6 * after / result['states']:.1f} "
            f"| {result['mean_gap']:.1e} | {result['std_gap']:.1e} |")


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rows', nargs='*', default=None, metavar='SYSTEM/MODE')
    parser.add_argument('--buffer', type=int, default=None)
    parser.add_argument('--refit-interval', type=int, default=None)
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--quick', action='store_true')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    defaults = QUICK if args.quick else {
        'buffer': 200_000, 'refit_interval': 1000,
        'rows': ['car_following/diff', 'pvtol/modular', 'pvtol/diff', 'unicycle/diff']}
    buffer = args.buffer or defaults['buffer']
    refit_interval = args.refit_interval or defaults['refit_interval']
    if refit_interval < 20 or args.repeats < 1 or buffer < 2 * refit_interval:
        parser.error('--refit-interval must be >= 20, --repeats >= 1, --buffer at least '
                     '2 x --refit-interval')
    rows = []
    for row in args.rows or defaults['rows']:
        system, _, mode = row.partition('/')
        if system not in SYSTEMS or mode not in MODES:
            parser.error(f'--rows: {row!r} is not SYSTEM/MODE with SYSTEM one of '
                         f'{", ".join(SYSTEMS)} and MODE one of {", ".join(MODES)}')
        rows.append((system, mode))
    load_before = os.getloadavg()
    before, after = WAYS
    table = [f'| system | mode | bound per output (rank) | states predicted '
             f'| pass CPU s, {before} '
             f'| pass CPU s, {after} | ratio | us per state, {after} '
             '| max mean difference / max abs mean | max std difference / std |',
             '|---|---|---|---:|---:|---:|---:|---:|---:|---:|']
    for system, mode in rows:
        result = measure(system, mode, buffer=buffer, refit_interval=refit_interval,
                         batch_size=defaults.get('batch_size', 256), repeats=args.repeats)
        table.append(row_text(system, mode, result))
        print(table[-1], flush=True)
    command = ('python benchmarks/bench_fill_pass.py' + (' --quick' if args.quick else '')
               + f' --buffer {buffer} --refit-interval {refit_interval}'
               + f' --repeats {args.repeats} --rows {" ".join(f"{s}/{m}" for s, m in rows)}')
    from _results import publish_table
    return publish_table('The memo pass at a full buffer: kernel from differences vs GEMM',
                         script='bench_fill_pass.py', command=command, table=table,
                         load_before=load_before, write=not args.no_write)


if __name__ == '__main__':
    main()

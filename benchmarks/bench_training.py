"""Training speed: environment steps per second including SAC updates, per system and mode.

    python benchmarks/bench_training.py [--steps 200] [--systems unicycle ...]

Setting of issue 4: 1 SAC update per environment step, minibatch 256, 256x256 networks, the
per-step safety filter (compiled assembly) and the GP estimate on every step, in-process. Each
configuration first fills the buffer with ``warmup`` random steps (not timed), then times
``steps`` steps with updates. Also reported: the median SAC update (diff mode: both losses
through the differentiable QP) and the per-action latency (policy + GP prediction + filter).

The reference column is the authors' implementation measured on this machine size, as quoted
in issue 4 (not re-measured here); the ratio is ours / reference.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.loop import build_run, RunConfig

torch.set_num_threads(1)

REFERENCE_STEPS_PER_S = {
    ('unicycle', 'diff'): 8.4, ('unicycle', 'modular'): 18.9, ('unicycle', 'baseline'): 27.3,
    ('car_following', 'diff'): 3.6, ('pvtol', 'diff'): 5.1,
}
"""Issue 4: the reference code's steps/s; its 'full' (differentiable layer) runs are listed
under diff and compared with both our diff rows."""


def measure(system: str, mode: str, model_based: bool, steps: int, warmup: int) -> dict:
    learner_cfg = LearnerConfig(mode=mode, model_based=model_based, seed=0,
                                start_steps=warmup, update_after=warmup, batch_size=256,
                                gp_refit_interval=warmup, rollout_interval=100)
    run = RunConfig(system=system, episodes=1, max_steps=10 ** 6, record_bag=False,
                    out_dir='/tmp/bench_training', compile_filter=True, learner=learner_cfg)
    env, filt, learner, _ = build_run(run)
    obs, info = env.reset(seed=0)
    state = info['state']
    action_times, update_times, filter_times = [], [], []

    def one_step(timed: bool) -> None:
        nonlocal obs, state
        t0 = time.perf_counter()
        proposal = learner.propose(obs, state)
        t1 = time.perf_counter()
        u_safe = proposal.u_proposed
        if filt is not None:
            u_safe = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std).u_safe
        t2 = time.perf_counter()
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe, reward=reward,
                        next_obs=next_obs, next_state=info['state'], terminated=terminated)
        t3 = time.perf_counter()
        metrics = learner.after_step()
        t4 = time.perf_counter()
        if timed:
            action_times.append(t2 - t0)
            filter_times.append(t2 - t1)
            if metrics:
                update_times.append(t4 - t3)
        obs, state = next_obs, info['state']
        if terminated or truncated:
            obs, info = env.reset()
            state = info['state']

    for _ in range(warmup):
        one_step(False)
    start = time.perf_counter()
    for _ in range(steps):
        one_step(True)
    elapsed = time.perf_counter() - start
    return {
        'steps_per_s': steps / elapsed,
        'update_ms': 1e3 * statistics.median(update_times) if update_times else float('nan'),
        'action_ms': 1e3 * statistics.median(action_times),
        'filter_ms': 1e3 * statistics.median(filter_times),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=200)
    parser.add_argument('--warmup', type=int, default=300)
    parser.add_argument('--systems', nargs='*', default=['unicycle', 'car_following', 'pvtol'])
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args()
    configs = []
    for system in args.systems:
        modes = [('baseline', False), ('modular', False), ('diff', False)]
        if system in ('unicycle', 'pvtol'):
            modes.append(('diff', True))
        configs += [(system, m, mb) for m, mb in modes]
    rows = ['| system | mode | steps/s | median update ms | action ms (policy+GP+filter) | '
            'filter ms | reference steps/s | ours / reference |',
            '|---|---|---:|---:|---:|---:|---:|---:|']
    for system, mode, mb in configs:
        result = measure(system, mode, mb, args.steps, args.warmup)
        name = f"{mode}{' + model_based' if mb else ''}"
        ref = REFERENCE_STEPS_PER_S.get((system, mode))
        ratio = f"{result['steps_per_s'] / ref:.1f}x" if ref else ''
        row = (f"| {system} | {name} | {result['steps_per_s']:.1f} | {result['update_ms']:.1f} "
               f"| {result['action_ms']:.2f} | {result['filter_ms']:.2f} | {ref or ''} "
               f'| {ratio} |')
        print(row, flush=True)
        rows.append(row)
    table = '\n'.join(rows)
    print(table)
    if not args.no_write:
        from _results import machine_line, write_section
        write_section('Training speed', (
            f'Command: `python benchmarks/bench_training.py --steps {args.steps}`. '
            + machine_line() + '. In-process, 1 update/step, batch 256, 256x256 networks, '
            "compiled per-step filter assembly. Reference steps/s: the authors' code on this "
            'machine size as quoted in issue 4 (Unicycle diff is their "full" = MB).\n\n'
            + table))


if __name__ == '__main__':
    np.set_printoptions(precision=3)
    main()

"""Per-action latency (policy + GP + filter), while training and when deployed, side by side.

    python benchmarks/bench_action_latency.py [--actions 400] [--systems unicycle ...]

The targets are a median per-action latency of at most 0.5 ms while training and 0.3 ms
deployed: from a state to the safe action, i.e. the policy's forward pass, one GP prediction
(mean and std at the state) and the RCBF-QP, as ``SafeLearner.propose`` and the filter do it.
The same code runs in two settings, measured here in one run, interleaved action by action so
that load from other processes hits both alike:

- **training**: a SAC update (batch 256, 256x256 networks) ran just before the action, as in
  the training loop and the learner node. The update streams megabytes of weights, gradients
  and minibatches through the caches, so the action finds the GP's cached factors and the
  policy weights in DRAM.
- **deployed**: no update since the previous action, as in the ``policy`` node (trained policy
  plus filter, no learner) and in the standalone ``safety_filter`` node.

Each setting runs with three GP paths, also interleaved: ``chosen`` (the default,
``DisturbanceGP.predict_state``: numpy on one state, each output's variance bound as chosen at
the refit, the projection, the hybrid low-rank-plus-neighbourhood or the low-rank bound),
``low-rank``
(``predict_state(..., bound='low_rank')``: the low-rank bound on every output) and ``exact``
(``DisturbanceGP.predict(..., exact=True)`` on a torch tensor: the exact variance through the
M x M factor). The action applied is the one filtered with the path's own estimate.

Each system first runs ``--warmup`` steps with updates, so that the GP is fitted at its training
cap (512 points) and the networks are trained; then the timed actions cycle through the six
(setting, GP path) pairs. The learner is the in-process one (``build_run``, baseline mode,
the filter's closed-form assembly), one torch thread, one BLAS thread.

Also reported, per system: where the filter's time goes (its constraint assembly, OSQP with the
row check, the rest of ``SafetyFilter.filter``, and the call's own overhead outside the
filter's timer), the CPU time of the action (``time.thread_time``: less sensitive to other
processes than the wall time), and the low-rank bound against the exact variance on the same
GP and states: the low-rank bound's kept rank, the worst-case variance excess the rank was
chosen for, each output's chosen bound and its rank, the measured std ratios of
both bounds to the exact std, and how often the true disturbance (the environment's, at the
state and the applied action) lies inside each box mean +/- k_c std.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import os

# One thread for OpenMP and MKL too, as torch's (rcbf_ros set OpenBLAS's): before numpy loads.
for _name in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_name, '1')

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from rcbf_ros.training.agent import LearnerConfig  # noqa: E402
from rcbf_ros.training.build import build_run, RunConfig  # noqa: E402

torch.set_num_threads(1)

PARTS = ('policy', 'gp', 'filter', 'total', 'cpu', 'assembly', 'solve', 'filter_rest',
         'call_overhead', 'osqp', 'policy_again', 'gp_again', 'filter_again')
SETTINGS = ('training', 'deployed')
PATHS = ('chosen', 'low-rank', 'exact')


def measure(system: str, actions: int, warmup: int) -> dict[str, object]:
    """Per-part latencies (seconds) of ``actions`` actions per (setting, GP path), and the
    low-rank bound's accuracy and containment on the states the timed actions visited."""
    learner_cfg = LearnerConfig(mode='baseline', seed=0, start_steps=warmup,
                                update_after=warmup, batch_size=256, gp_refit_interval=warmup)
    run = RunConfig(system=system, episodes=1, max_steps=10 ** 6, record_bag=False,
                    out_dir='/tmp/bench_action_latency', learner=learner_cfg)
    env, filt, learner, _ = build_run(run)
    assert filt is not None
    gp, k_c, system_model = learner.gp, learner.config.k_c, learner.system
    assemble = filt._assemble
    assembly_time = [0.0]

    def timed_assembly(*args: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        start = time.perf_counter()
        out = assemble(*args)
        assembly_time[0] = time.perf_counter() - start
        return out

    filt._assemble = timed_assembly
    solver_solve = filt._solver.solve
    solves = [0]

    def counted_solve(*args: object, **kwargs: object) -> object:
        solves[0] += 1
        return solver_solve(*args, **kwargs)

    filt._solver.solve = counted_solve
    obs, info = env.reset(seed=0)
    state = info['state']
    times = {(s, p): {part: [] for part in PARTS} for s in SETTINGS for p in PATHS}
    boxes: list[tuple[np.ndarray, ...]] = []

    def gp_estimate(path: str) -> tuple[np.ndarray, np.ndarray]:
        if path == 'chosen':
            return gp.predict_state(np.asarray(state, dtype=np.float64))
        if path == 'low-rank':
            return gp.predict_state(np.asarray(state, dtype=np.float64), bound='low_rank')
        x = torch.as_tensor(np.array(state, dtype=np.float64)).unsqueeze(0)
        mean, std = gp.predict(x, exact=True)
        return mean[0].numpy(), std[0].numpy()

    def act(path: str, record: dict[str, list[float]] | None
            ) -> tuple[np.ndarray, np.ndarray]:
        solves_before = solves[0]
        c0 = time.thread_time()
        t0 = time.perf_counter()
        detailed = learner.sac.act_detailed(np.asarray(obs, dtype=np.float64), False)
        t1 = time.perf_counter()
        mean, std = gp_estimate(path)
        t2 = time.perf_counter()
        result = filt.filter(state, detailed.u_proposed.astype(np.float64), mean, std)
        t3 = time.perf_counter()
        c1 = time.thread_time()
        ran_osqp, assembly = float(solves[0] > solves_before), assembly_time[0]
        if record is not None:
            # The same three calls again at once: what they cost with warm caches.
            r0 = time.perf_counter()
            learner.sac.act_detailed(np.asarray(obs, dtype=np.float64), False)
            r1 = time.perf_counter()
            gp_estimate(path)
            r2 = time.perf_counter()
            filt.filter(state, detailed.u_proposed.astype(np.float64), mean, std)
            r3 = time.perf_counter()
            values = (t1 - t0, t2 - t1, t3 - t2, t3 - t0, c1 - c0, assembly,
                      result.solve_time_s, result.total_time_s - assembly - result.solve_time_s,
                      (t3 - t2) - result.total_time_s, ran_osqp,
                      r1 - r0, r2 - r1, r3 - r2)
            for part, value in zip(PARTS, values):
                record[part].append(value)
        return detailed.u_rl.astype(np.float64), result.u_safe

    def step(u_rl: np.ndarray, u_safe: np.ndarray) -> np.ndarray:
        nonlocal obs, state
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        x = torch.as_tensor(np.asarray(state, dtype=np.float64)).unsqueeze(0)
        u = torch.as_tensor(u_safe).reshape(1, -1, 1)
        nominal = system_model.f(x) + (system_model.g(x) @ u).squeeze(-1)
        true = ((torch.as_tensor(info['state']) - x[0]) / env.dt - nominal[0]).numpy()
        learner.observe(obs=obs, state=state, u_rl=u_rl, u_safe=u_safe, reward=reward,
                        next_obs=next_obs, next_state=info['state'], terminated=terminated)
        obs, state = next_obs, info['state']
        if terminated or truncated:
            obs, info = env.reset()
            state = info['state']
        return true

    for _ in range(warmup):
        step(*act('chosen', None))
        learner.after_step()
    for k in range(2 * len(PATHS) * actions):
        setting, path = SETTINGS[k % 2], PATHS[(k // 2) % len(PATHS)]
        if setting == 'training':
            learner.after_step()  # the update right before the action, as in the loop
        x_before = np.asarray(state, dtype=np.float64)
        u_rl, u_safe = act(path, times[(setting, path)])
        true = step(u_rl, u_safe)
        boxes.append((x_before, true))
    active = gp.active_outputs.numpy()
    states = torch.as_tensor(np.stack([b[0] for b in boxes]))
    truth = np.stack([b[1] for b in boxes])[:, active]
    mean_e, std_e = (t.numpy()[:, active] for t in gp.predict(states, exact=True))
    mean_r, std_r = (t.numpy()[:, active] for t in gp.predict(states, bound='low_rank'))
    mean_c, std_c = (t.numpy()[:, active] for t in gp.predict(states))
    ratio = std_r / np.maximum(std_e, 1e-300)
    ratio_c = std_c / np.maximum(std_e, 1e-300)
    rank = gp.variance_rank
    hybrid = gp.variance_bound
    chosen = ', '.join(f"{name.replace('_', '-')} {r}"
                       for name, r in zip(hybrid['bound'], hybrid['rank'].tolist()))
    return {
        'times': {key: {p: np.asarray(v) for p, v in parts.items()}
                  for key, parts in times.items()},
        'active': f'{int(active.sum())} of {active.size}',
        'rank': f"{', '.join(str(r) for r in rank['kept'].tolist())} of {rank['points']}",
        'excess': float(rank['excess'].max()) if rank['excess'].numel() else 0.0,
        'contained_exact': float((np.abs(truth - mean_e) <= k_c * std_e).mean()),
        'contained_low_rank': float((np.abs(truth - mean_r) <= k_c * std_r).mean()),
        'contained_chosen': float((np.abs(truth - mean_c) <= k_c * std_c).mean()),
        'std_ratio': (float(np.median(ratio)), float(ratio.max()), float(ratio.min())),
        'std_ratio_chosen': (float(np.median(ratio_c)), float(ratio_c.max()),
                             float(ratio_c.min())),
        'chosen': f"{chosen} (m = {hybrid['size']}, shared basis {hybrid['shared']})",
        'checks': truth.size,
    }


TARGET_US = {'training': 500.0, 'deployed': 300.0}
"""Median per-action latency targets, microseconds."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--actions', type=int, default=400,
                        help='timed actions per setting, GP path and system')
    parser.add_argument('--warmup', type=int, default=600)
    parser.add_argument('--systems', nargs='*', default=['unicycle', 'pvtol', 'car_following'])
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    rows = ['| system | GP outputs with a posterior | setting | GP path | policy | GP | filter '
            '| total median | total p99 | total CPU median |',
            '|---|---:|---|---|---:|---:|---:|---:|---:|---:|']
    split = ['| system | setting | filter | assembly | OSQP + row check | rest of filter '
             '| call overhead | actions that ran OSQP | called again at once: policy, GP, '
             'filter |',
             '|---|---|---:|---:|---:|---:|---:|---:|---|']
    bound = ['| system | low-rank: rank kept per output | worst-case variance excess / s '
             '| chosen bound per output | std ratio low-rank / exact (median, max, min) '
             '| std ratio chosen / exact (median, max, min) '
             '| true disturbance inside the box: exact | low-rank | chosen | checks |',
             '|---|---:|---:|---|---|---|---:|---:|---:|---:|']
    verdicts = []
    for system in args.systems:
        result = measure(system, args.actions, args.warmup)
        times = result['times']
        med = {key: {p: 1e6 * np.median(v) for p, v in parts.items()}
               for key, parts in times.items()}
        training = med[('training', 'chosen')]['total']
        deployed = med[('deployed', 'chosen')]['total']
        verdicts.append(
            f"{system} training {training:.0f} us "
            f"({'met' if training <= TARGET_US['training'] else 'not met'}; low-rank GP "
            f"{med[('training', 'low-rank')]['total']:.0f}, exact GP "
            f"{med[('training', 'exact')]['total']:.0f}), deployed {deployed:.0f} us "
            f"({'met' if deployed <= TARGET_US['deployed'] else 'not met'}; low-rank GP "
            f"{med[('deployed', 'low-rank')]['total']:.0f}, exact GP "
            f"{med[('deployed', 'exact')]['total']:.0f})")
        for setting in SETTINGS:
            for path in PATHS:
                m = med[(setting, path)]
                p99 = 1e6 * np.percentile(times[(setting, path)]['total'], 99)
                row = (f"| {system} | {result['active']} | {setting} | {path} "
                       f"| {m['policy']:.0f} | {m['gp']:.0f} | {m['filter']:.0f} "
                       f"| {m['total']:.0f} | {p99:.0f} | {m['cpu']:.0f} |")
                print(row, flush=True)
                rows.append(row)
            m = med[(setting, 'chosen')]
            osqp = 100.0 * times[(setting, 'chosen')]['osqp'].mean()
            split.append(f"| {system} | {setting} | {m['filter']:.0f} | {m['assembly']:.0f} "
                         f"| {m['solve']:.0f} | {m['filter_rest']:.0f} "
                         f"| {m['call_overhead']:.0f} | {osqp:.0f} % "
                         f"| {m['policy_again']:.0f}, {m['gp_again']:.0f}, "
                         f"{m['filter_again']:.0f} |")
        ratio, ratio_c = result['std_ratio'], result['std_ratio_chosen']
        bound.append(f"| {system} | {result['rank']} | {result['excess']:.1e} "
                     f"| {result['chosen']} "
                     f"| {ratio[0]:.6f}, {ratio[1]:.6f}, {ratio[2]:.6f} "
                     f"| {ratio_c[0]:.6f}, {ratio_c[1]:.6f}, {ratio_c[2]:.6f} "
                     f"| {100 * result['contained_exact']:.2f} % "
                     f"| {100 * result['contained_low_rank']:.2f} % "
                     f"| {100 * result['contained_chosen']:.2f} % | {result['checks']} |")
        print(split[-2], split[-1], bound[-1], sep='\n', flush=True)
    load_after = os.getloadavg()[0]
    tables = '\n'.join(rows) + '\n\n' + '\n'.join(split) + '\n\n' + '\n'.join(bound)
    reading = ('Medians against the targets (training <= '
               f"{TARGET_US['training']:.0f} us, deployed <= {TARGET_US['deployed']:.0f} us), "
               'GP path chosen (the default): ' + '; '.join(verdicts) + '.')
    print(tables, reading, sep='\n\n')
    if not args.no_write:
        from _results import machine_line, write_section
        write_section('Per-action latency, training vs deployed', (
            f'Command: `python benchmarks/bench_action_latency.py --actions {args.actions}` '
            f'(one run). {machine_line()}; 1-minute load average {load_before:.1f} before, '
            f'{load_after:.1f} after, on 2 cores. Microseconds; {args.actions} actions per '
            f'setting and GP path, interleaved, after {args.warmup} warm-up steps (GP at its '
            '512-point cap). "training": a SAC update ran right before the action; '
            '"deployed": none did (the policy node, the standalone filter). See the '
            "script's docstring.\n\n" + tables + '\n\n' + reading))


if __name__ == '__main__':
    main()

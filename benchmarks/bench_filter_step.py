"""Per-step safety filter: ours (OSQP set up once, update per call) vs the alternatives.

    python benchmarks/bench_filter_step.py [--calls 2000]

Same QPs for every solver, one run: the Unicycle QP (8 obstacles + input limits) and the PVTOL
QP (9 obstacles + operator band, cascaded twice, + input limits), at random states. Columns:
median / p99 per call in microseconds and the ratio to ours.
- ours, solve: OSQP.update(Ax, u) + solve (warm start, polish) on the fixed pattern
- ours, filter(): the whole SafetyFilter.filter() call, constraint assembly (torch autograd
  through the barriers and cascades) included, eager and compiled (compile_assembly=True)
- OSQP set up every call: a new OSQP object per call (setup + solve)
- qpth at batch 1: the reference implementation's choice (a batched interior point at B = 1)
"""
from __future__ import annotations

import argparse
import time

from _problems import pvtol_params, unicycle_params
import numpy as np
import osqp
import scipy.sparse as sp
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter

torch.set_num_threads(1)


def random_inputs(system_name: str, n: int, rng: np.random.Generator, problem=None):
    """n states inside the safe set (every top-level barrier >= 0) and n proposals in the box."""
    states = np.zeros((0, problem.system.n_x))
    while len(states) < n:
        candidates = _candidates(system_name, 4 * n, rng)
        h = problem.terms(torch.from_numpy(candidates)).h.numpy()
        states = np.concatenate([states, candidates[(h >= 0).all(axis=1)]])[:n]
    return states, rng.uniform(-2.5, 2.5, (n, 2))


def _candidates(system_name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    if system_name == 'unicycle':
        r = rng.uniform(0.3, 1.5, n)
        a = rng.uniform(0, 2 * np.pi, n)
        states = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-np.pi, np.pi, n)], 1)
    else:
        states = np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), rng.normal(0, 0.5, (n, 2)),
                                 rng.normal(0, 0.2, (n, 1)), rng.uniform(0.8, 1.2, (n, 1)),
                                 rng.uniform(-0.3, 0.3, (n, 1))], 1)
    return states


def percentiles(samples: list[float]) -> tuple[float, float]:
    arr = 1e6 * np.asarray(samples)
    return float(np.median(arr)), float(np.percentile(arr, 99))


def clarabel_solution(qp) -> np.ndarray:
    """Independent reference: the same QP through cvxpy + Clarabel (interior point, float64)."""
    import cvxpy as cp
    P, q, G, h = (t[0].numpy() for t in qp)
    z = cp.Variable(P.shape[0])
    cp.Problem(cp.Minimize(0.5 * cp.quad_form(z, P) + q @ z), [G @ z <= h]).solve(
        solver='CLARABEL')
    return z.value


def bench(system_name: str, params: dict, calls: int):
    from qpth.qp import QPFunction
    config = filter_config_from_params(params)
    filt = SafetyFilter(config.problem)
    rng = np.random.default_rng(0)
    states, proposals = random_inputs(system_name, calls, rng, config.problem)
    mean = np.zeros(config.problem.system.n_x)
    std = np.full(config.problem.system.n_x, 0.02)
    # The QPs every solver sees, built once with the package's builder.
    qps = [config.problem.qp(torch.from_numpy(x)[None], torch.from_numpy(u)[None],
                             torch.from_numpy(mean)[None], torch.from_numpy(std)[None])
           for x, u in zip(states, proposals)]
    ours_total, ours_solve, osqp_solve, z_ours = [], [], [], []
    for x, u in zip(states, proposals):
        res = filt.filter(x, u, mean, std)
        ours_total.append(res.total_time_s)
        ours_solve.append(res.solve_time_s)
        if res.active:  # the QP needed a solve (not the exact z = 0 pass-through)
            osqp_solve.append(res.solve_time_s)
        z_ours.append(res.u_s)
    compiled = SafetyFilter(config.problem, compile_assembly=True)
    compiled_total = [compiled.filter(x, u, mean, std).total_time_s
                      for x, u in zip(states, proposals)]
    setup_every, z_setup = [], []
    for qp in qps:
        P = sp.csc_matrix(qp.P[0].numpy())
        A = sp.csc_matrix(qp.G[0].numpy())
        t0 = time.perf_counter()
        solver = osqp.OSQP()
        solver.setup(P=P, q=qp.q[0].numpy(), A=A, l=np.full(A.shape[0], -np.inf),
                     u=qp.h[0].numpy(), verbose=False, polishing=False, eps_abs=1e-9, eps_rel=1e-9)
        out = solver.solve(raise_error=False)
        setup_every.append(time.perf_counter() - t0)
        z_setup.append(out.x[:-1])
    layer = QPFunction(verbose=-1, eps=1e-10, maxIter=50)
    empty = torch.Tensor().double()
    qpth_times, z_qpth = [], []
    for qp in qps[: min(calls, 500)]:
        t0 = time.perf_counter()
        z = layer(qp.P, qp.q, qp.G, qp.h, empty, empty)
        qpth_times.append(time.perf_counter() - t0)
        z_qpth.append(z[0, :-1].numpy())
    refs = [clarabel_solution(qp)[:-1] for qp in qps[:len(z_qpth)]]
    diff_ours = max(float(np.abs(a - b).max()) for a, b in zip(z_ours, refs))
    diff_qpth = max(float(np.abs(a - b).max()) for a, b in zip(z_qpth, refs))
    slack_active = sum(1 for qp, r in zip(qps, refs) if abs(clarabel_solution(qp)[-1]) > 1e-6)
    med_solve, p99_solve = percentiles(ours_solve)
    rows = []
    for name, samples in [('ours, solve (OSQP update + solve, or z = 0 pass-through)',
                           ours_solve),
                          (f'ours, solve, only the {len(osqp_solve)} calls that ran OSQP',
                           osqp_solve),
                          ('ours, filter() incl. assembly (eager autograd)', ours_total),
                          ('ours, filter() incl. compiled assembly', compiled_total),
                          ('OSQP set up every call', setup_every),
                          ('qpth at batch 1 (reference)', qpth_times)]:
        med, p99 = percentiles(samples)
        rows.append((name, med, p99, med / med_solve))
    accuracy = (f'vs Clarabel on {len(refs)} QPs ({slack_active} with active slack): '
                f'max |u_S - u_S*| ours {diff_ours:.1e}, qpth {diff_qpth:.1e}')
    print(system_name, accuracy)
    return rows, accuracy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=2000)
    parser.add_argument('--no-write', action='store_true', help='do not update RESULTS.md')
    args = parser.parse_args()
    lines = []
    for system_name, params in [('unicycle', unicycle_params()), ('pvtol', pvtol_params())]:
        rows, accuracy = bench(system_name, params, args.calls)
        lines.append(f'\n**{system_name}** ({args.calls} calls at states inside the safe set; '
                     f'accuracy {accuracy})\n')
        lines.append('| solver | median us | p99 us | median / ours-solve |')
        lines.append('|---|---:|---:|---:|')
        lines += [f'| {n} | {m:.1f} | {p:.1f} | {r:.1f}x |' for n, m, p, r in rows]
    table = '\n'.join(lines)
    print(table)
    if not args.no_write:
        from _results import machine_line, write_section
        write_section('Per-step safety filter', (
            'Command: `python benchmarks/bench_filter_step.py`. ' + machine_line() + '.\n'
            + table))


if __name__ == '__main__':
    main()

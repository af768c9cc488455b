"""Per-step safety filter: the three constraint assemblies, and OSQP against the alternatives.

    python benchmarks/bench_filter_step.py [--calls 2000] [--rounds 4] [--cold-calls 300]
        [--no-write] [--reference DIR --reference-python PATH [--reference-calls 400]]

The shipped problems (config/unicycle.yaml, car_following.yaml, pvtol.yaml, the safety_filter
section), then two denser problems (see PROBLEMS), at random
states inside the safe set (every barrier >= 0), proposals uniform in the input box (Car
following, unbounded: in [-5, 5]) and a disturbance box std 0.02. The calls go in --rounds
blocks, each block through the three filters one after the other (consecutive calls on one
filter, as when it filters continuously; the rounds spread the machine's load over the paths):

- closed form: SafetyFilter's default for the built-in problems, the constraint assembly as
  straight-line Python on floats generated for the problem at construction
  (rcbf_ros.core.lie_closed_form), no warm-up;
- autograd: the same filter with closed_form=False, the assembly through torch autograd
  (RCBFProblem.qp), no warm-up;
- compiled: closed_form=False, compile_assembly=True: the autograd assembly traced and
  compiled at construction.

Reported per path: the median and p99 of FilterResult.total_time_s over all calls, the
medians over the calls that passed the proposal through (every row holds at z = 0, no solve),
over those answered by the exact active-set solve (SafetyFilter._active_set: one, two or
three rows active, limits among them; no OSQP) and over those that ran OSQP (where the
active-set solve gave way; each counted by wrapping it), and the median CPU time of the calling
thread (time.thread_time: what the call itself consumed, less sensitive to the machine's load
than the wall time, though cores shared with other work still slow it). For the closed form,
the call split in stages: the assembly (timed per call by wrapping it); solve =
FilterResult.solve_time_s, i.e. the active-set solve (and, where it gave way, OSQP update +
solve) + the row check, or on a pass-through the result at z = 0 (where the row check holds by
construction), with OSQP's own C timers of update and solve; the rest = input checks,
clipping, the data check and the result.
Then the closed-form call with cold caches: before each of --cold-calls calls a 64 MB buffer
is written (untimed), as a SAC update or the rest of a ROS node evicts the last-level cache
between two filter calls, and the same call is repeated at once (warm) for the comparison.
Then the solver alone against a new OSQP per call and qpth at batch 1, with the
accuracy of each against Clarabel.

Reference (``--reference DIR``, the authors' Mod-RL-RCBF tree; its venv as described in
benchmarks/bench_training.py): for the three shipped systems, its per-step filter re-run in a
subprocess after each block of ours (ours, reference, ours, reference, ...), 1 thread each. The
driver (benchmarks/_reference.py) runs its own main.py with random actions and no SAC update
(``--start_steps`` and ``--batch_size`` beyond the run) and times every batch-1 call of its
``CBFQPLayer.get_safe_action``: its constraint assembly in torch, the row normalisation and
qpth with its own settings (eps 1e-4, maxIter 100000, notImprovedLim 10), then the clamp; the
GP prediction before it is not included (nor is ours). Its states are those its environment
visits under random actions (ours: random states in the safe set), its obstacles its own.
Without ``--reference`` the comparison is skipped.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import os
import sys
import time
from typing import Callable

from _problems import pvtol_params, unicycle_params
from _reference import (
    add_reference_arguments,
    ENV_NAMES,
    reference_requested,
    ReferenceError,
    run_reference,
)
import numpy as np
import osqp
import scipy.sparse as sp
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.parameters.rules import find_config, load_params

torch.set_num_threads(1)


PATHS = ('closed form', 'autograd', 'compiled')
CAR_PROPOSAL = 5.0
"""|u| bound of the Car following proposals (its input is unbounded; the nominal controller
accelerates at 5 m/s^2)."""
PATHS_DIFFER = (
    'What differs between the paths: only the constraint assembly (h, grad h, L_f h, L_g h, '
    'the robust margin and the QP rows); the input checks, clipping, the solve and the row '
    'check '
    "are the same code. Closed form: one generated Python function of the state on floats, "
    "from each family's quadratic coefficients (or the look-ahead circle's formula) and the "
    "system's f, J, g, constants folded in, no warm-up. Autograd: RCBFProblem.qp in torch, "
    'one autograd pass per family (a double one '
    'through each cascade), no warm-up. Compiled: that autograd graph traced and compiled at '
    'construction (its seconds per system below). The QP data agree to round-off; OSQP '
    "answers then agree to round-off (active set) or OSQP's tolerance (differences below), "
    "and a call near the row check's "
    'threshold can go to the interior-point fallback on one path and not the other.')
"""Printed with the tables."""
STAGES = {'rest': 'input checks, clip, data check, result',
          'assembly': 'constraint assembly (closed form)',
          'solve': 'solve + row check (pass-through: the result at z = 0; active set: the '
                   'exact solve)',
          'osqp update': 'of which OSQP update, C timer',
          'osqp solve': 'of which OSQP solve, C timer'}
"""The stages of a closed-form call (module docstring)."""
KINDS = ('pass', 'active set', 'osqp')
"""How a call was answered: pass-through, the exact active-set solve, OSQP (module docstring)."""
TARGET_US = 50.0
"""The per-call budget the closed form is measured against (median of all calls)."""
REFERENCE_QPS = 300
"""QPs solved by the slow references (qpth, Clarabel)."""


def _unicycle_arena(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.stack([rng.uniform(-3.0, 3.0, n), rng.uniform(-3.0, 3.0, n),
                     rng.uniform(-np.pi, np.pi, n)], 1)


def _pvtol_arena(n: int, rng: np.random.Generator) -> np.ndarray:
    """Inside the arena, thrust and tilt bands, the operator within the band or near it."""
    x1 = rng.uniform(-5.5, 5.5, n)
    return np.stack([x1, rng.uniform(-2.5, 2.5, n), rng.normal(0, 0.5, n), rng.normal(0, 0.5, n),
                     rng.normal(0, 0.2, n), rng.uniform(0.6, 1.4, n),
                     x1 + rng.uniform(-0.5, 0.5, n)], 1)


def _cars_platoon(n: int, rng: np.random.Generator) -> np.ndarray:
    positions = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + rng.normal(0.0, 1.0, (n, 5))
    velocities = 30.0 + rng.normal(0.0, 2.0, (n, 5))
    return np.stack([positions, velocities], axis=2).reshape(n, 10)


def _unicycle_ring(n: int, rng: np.random.Generator) -> np.ndarray:
    """States inside a ring of 8 obstacles."""
    r, a = rng.uniform(0.3, 1.5, n), rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-np.pi, np.pi, n)], 1)


def _pvtol_centre(n: int, rng: np.random.Generator) -> np.ndarray:
    """States near the origin, hovering."""
    return np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), rng.normal(0, 0.5, (n, 2)),
                           rng.normal(0, 0.2, (n, 1)), rng.uniform(0.8, 1.2, (n, 1)),
                           rng.uniform(-0.3, 0.3, (n, 1))], 1)


def _shipped(system_name: str) -> Callable[[], dict]:
    return lambda: load_params(find_config(system_name), 'safety_filter')


Sampler = Callable[[int, np.random.Generator], np.ndarray]
PROBLEMS: tuple[tuple[str, Sampler, Callable[[], dict]], ...] = (
    ('unicycle', _unicycle_arena, _shipped('unicycle')),
    ('car_following', _cars_platoon, _shipped('car_following')),
    ('pvtol', _pvtol_arena, _shipped('pvtol')),
    ('unicycle-8 ring', _unicycle_ring, unicycle_params),
    ('pvtol-9 hover', _pvtol_centre, pvtol_params),
)
"""(label, state sampler, flat parameters): the shipped configs, then two denser
problems (benchmarks/_problems.py: a ring of 8 obstacles; 9
obstacles and the quadratic operator band, without the envelope)."""


def random_inputs(sampler: Sampler, problem, n: int, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
    """n states inside the safe set and n proposals in the input box."""
    states = np.zeros((0, problem.system.n_x))
    while len(states) < n:
        candidates = sampler(4 * n, rng)
        h = problem.state_h(torch.from_numpy(candidates)).numpy()
        states = np.concatenate([states, candidates[(h >= 0).all(axis=1)]])[:n]
    system = problem.system
    if system.u_min is None:
        proposals = rng.uniform(-CAR_PROPOSAL, CAR_PROPOSAL, (n, system.n_u))
    else:
        proposals = rng.uniform(system.u_min, system.u_max, (n, system.n_u))
    return states, proposals


def _us(samples) -> np.ndarray:
    return 1e6 * np.asarray(samples, dtype=np.float64)


def _median(samples) -> str:
    return f'{np.median(_us(samples)):.1f}' if len(samples) else '-'


class _TimedAssembly:
    """Wraps a filter's assembly and keeps the wall time of its last call."""

    def __init__(self, assembly) -> None:
        self.assembly = assembly
        self.last = 0.0

    def __call__(self, *args):
        start = time.perf_counter()
        out = self.assembly(*args)
        self.last = time.perf_counter() - start
        return out


class _CountedActiveSet:
    """Wraps a filter's active-set solve and counts the calls it answered."""

    def __init__(self, active_set) -> None:
        self.active_set = active_set
        self.answered = 0

    def __call__(self, *args, **kwargs):
        z = self.active_set(*args, **kwargs)
        self.answered += z is not None
        return z


class _CountedSolve:
    """Wraps a filter's OSQP solve and counts its calls (a pass-through makes none)."""

    def __init__(self, solver) -> None:
        self.solve = solver.solve
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.solve(*args, **kwargs)


def bench_paths(problem, states, proposals, mean, std, rounds: int,
                after_block: Callable[[], None] = lambda: None) -> dict:
    """The calls in ``rounds`` blocks; each block on the three filters one after the other
    (warm caches within a block, the load shared between paths across the rounds), then
    ``after_block()`` (the reference's block, when compared)."""
    started = time.perf_counter()
    compiled = SafetyFilter(problem, closed_form=False, compile_assembly=True)
    compile_s = time.perf_counter() - started
    filters = {'closed form': SafetyFilter(problem),
               'autograd': SafetyFilter(problem, closed_form=False),
               'compiled': compiled}
    assert filters['closed form'].assembly == 'closed_form'
    assert filters['autograd'].assembly == 'autograd'
    assert compiled.assembly == 'compiled'
    timer = _TimedAssembly(filters['closed form']._assemble)
    filters['closed form']._assemble = timer
    solves = {path: _CountedSolve(filt._solver) for path, filt in filters.items()}
    active_sets = {path: _CountedActiveSet(filt._active_set) for path, filt in filters.items()}
    for path, filt in filters.items():
        filt._solver.solve = solves[path]
        filt._active_set = active_sets[path]
    totals = {path: [] for path in PATHS}
    cpu = {path: [] for path in PATHS}
    # how each call was answered: pass-through, the exact active-set solve, OSQP
    answered = {kind: {path: [] for path in PATHS} for kind in KINDS}
    # stage -> calls: all, and by how they were answered; OSQP's own C timers where it ran
    stages = {stage: {'all': [], **{kind: [] for kind in KINDS}} for stage in STAGES}
    iterations = []
    osqp_info = filters['closed form']._solver._ext.info
    results = {path: [] for path in PATHS}
    for block in np.array_split(np.arange(len(states)), rounds):
        for path, filt in filters.items():
            for i in block:
                calls, exact = solves[path].calls, active_sets[path].answered
                cpu_start = time.thread_time()
                res = filt.filter(states[i], proposals[i], mean, std)
                cpu[path].append(time.thread_time() - cpu_start)
                ran = solves[path].calls > calls
                kind = ('osqp' if ran else 'active set' if active_sets[path].answered > exact
                        else 'pass')
                results[path].append(res)
                totals[path].append(res.total_time_s)
                answered[kind][path].append(res.total_time_s)
                if path != 'closed form':
                    continue
                split = {'assembly': timer.last, 'solve': res.solve_time_s,
                         'rest': res.total_time_s - timer.last - res.solve_time_s}
                if ran:
                    split.update({'osqp update': osqp_info.update_time,
                                  'osqp solve': osqp_info.solve_time})
                    iterations.append(osqp_info.iter)
                for stage, value in split.items():
                    stages[stage]['all'].append(value)
                    stages[stage][kind].append(value)
        after_block()
    pairs = list(zip(results['closed form'], results['autograd']))
    return {'totals': totals, 'cpu': cpu, 'answered': answered,
            'stages': stages, 'iterations': iterations, 'compile_s': compile_s,
            'worst_action': max(float(np.max(np.abs(a.u_safe - b.u_safe))) for a, b in pairs),
            'worst_h': max(float(np.max(np.abs(a.h - b.h))) for a, b in pairs)}


COLD_BUFFER_BYTES = 64 * 2 ** 20
"""Written before each cold call: more than the last-level cache of the machines measured."""


def bench_cold(problem, states, proposals, mean, std, calls: int) -> tuple[list, list]:
    """The closed-form filter's whole call (total_time_s) with the caches flushed before it
    (a 64 MB buffer written, untimed), and the same call repeated at once (warm)."""
    filt = SafetyFilter(problem)
    flush = np.zeros(COLD_BUFFER_BYTES // 8)
    cold, warm = [], []
    for i in range(min(calls, len(states))):
        np.add(flush, 1.0, out=flush)
        cold.append(filt.filter(states[i], proposals[i], mean, std).total_time_s)
        warm.append(filt.filter(states[i], proposals[i], mean, std).total_time_s)
    return cold, warm


def clarabel_solution(qp) -> np.ndarray:
    """Independent reference: the same QP through cvxpy + Clarabel (interior point, float64)."""
    import cvxpy as cp
    P, q, G, h = (t[0].numpy() for t in qp)
    z = cp.Variable(P.shape[0])
    cp.Problem(cp.Minimize(0.5 * cp.quad_form(z, P) + q @ z), [G @ z <= h]).solve(
        solver='CLARABEL')
    return z.value


def bench_solvers(problem, states, proposals, mean, std) -> tuple[list, str]:
    """The filter's solve as it runs it against a new OSQP per call and qpth at batch 1."""
    from qpth.qp import QPFunction
    filt = SafetyFilter(problem)
    qps = [problem.qp(torch.from_numpy(x)[None], torch.from_numpy(u)[None],
                      torch.from_numpy(mean)[None], torch.from_numpy(std)[None])
           for x, u in zip(states, proposals)]
    ours, ours_osqp, z_ours = [], [], []
    for x, u in zip(states, proposals):
        res = filt.filter(x, u, mean, std)
        ours.append(res.solve_time_s)
        if res.active:
            ours_osqp.append(res.solve_time_s)
        z_ours.append(res.u_s)
    setup_every = []
    for qp in qps:
        P = sp.csc_matrix(qp.P[0].numpy())
        A = sp.csc_matrix(qp.G[0].numpy())
        t0 = time.perf_counter()
        solver = osqp.OSQP()
        solver.setup(P=P, q=qp.q[0].numpy(), A=A, l=np.full(A.shape[0], -np.inf),
                     u=qp.h[0].numpy(), verbose=False, polishing=False, eps_abs=1e-9,
                     eps_rel=1e-9)
        solver.solve(raise_error=False)
        setup_every.append(time.perf_counter() - t0)
    layer = QPFunction(verbose=-1, eps=1e-10, maxIter=50)
    empty = torch.Tensor().double()
    qpth_times, z_qpth = [], []
    for qp in qps[:REFERENCE_QPS]:
        t0 = time.perf_counter()
        z = layer(qp.P, qp.q, qp.G, qp.h, empty, empty)
        qpth_times.append(time.perf_counter() - t0)
        z_qpth.append(z[0, :-1].numpy())
    refs = [clarabel_solution(qp) for qp in qps[:len(z_qpth)]]
    diff_ours = max(float(np.abs(a - r[:-1]).max()) for a, r in zip(z_ours, refs))
    diff_qpth = max(float(np.abs(a - r[:-1]).max()) for a, r in zip(z_qpth, refs))
    slack_active = sum(1 for r in refs if abs(r[-1]) > 1e-6)
    rows = [("the filter's solve and row check: the exact active-set solve (OSQP update + "
             'solve where it gives way), or the result at z = 0 (pass-through)', ours),
            (f'the same, only the {len(ours_osqp)} calls that corrected the proposal',
             ours_osqp),
            ('a new OSQP set up every call', setup_every),
            ('qpth at batch 1 (eps 1e-10, maxIter 50)', qpth_times)]
    accuracy = (f'vs Clarabel on {len(refs)} QPs ({slack_active} with active slack): max '
                f'|u_S - u_S*| ours {diff_ours:.1e}, qpth {diff_qpth:.1e}')
    return rows, accuracy


def reference_line(compared: list[str]) -> str:
    """What the reference rows say, or that the comparison was skipped."""
    if not compared:
        return 'Reference comparison skipped (no --reference DIR).'
    return ("Reference (the authors' per-step filter, re-run after each block of ours): its "
            'median call over our closed-form median: ' + '; '.join(compared) + '. What '
            'differs: it assembles the QP in torch and solves it with qpth (interior point, '
            'eps 1e-4, rows normalised) on the states its environment visits under random '
            'actions, with its own obstacles; ours assembles in closed form and solves '
            'exactly with the active-set method (warm-started OSQP where it gives way) on '
            'random states inside the safe set. Neither includes the GP prediction.')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=2000)
    parser.add_argument('--rounds', type=int, default=4,
                        help='blocks of calls, each on the three filters in turn')
    parser.add_argument('--no-write', action='store_true', help='do not update RESULTS.md')
    add_reference_arguments(parser)
    parser.add_argument('--cold-calls', type=int, default=300,
                        help='closed-form calls with the caches flushed before each, per system')
    parser.add_argument('--reference-calls', type=int, default=400,
                        help="the reference's filter calls per system (split over the rounds)")
    args = parser.parse_args()
    reference_requested(parser, args, minimums=[
        (args.reference_calls, args.rounds, '--reference-calls: at least one call per round')])
    compared = []
    load_before = os.getloadavg()
    summary = ['| system | path | median us (all) | p99 us | median us, pass-through (n) '
               '| median us, active set (n) | median us, OSQP ran (n) | median CPU us |',
               '|---|---|---:|---:|---:|---:|---:|---:|']
    breakdown = ['| system | stage | median us, all calls | pass-through | active set '
                 '| OSQP ran |', '|---|---|---:|---:|---:|---:|']
    details = []
    cold_rows = ['| system | median us, warm | median us, cold | p90 us, cold | calls |',
                 '|---|---:|---:|---:|---:|']
    target = []
    for label, sampler, params in PROBLEMS:
        problem = filter_config_from_params(params()).problem
        rng = np.random.default_rng(0)
        states, proposals = random_inputs(sampler, problem, args.calls, rng)
        mean = np.zeros(problem.system.n_x)
        std = np.full(problem.system.n_x, 0.02)
        reference_calls: list[tuple[float, float]] = []

        def reference_block(system: str = label,
                            calls: list[tuple[float, float]] = reference_calls) -> None:
            if args.reference is None or system not in ENV_NAMES:
                return
            out = run_reference(directory=args.reference, python=args.reference_python,
                                system=system, mode='baseline', warmup=0,
                                steps=args.reference_calls // args.rounds, filter_only=True,
                                seed=12345 + len(calls))  # each block from another start
            calls.extend(out['filter_calls'])

        try:
            out = bench_paths(problem, states, proposals, mean, std, args.rounds,
                              after_block=reference_block)
        except ReferenceError as exc:
            sys.exit(f'bench_filter_step: {exc}')
        for path in PATHS:
            totals = out['totals'][path]
            summary.append(
                f'| {label} | {path} | {_median(totals)} '
                f'| {np.percentile(_us(totals), 99):.1f} '
                + ''.join(f'| {_median(out["answered"][kind][path])} '
                          f'({len(out["answered"][kind][path])}) '
                          for kind in KINDS)
                + f'| {_median(out["cpu"][path])} |')
        if reference_calls:
            wall = [w for w, _ in reference_calls]
            summary.append(f'| {label} | reference: qpth at batch 1 | {_median(wall)} '
                           f'| {np.percentile(_us(wall), 99):.1f} | - | - | - '
                           f'| {_median([c for _, c in reference_calls])} |')
            ours_median = float(np.median(_us(out['totals']['closed form'])))
            compared.append(f'{label} {np.median(_us(wall)) / ours_median:.0f}x '
                            f'({len(wall)} reference calls)')
        median = float(np.median(_us(out['totals']['closed form'])))
        target.append(f'{label} {median:.1f} us ({"within" if median <= TARGET_US else "over"})')
        iterations = out['iterations']
        for stage, stage_name in STAGES.items():
            if stage == 'osqp solve' and iterations:
                stage_name += f' ({np.median(iterations):.0f} iterations)'
            times = out['stages'][stage]
            breakdown.append(f'| {label} | {stage_name} | {_median(times["all"])} '
                             + ''.join(f'| {_median(times[kind])} ' for kind in KINDS) + '|')
        cold, warm = bench_cold(problem, states, proposals, mean, std, args.cold_calls)
        cold_rows.append(f'| {label} | {_median(warm)} | {_median(cold)} '
                         f'| {np.percentile(_us(cold), 90):.1f} | {len(cold)} |')
        rows, accuracy = bench_solvers(problem, states, proposals, mean, std)
        details.append(
            f'\n**{label}** ({args.calls} calls; K = {problem.n_barriers} barrier rows; '
            f'compile at construction {out["compile_s"]:.1f} s; closed form vs autograd: max '
            f'|u_safe difference| {out["worst_action"]:.1e}, max |h difference| '
            f'{out["worst_h"]:.1e}; solver accuracy {accuracy})\n')
        details.append('| solver, closed-form filter | median us | p99 us |')
        details.append('|---|---:|---:|')
        details += [f'| {name} | {_median(s)} | {np.percentile(_us(s), 99):.1f} |'
                    for name, s in rows]
        print(label, 'done', flush=True)
    load_after = os.getloadavg()
    from _results import load_before_after
    load = load_before_after(load_before, load_after) + ' (2 cores).'
    table = '\n'.join(['Whole SafetyFilter.filter() call (FilterResult.total_time_s), '
                       f'{args.calls} calls per system:', '', *summary, '',
                       f'Closed form against the {TARGET_US:.0f} us target (median of all '
                       f'calls): {"; ".join(target)}.', '',
                       reference_line(compared), '',
                       'The closed-form call in stages:', '', *breakdown, '',
                       'The closed-form call with cold caches (a 64 MB buffer written before '
                       'each call), and the same call repeated at once:', '', *cold_rows, '',
                       load, '',
                       PATHS_DIFFER, *details])
    print(table)
    if not args.no_write:
        from _results import machine_line, write_section
        write_section('Per-step safety filter', (
            f'Command: `python benchmarks/bench_filter_step.py --calls {args.calls} --rounds '
            f'{args.rounds} --cold-calls {args.cold_calls}'
            + (' --reference <Mod-RL-RCBF checkout> --reference-python '
               '<its venv>/bin/python --reference-calls '
               f'{args.reference_calls}' if args.reference else '') + '`. '
            + machine_line() + '.\n\n' + table))


if __name__ == '__main__':
    main()

"""``rcbf_ros experiment``: train (resumably), evaluate and report one experiment or all.

    rcbf_ros experiment transfer --budget smoke --seeds 1 --out runs/experiments
    rcbf_ros experiment all --budget paper --seeds 10 --ray --num-cpus 8
    rcbf_ros experiment sample_efficiency --budget paper --seeds 10 --address ray://head:10001

Outputs: ``<out>/<budget>/<system>/<method>/seed<k>/`` per run (as ``rcbf_ros train``: metrics,
checkpoint, policy, MCAP bag, plus ``summary.json`` and cached transfer evaluations) and
``<out>/<budget>/report/`` (CSV, PNG, markdown; see rcbf_ros.experiments.report).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import json
from pathlib import Path
import shlex
import signal
import sys
import time
from typing import Any, Callable, Sequence

import torch

from rcbf_ros.experiments.definitions import (
    Budget,
    BUDGETS,
    experiment_methods,
    experiment_names,
    experiment_runs,
    METHODS,
    POLICY_BOXES,
    RunSpec,
)
from rcbf_ros.experiments.runner import (
    Backend,
    ClusterError,
    parallel_map,
    run_all,
    select_backend,
)


@dataclass(frozen=True)
class ExperimentRequest:
    """Everything one ``rcbf_ros experiment`` call does."""

    name: str
    """sample_efficiency | transfer | value_maps | all."""
    budget: Budget
    """Budget after command-line overrides."""
    seeds: int
    """Seeds per configuration."""
    out: str
    """Root output directory."""
    first_seed: int = 0
    """Seeds are first_seed .. first_seed + seeds - 1."""
    systems: tuple[str, ...] | None = None
    """Restrict to these systems (None: every system of the experiment)."""
    methods: tuple[str, ...] | None = None
    """Restrict to these methods (None: every method of the experiment); the report then
    covers only them."""
    gp: str = 'learned'
    """Transfer filter's disturbance estimate: the run's GP ('learned') or the prior."""
    report: bool = True
    """Write the report after training (false: train and evaluate only)."""


def plan_runs(request: ExperimentRequest) -> list[RunSpec]:
    """The request's training runs (seeds shifted, systems filtered).

    Raises:
        ValueError: naming ``methods`` when a method is unknown or the filters leave no run.
    """
    specs = experiment_runs(request.name, request.budget, request.seeds,
                            optional=request.methods or ())
    if request.first_seed:
        specs = [RunSpec(s.system, s.method, s.seed + request.first_seed, s.budget)
                 for s in specs]
    if request.systems is not None:
        specs = [s for s in specs if s.system in request.systems]
    if request.methods is not None:
        unknown = sorted(set(request.methods) - set(METHODS))
        if unknown:
            raise ValueError(f'methods: unknown {unknown}, expected some of {sorted(METHODS)}')
        specs = [s for s in specs if s.method in request.methods]
    if not specs:
        raise ValueError(f'methods: {list(request.methods or ())} on systems '
                         f'{list(request.systems or ())} select no run of {request.name!r} '
                         '(e.g. modular_envelope is offered on PVTOL transfer only)')
    return specs


def _specs_of(experiment: str, specs: Sequence[RunSpec]) -> list[RunSpec]:
    everything = tuple(METHODS)
    return [s for s in specs if s.method in experiment_methods(experiment, s.system, everything)]


def run_experiment(request: ExperimentRequest, *, backend: Backend = 'sequential',
                   address: str | None = None, num_cpus: int | None = None,
                   command: str = '', log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train what is missing, evaluate transfer, compute value maps, write the report.

    Returns a dict with the run summaries, the report directory and the wall time.
    """
    from rcbf_ros.experiments import report
    torch.set_num_threads(1)
    start = time.perf_counter()
    specs = plan_runs(request)
    root = Path(request.out)
    summaries = run_all(specs, root, backend=backend, address=address, num_cpus=num_cpus,
                        log=log)
    report_dir = root / request.budget.name / 'report'
    report_dir.mkdir(parents=True, exist_ok=True)
    experiments = experiment_names(request.name)
    transfer_results: dict[RunSpec, list[dict[str, Any]]] = {}
    if 'transfer' in experiments:
        transfer_specs = _specs_of('transfer', specs)
        seeds = tuple(range(request.budget.layouts))
        jobs = [(str(s.run_dir(root)), seeds, request.budget.eval_max_steps.get(s.system),
                 request.gp) for s in transfer_specs]
        log(f'evaluating {len(jobs)} policies on {len(seeds)} layouts')
        from rcbf_ros.experiments.evaluate import evaluate_job
        for spec, rows in zip(transfer_specs, parallel_map(
                evaluate_job, jobs, backend=backend, address=address, num_cpus=num_cpus)):
            transfer_results[spec] = rows
    wall = time.perf_counter() - start
    if request.report:
        if 'sample_efficiency' in experiments:
            report.sample_efficiency_report(_specs_of('sample_efficiency', specs), root,
                                            report_dir)
        if transfer_results:
            report.sample_efficiency_report(
                list(transfer_results), root, report_dir, prefix='transfer_training',
                heading='Training curves of the transfer runs')
            report.transfer_report(transfer_results, report_dir, layouts=request.budget.layouts,
                                   eval_max_steps=request.budget.eval_max_steps)
            report.transfer_paths_report(list(transfer_results), root, report_dir,
                                         layouts=request.budget.layouts,
                                         eval_max_steps=request.budget.eval_max_steps,
                                         gp=request.gp)
        if 'value_maps' in experiments:
            map_specs = _specs_of('value_maps', specs)
            if map_specs:
                from rcbf_ros.experiments.evaluate import load_trained_learner
                from rcbf_ros.experiments.value_map import value_map
                seed = min(s.seed for s in map_specs)
                maps = {}
                for spec in map_specs:
                    if spec.seed == seed:
                        _, learner = load_trained_learner(spec.run_dir(root))
                        maps[spec.method] = value_map(learner, grid=request.budget.value_map_grid)
                report.value_maps_report(maps, report_dir, seed=seed)
        train_wall = sum(float(s.get('wall_s', 0.0)) for s in summaries)
        header = '\n'.join([
            f'# Experiment report: {request.name} (budget {request.budget.name})', '',
            f'Command: `{command}`' if command else '',
            f'Seeds: {request.first_seed} .. {request.first_seed + request.seeds - 1}; runs: '
            f'{len(specs)}; training wall time of the runs (as recorded when they were '
            f'trained): {train_wall:.0f} s; this call: {wall:.0f} s.', ''])
        report.write_report_md(report_dir, header)
        (report_dir / 'summaries.json').write_text(json.dumps(summaries, indent=2))
    return {'summaries': summaries, 'report_dir': str(report_dir), 'wall_s': wall}


# --------------------------------------------------------------------------- command line
def add_experiment_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rcbf_ros experiment``."""
    parser.add_argument('name', choices=['sample_efficiency', 'transfer', 'value_maps', 'all'])
    parser.add_argument('--budget', default='smoke', choices=sorted(BUDGETS))
    parser.add_argument('--seeds', type=int, default=1, help='seeds per configuration')
    parser.add_argument('--first-seed', type=int, default=0, help='first seed (default 0)')
    parser.add_argument('--out', default='runs/experiments', help='root output directory')
    parser.add_argument('--systems', nargs='+', default=None,
                        choices=['unicycle', 'car_following', 'pvtol'],
                        help='only these systems')
    parser.add_argument('--methods', nargs='+', default=None, choices=sorted(METHODS),
                        help='only these methods (e.g. modular)')
    parser.add_argument('--episodes', type=int, default=None, help='override: episodes')
    parser.add_argument('--max-steps', type=int, default=None,
                        help='override: training episode length')
    parser.add_argument('--eval-max-steps', type=int, default=None,
                        help='override: transfer episode length')
    parser.add_argument('--layouts', type=int, default=None, help='override: transfer layouts')
    parser.add_argument('--gp', default='learned', choices=['learned', 'prior'],
                        help="transfer filter's disturbance estimate")
    parser.add_argument('--policy-box', default=None, choices=POLICY_BOXES,
                        help="override: the policy's proposal box; config: the config file's "
                             "/learner policy_limits (default), inputs: the input limits "
                             "(the reference's; the Unicycle may then propose reversing)")
    parser.add_argument('--no-bag', action='store_true', help='do not record MCAP')
    parser.add_argument('--no-report', action='store_true', help='train/evaluate only')
    parser.add_argument('--ray', action='store_true', help='run as Ray tasks (optional ray)')
    parser.add_argument('--address', default=None, help='existing Ray cluster address')
    parser.add_argument('--num-cpus', type=int, default=None,
                        help='CPUs of a local Ray instance')


def run_experiment_command(args: argparse.Namespace, argv: Sequence[str] | None = None) -> int:
    """``rcbf_ros experiment``; 0 on success, 2 on bad arguments, 1 when a file of a run
    cannot be written (a full disk: one line; the finished runs are kept), 130 on Ctrl-C."""
    try:
        budget = BUDGETS[args.budget].with_overrides(
            episodes=args.episodes, max_steps=args.max_steps, eval_max_steps=args.eval_max_steps,
            layouts=args.layouts, record_bag=False if args.no_bag else None,
            policy_box=args.policy_box)
        request = ExperimentRequest(
            name=args.name, budget=budget, seeds=args.seeds, out=args.out,
            first_seed=args.first_seed, systems=tuple(args.systems) if args.systems else None,
            methods=tuple(args.methods) if args.methods else None,
            gp=args.gp, report=not args.no_report)
        if args.first_seed < 0:
            raise ValueError(f'--first-seed: must be >= 0, got {args.first_seed}')
        if args.num_cpus is not None and args.num_cpus < 1:
            raise ValueError(f'--num-cpus: must be >= 1, got {args.num_cpus}')
        plan_runs(request)
        backend = select_backend(use_ray=args.ray, address=args.address,
                                 log=lambda line: print(line, file=sys.stderr))
    except (ValueError, RuntimeError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    command = 'rcbf_ros ' + shlex.join(list(argv)) if argv is not None else \
        'rcbf_ros ' + shlex.join(sys.argv[1:])
    from rcbf_ros.bag.interrupts import interrupts_raise
    try:  # Ctrl-C as Python's, but never halfway through a bag write
        with interrupts_raise(signal.SIGINT):
            result = run_experiment(request, backend=backend, address=args.address,
                                    num_cpus=args.num_cpus, command=command,
                                    log=lambda line: print(line, flush=True))
    except ClusterError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:  # a run's file not written (a full disk): the runs done are kept
        print(f'error: {" ".join(str(exc).split())}; finished runs are kept; run the same '
              'command again to resume', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('interrupted: finished runs are kept; run the same command again to resume',
              file=sys.stderr)
        return 130
    print(json.dumps({'report_dir': result['report_dir'], 'wall_s': round(result['wall_s'], 1),
                      'runs': len(result['summaries'])}, indent=2))
    return 0

"""``rcbf_ros train``: train in-process (no middleware), one run of one system and mode.

    rcbf_ros train --system unicycle --mode modular --seed 0 --episodes 50
    rcbf_ros train --system unicycle --mode diff --model-based --episodes 50
    rcbf_ros train --system unicycle --mode unconstrained --no-obstacles
    rcbf_ros train ... --resume            # continue a killed run from its checkpoint
"""
from __future__ import annotations

import argparse
from dataclasses import fields
import json
from pathlib import Path
import signal
import sys

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.messages import systems
from rcbf_ros.training.agent import LearnerConfig, MODES
from rcbf_ros.training.run_files import DEFAULT_CHECKPOINT_EVERY


def _learner_overrides(args: argparse.Namespace) -> dict:
    """The :class:`LearnerConfig` fields given on the command line (None: not given)."""
    names = {f.name for f in fields(LearnerConfig)}
    return {k: v for k, v in vars(args).items() if k in names and v is not None}


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rcbf_ros train``."""
    parser.add_argument('--system', default='unicycle', choices=systems.system_names())
    parser.add_argument('--mode', default='modular', choices=MODES)
    parser.add_argument('--model-based', dest='model_based', action='store_true', default=None,
                        help='MB SAC-RCBF: synthetic k-step rollouts (mode diff)')
    parser.add_argument('--modular-envelope', dest='modular_envelope',
                        action=argparse.BooleanOptionalAction, default=None,
                        help="modular: keep the envelope's correction (bands not marked "
                        "'layout: true') in the losses, as the authors' PVTOL code (default: "
                        "the config file's /learner modular_envelope; config/pvtol.yaml sets it)")
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--episodes', type=int, default=20)
    parser.add_argument('--max-steps', type=int, default=None, help='episode length override')
    parser.add_argument('--config', default=None, help='ROS params file (default: packaged)')
    parser.add_argument('--out', default=None, help='output directory (default: runs/<name>)')
    parser.add_argument('--no-obstacles', action='store_true',
                        help='train without obstacles and filter (transfer upper bound)')
    parser.add_argument('--no-bag', action='store_true', help='do not record MCAP')
    parser.add_argument('--resume', action='store_true',
                        help='continue the run in --out from its checkpoint (none: start at '
                             'episode 0, keeping its files); without it an existing run is '
                             'refused')
    parser.add_argument('--checkpoint-every', dest='checkpoint_every', type=int,
                        default=DEFAULT_CHECKPOINT_EVERY, metavar='N',
                        help='episodes between checkpoints (a kill loses at most the episodes '
                             'since the last one; default %(default)s)')
    parser.add_argument('--compile-filter', action='store_true',
                        help='compile the per-step autograd constraint assembly of a system or '
                             'barrier without a closed form (faster, slower start)')
    parser.add_argument('--compile-update', dest='compile_update', action='store_true',
                        help='compile the SAC update: without a safety layer in the losses '
                             'as one graph (about 1.6x faster per update); where they pass it '
                             '(diff; modular with an envelope) its network parts, the layer '
                             'eager between them (training steps 1.1-1.25x faster); a one-off '
                             "compile of tens of seconds, seconds once torch's compile cache "
                             'has it')
    parser.add_argument('--threads', type=int, default=1,
                        help='torch threads (2 speeds SAC updates 1.2-1.7x on an idle 2-core '
                             'machine; 1 when runs or nodes share the cores)')
    parser.add_argument('--random-start', dest='random_start', action='store_true',
                        default=None, help="random episode starts (default: the config's)")
    parser.add_argument('--initial-alpha', dest='initial_alpha', type=float, default=None,
                        help="SAC's initial entropy temperature (default: the config's "
                             'learner initial_alpha, else 0.2)')
    parser.add_argument('--start-steps', dest='start_steps', type=int, default=None)
    parser.add_argument('--update-after', dest='update_after', type=int, default=None)
    parser.add_argument('--batch-size', dest='batch_size', type=int, default=None)
    parser.add_argument('--gp-refit-interval', dest='gp_refit_interval', type=int,
                        default=None)


def run_train(args: argparse.Namespace) -> int:
    """Run ``rcbf_ros train``: 0, 2 on bad arguments, output directory or checkpoint, 1 when a
    file of the run cannot be written (a full disk: the bag closed, the previous checkpoint
    kept), 130 on Ctrl-C or SIGTERM (checkpoint, bag and plot written)."""
    from rcbf_ros.training.build import RunConfig, RunSetupError
    from rcbf_ros.training.loop import check_out_dir, train
    from rcbf_ros.training.progress import summarize
    from rcbf_ros.training.run_files import RunWriteError
    try:
        learner = LearnerConfig(**_learner_overrides(args),
                                sac=SACConfig(initial_alpha=args.initial_alpha,
                                              compile_update=args.compile_update))
    except (TypeError, ValueError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    name = f"{args.system}_{args.mode}{'_mb' if args.model_based else ''}_s{args.seed}"
    run = RunConfig(system=args.system, episodes=args.episodes,
                    out_dir=args.out or str(Path('runs') / name), config_file=args.config,
                    max_steps=args.max_steps, no_obstacles=args.no_obstacles,
                    random_start=args.random_start,
                    record_bag=not args.no_bag, resume=args.resume,
                    checkpoint_every=args.checkpoint_every,
                    compile_filter=args.compile_filter, threads=args.threads, learner=learner)
    try:
        check_out_dir(run)
    except RunSetupError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    print(f'training {name}: {args.episodes} episodes -> {run.out_dir}', flush=True)
    if args.compile_update:
        print('--compile-update: the first SAC update compiles (tens of seconds the first time, '
              "seconds once torch's compile cache has it)", flush=True)

    def on_sigterm(signum: int, frame: object) -> None:
        raise KeyboardInterrupt  # same path as Ctrl-C: checkpoint, bag and plot are written

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        history = train(run, log=lambda line: print(line, flush=True))
    except RunSetupError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except RunWriteError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'interrupted: checkpoint and partial results are in {run.out_dir}',
              file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    summary = summarize(history)
    summary['out_dir'] = run.out_dir
    print(json.dumps(summary, indent=2))
    return 0

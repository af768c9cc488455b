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
import signal
import sys
import typing
from typing import Any

from rcbf_ros.messages import systems
from rcbf_ros.parameters.reader import ParameterError, read_parameters
from rcbf_ros.training.settings import MODES, TrainingSettings

OPTIONS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ('system', '--system', {}),   # choices: the table's names when the parser is built
    ('mode', '--mode', dict(choices=MODES)),
    ('model_based', '--model-based', dict(
        action='store_true', help='MB SAC-RCBF: synthetic k-step rollouts (mode diff)')),
    ('modular_envelope', '--modular-envelope', dict(
        action=argparse.BooleanOptionalAction,
        help="modular: keep the envelope's correction (bands not marked 'layout: true') in the "
             "losses, as the authors' PVTOL code (default: the config file's /learner "
             'modular_envelope; config/pvtol.yaml sets it)')),
    ('seed', '--seed', {}),
    ('episodes', '--episodes', {}),
    ('max_steps', '--max-steps', dict(help='episode length override')),
    ('config_file', '--config', dict(metavar='CONFIG',
                                     help='ROS params file (default: packaged)')),
    ('out_dir', '--out', dict(metavar='OUT', help='output directory (default: runs/<name>)')),
    ('no_obstacles', '--no-obstacles', dict(
        action='store_true', help='train without obstacles and filter (transfer upper bound)')),
    ('record_bag', '--no-bag', dict(action='store_false', help='do not record MCAP')),
    ('resume', '--resume', dict(
        action='store_true',
        help='continue the run in --out from its checkpoint (none: start at episode 0, keeping '
             'its files); without it an existing run is refused')),
    ('checkpoint_every', '--checkpoint-every', dict(
        metavar='N', help='episodes between checkpoints (a kill loses at most the episodes '
                          'since the last one; default %(default)s)')),
    ('compile_filter', '--compile-filter', dict(
        action='store_true',
        help='compile the per-step autograd constraint assembly of a system or barrier without '
             'a closed form (faster, slower start)')),
    ('compile_update', '--compile-update', dict(
        action='store_true',
        help='compile the SAC update: without a safety layer in the losses as one graph (about '
             '1.6x faster per update); where they pass it (diff; modular with an envelope) its '
             'network parts, the layer eager between them (training steps 1.1-1.25x faster); a '
             "one-off compile of tens of seconds, seconds once torch's compile cache has it")),
    ('threads', '--threads', dict(
        help='torch threads (2 speeds SAC updates 1.2-1.7x on an idle 2-core machine; 1 when '
             'runs or nodes share the cores)')),
    ('random_start', '--random-start', dict(
        action='store_true', help="random episode starts (default: the config's)")),
    ('initial_alpha', '--initial-alpha', dict(
        help="SAC's initial entropy temperature (default: the config's learner initial_alpha, "
             'else 0.2)')),
    ('start_steps', '--start-steps', {}),
    ('update_after', '--update-after', {}),
    ('batch_size', '--batch-size', {}),
    ('gp_refit_interval', '--gp-refit-interval', {}),
)
"""(TrainingSettings field, option, what argparse needs beyond the field's type and default),
in ``--help``'s order."""


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rcbf_ros train``: one option per :data:`OPTIONS` entry, its destination,
    default and type those of its :class:`TrainingSettings` field."""
    settings = {f.name: f for f in fields(TrainingSettings)}
    hints = typing.get_type_hints(TrainingSettings)
    for name, option, extra in OPTIONS:
        kwargs: dict[str, Any] = {'dest': name, 'default': settings[name].default, **extra}
        if name == 'system':
            kwargs['choices'] = systems.system_names()
        if 'action' not in extra:
            kind = [a for a in typing.get_args(hints[name]) if a is not type(None)] or \
                [hints[name]]
            if kind[0] is not str:
                kwargs['type'] = kind[0]
        parser.add_argument(option, **kwargs)


def settings_from_arguments(args: argparse.Namespace) -> TrainingSettings:
    """The run's settings from the parsed options (fields without an option keep their
    defaults), each checked against its field's declared bounds.

    Raises:
        ParameterError: one line naming the option (``--seed: must be >= 0, got -1``).
    """
    options = {name: option for name, option, _ in OPTIONS}
    try:
        return read_parameters(TrainingSettings,
                               {name: getattr(args, name) for name in options})
    except ParameterError as exc:
        key, _, why = str(exc).partition(': ')
        raise ParameterError(f'{options.get(key, key)}: {why}') from None


def run_train(args: argparse.Namespace) -> int:
    """Run ``rcbf_ros train``: 0, 2 on bad arguments, output directory or checkpoint, 1 when a
    file of the run cannot be written (a full disk: the bag closed, the previous checkpoint
    kept; also when Ctrl-C lands in the write that fails), 130 on Ctrl-C or SIGTERM (checkpoint,
    bag and plot written)."""
    from rcbf_ros.bag.interrupts import interrupts_raise
    from rcbf_ros.training.build import check_config_file, RunSetupError
    from rcbf_ros.training.loop import check_out_dir, train
    from rcbf_ros.training.progress import summarize
    from rcbf_ros.training.run_files import RunWriteError
    try:
        settings = settings_from_arguments(args)
        run = settings.run_config()
    except (TypeError, ValueError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    name = settings.name
    try:
        check_out_dir(run)
        check_config_file(run)
    except (RunSetupError, FileNotFoundError, ValueError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:  # a config file that cannot be read, or is not a regular file
        print(f'error: --config {exc.filename!r}: {exc.strerror or exc}', file=sys.stderr)
        return 2
    print(f'training {name}: {run.episodes} episodes -> {run.out_dir}', flush=True)
    if settings.compile_update:
        print('--compile-update: the first SAC update compiles (tens of seconds the first time, '
              "seconds once torch's compile cache has it)", flush=True)

    try:  # SIGTERM as Ctrl-C: checkpoint, bag and plot are written; a bag write finishes
        with interrupts_raise(signal.SIGINT, signal.SIGTERM):
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
    summary = summarize(history)
    summary['out_dir'] = run.out_dir
    print(json.dumps(summary, indent=2))
    return 0

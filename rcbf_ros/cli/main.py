"""The rcbf_ros command: training, experiments, launches, bags and run reports.

    rcbf_ros train --system unicycle --mode modular --seed 0 --episodes 50
    rcbf_ros experiment transfer --budget smoke --seeds 2 --out runs/experiments [--ray]
    rcbf_ros bag recover bags/<run>/bag    # a bag whose recorder was killed -> complete MCAP
    rcbf_ros bag check bags/<run>/bag      # every chunk and CRC checked
    rcbf_ros launch unicycle_filter --domain-id 7   # a launch's nodes as processes, no ROS 2
    rcbf_ros refilter bags/<run>/bag out --params-file my.yaml   # the filter again, offline
    rcbf_ros summary bags/<run>            # what a run left behind, and its trajectories
    rcbf_ros interface-doc --check docs/INTERFACE.md   # the interface tables up to date

``train``, ``experiment`` and ``bag`` are parsed here (their arguments in
:mod:`rcbf_ros.cli.train`, :mod:`rcbf_ros.experiments.command`, :mod:`rcbf_ros.bag.recover`).
The other subcommands hand the rest of the command line, unchanged, to their module's own
``main(argv)`` (:data:`DELEGATED`): their ``--help``, messages and exit codes are that
module's. ``rcbf_ros_launch`` and ``rcbf_ros_refilter`` are the same commands under their
older console-script names. A subcommand's module is imported only when it runs, so that
``rcbf_ros --help`` and each subcommand start without the others' imports (torch, Ray).
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import importlib
import sys
from typing import Any

from rcbf_ros.ros.console import run_writing_stdout


@dataclass(frozen=True)
class Delegated:
    """A subcommand that is another module's command line."""

    module: str
    """Module whose ``main(argv: Sequence[str] | None) -> int`` runs the subcommand."""
    help: str
    """The one line ``rcbf_ros --help`` shows for it."""


DELEGATED: dict[str, Delegated] = {
    'launch': Delegated('rcbf_ros.launch.local',
                        "start a launch's nodes as processes, without ROS 2"),
    'refilter': Delegated('rcbf_ros.bag.refilter',
                          'filter the proposals of a bag again, other parameters'),
    'summary': Delegated('rcbf_ros.reports.run_summary',
                         "print a run's results and draw its trajectories"),
    'interface-doc': Delegated('rcbf_ros.cli.interface_doc',
                               "print, write or check docs/INTERFACE.md's tables"),
}
"""Subcommands run by another module's ``main``, by name."""


@dataclass(frozen=True)
class Parsed:
    """A subcommand whose arguments are parsed here (its module imported only when it runs)."""

    module: str
    """Module holding the two functions below."""
    add_arguments: str
    """Its function that adds the subcommand's arguments to an ``argparse`` parser."""
    run: str
    """Its function that runs the parsed arguments and returns the exit code."""
    help: str
    """The one line ``rcbf_ros --help`` shows for it."""


PARSED_COMMANDS: dict[str, Parsed] = {
    'train': Parsed('rcbf_ros.cli.train', 'add_train_arguments', 'run_train',
                    'train in-process (no middleware)'),
    'experiment': Parsed('rcbf_ros.experiments.command', 'add_experiment_arguments',
                         'run_experiment_command',
                         "reproduce a paper's experiment: train, evaluate, report"),
    'bag': Parsed('rcbf_ros.bag.recover', 'add_bag_arguments', 'run_bag_command',
                  'check a bag, or recover one whose recorder was killed'),
}
"""Subcommands parsed here, by name."""

PARSED: dict[str, str] = {name: parsed.help for name, parsed in PARSED_COMMANDS.items()}
"""Subcommands parsed here, by name, with the one line ``rcbf_ros --help`` shows."""


def commands_help() -> str:
    """The ``commands:`` part of ``rcbf_ros --help``: every subcommand and its line."""
    lines = {**PARSED, **{name: d.help for name, d in DELEGATED.items()}}
    width = max(map(len, lines)) + 2
    return 'commands:\n' + '\n'.join(f'  {name:<{width}}{line}' for name, line in lines.items())


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``rcbf_ros`` parser. Only ``command`` (one of :data:`PARSED`) gets its arguments,
    so that its module is the only one imported: ``rcbf_ros --help`` imports none, and a
    subcommand does not wait for the others' (torch, Ray, ...). None: every subcommand's."""
    parser = argparse.ArgumentParser(
        prog='rcbf_ros', usage='%(prog)s [-h] COMMAND ...',
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.splitlines()[0] + '\n\n' + commands_help(),
        epilog='rcbf_ros <command> --help: its arguments. rcbf_ros_launch and '
               'rcbf_ros_refilter are\nrcbf_ros launch and rcbf_ros refilter; python -m '
               'rcbf_ros is rcbf_ros.')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND', prog='rcbf_ros',
                                help=argparse.SUPPRESS)
    for name, parsed in PARSED_COMMANDS.items():
        subparser = sub.add_parser(name, help=parsed.help)
        if command is None or command == name:
            _function(parsed, 'add_arguments')(subparser)
    for name, delegated in DELEGATED.items():  # choices only: main() hands these on unparsed
        sub.add_parser(name, help=delegated.help, add_help=False)
    return parser


def _function(parsed: Parsed, role: str) -> Any:
    """The function ``parsed`` names for ``role`` ('add_arguments' or 'run'), its module
    imported now."""
    return getattr(importlib.import_module(parsed.module), getattr(parsed, role))


def run_delegated(name: str, argv: Sequence[str]) -> int:
    """Run the subcommand ``name`` of :data:`DELEGATED` on ``argv`` (what follows its name)."""
    module = importlib.import_module(DELEGATED[name].module)
    return module.main(list(argv))


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``rcbf_ros`` (and ``python -m rcbf_ros``); returns the exit code. A
    stdout whose reader leaves costs the output, not the work (:func:`run_writing_stdout`)."""
    return run_writing_stdout('rcbf_ros', lambda: _run(argv))


def launch_alias() -> int:
    """Console script ``rcbf_ros_launch``: ``rcbf_ros launch``, its stdout guarded alike."""
    return main(['launch', *sys.argv[1:]])


def refilter_alias() -> int:
    """Console script ``rcbf_ros_refilter``: ``rcbf_ros refilter``, its stdout guarded alike."""
    return main(['refilter', *sys.argv[1:]])


def _run(argv: Sequence[str] | None) -> int:
    """The subcommand of ``argv`` run; its exit code."""
    given = sys.argv[1:] if argv is None else list(argv)
    # Before any parsing: a delegated subcommand's --help and errors are its module's own.
    if given and given[0] in DELEGATED:
        return run_delegated(given[0], given[1:])
    args = build_parser(given[0] if given else '').parse_args(given)
    run = _function(PARSED_COMMANDS[args.command], 'run')
    if args.command == 'experiment':  # its run records the command line it was given
        return run(args, argv)
    return run(args)


if __name__ == '__main__':
    sys.exit(main())

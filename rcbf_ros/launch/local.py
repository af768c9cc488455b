"""rcbf_ros launch: start a launch's nodes as separate processes, without ROS 2 installed.

The local counterpart of ``ros2 launch rcbf_ros <name>.launch.py``: both read
:mod:`rcbf_ros.launch.table`, so the two start the same nodes with the same arguments. Each node
runs through :mod:`rcbf_ros.ros.node_main` in its own process group on loopback DDS; the params
file and the launch arguments are checked before any node starts. Stopping, respawn and exit
codes follow launch_ros (docs/NODES.md).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time
from typing import Any, Callable, IO, Mapping, Sequence

import yaml

from rcbf_ros.launch.table import (
    Argument,
    argument_values,
    launch_setup,
    LAUNCHES,
    LaunchSetup,
    MAX_TIMEOUT_S,
    PARAMS_FILE_ARGUMENT,
    parse_launch_arguments,
    resolve_entry,
    ros_arguments,
)
from rcbf_ros.parameters import bounded_yaml
from rcbf_ros.parameters.arguments import expand_topic_name, parse_ros_arguments
from rcbf_ros.parameters.rules import find_config, node_key_level
from rcbf_ros.ros.loopback import ensure_loopback
from rcbf_ros.ros.node_main import stop_signals

_REPO_ROOT = Path(__file__).resolve().parents[2]
# Exit statuses of a process that stopped because we asked it to.
_STOPPED_OK = {0, -signal.SIGINT, -signal.SIGTERM, 128 + signal.SIGINT, 128 + signal.SIGTERM}
NODE_RUNNER = 'rcbf_ros.ros.node_main'
"""Module that runs each node's module (``python -m NODE_RUNNER <module> ...``)."""


@dataclass(frozen=True)
class ChildSpec:
    """One process to start."""

    name: str
    """Output prefix and node name."""
    command: tuple[str, ...]
    """argv."""
    required: bool = True
    """A failure of this process fails the launch."""
    ends_launch: bool = False
    """Its exit stops every other process."""
    sigint_timeout_s: float | None = None
    """Seconds from SIGINT to SIGTERM when stopping it (None: the launch's default)."""
    respawn: bool = False
    """Start it again whenever it exits while the launch runs."""
    respawn_delay_s: float = 0.0
    """Seconds from its exit to its new start."""


@dataclass
class LaunchOutcome:
    """How a launch ended."""

    exit_code: int
    """0, or 1 when a required process failed."""
    returncodes: dict[str, int | None] = field(default_factory=dict)
    """Final return code per process (negative: killed by that signal)."""
    failed: list[str] = field(default_factory=list)
    """Required processes that failed."""
    escalations: dict[str, str] = field(default_factory=dict)
    """The strongest signal each stopped process needed ('SIGINT', 'SIGTERM', 'SIGKILL')."""
    reason: str = ''
    """Why the launch stopped."""
    respawns: dict[str, int] = field(default_factory=dict)
    """How many times each respawning process was started again."""


def child_commands(setup: LaunchSetup, *, params_file: str | Path,
                   overrides: Mapping[str, Mapping[str, Any]] | None = None,
                   without: Sequence[str] = (), python: str = sys.executable,
                   arguments: Mapping[str, str] | None = None) -> list[ChildSpec]:
    """The processes of a launch, in start order.

    Args:
        params_file: the params file every node reads.
        overrides: node name -> {parameter: value} (``-p``), winning over the file.
        without: node names not to start.
        arguments: launch arguments given (``name:=value``); the others take their defaults.

    Raises:
        ValueError: an override or ``without`` names a node the launch does not have; an
            argument the launch does not declare, a value outside its choices, one that a
            remap takes as a topic name and is none (empty, a bad token, ...), or a respawn
            setting that is none (:func:`rcbf_ros.launch.table.respawn_settings`).
    """
    values = argument_values(setup, arguments or {})
    for entry in setup.nodes:
        for _, target in entry.remappings:
            if isinstance(target, Argument):
                try:
                    expand_topic_name(values[target.name], entry.name, '/')
                except ValueError as exc:
                    raise ValueError(f'{setup.name}: launch argument '
                                     f'{target.name}:={values[target.name]!r}: {exc}') from exc
    names = {entry.name for entry in setup.nodes}
    for node in (*(overrides or {}), *without):
        if node not in names:
            raise ValueError(f'{setup.name}: no node {node!r} (nodes: {sorted(names)})')
    children = []
    for entry in setup.nodes:
        if entry.name in without:
            continue
        try:
            entry = resolve_entry(entry, values)
        except ValueError as exc:
            raise ValueError(f'{setup.name}: {exc}') from exc
        if without:   # nobody waits for a node that is not started (an empty list: unset)
            parameters = [(key, [name for name in value if name not in without])
                          if key == 'wait_for_subscribers' else (key, value)
                          for key, value in entry.parameters]
            entry = replace(entry, parameters=tuple(
                (key, value) for key, value in parameters
                if not (key == 'wait_for_subscribers' and value == [])))
        args = ros_arguments(entry, params_file=str(params_file),
                             overrides=(overrides or {}).get(entry.name))
        children.append(ChildSpec(name=entry.name,
                                  command=(python, '-m', NODE_RUNNER, entry.module, *args),
                                  required=entry.required, ends_launch=entry.ends_launch,
                                  sigint_timeout_s=entry.sigint_timeout_s,
                                  respawn=bool(entry.respawn),
                                  respawn_delay_s=float(entry.respawn_delay_s)))
    return children


def check_params_file(setup: LaunchSetup, params_file: str | Path) -> None:
    """Refuse a params file before any node starts, as the nodes would each refuse it.

    Raises:
        ValueError: one line naming the file: missing or unreadable, not YAML, not a mapping of
            node sections with ``ros__parameters``, or no section for any node of ``setup``.
    """
    # Read as every node reads its --params-file; RosArgumentError is a ValueError.
    arguments = parse_ros_arguments(['--ros-args', '--params-file', str(params_file)])
    sections = arguments.parameter_rules.sections()
    names = [entry.name for entry in setup.nodes]
    if not any(node_key_level(key, name, f'/{name}') for key in sections for name in names):
        raise ValueError(f'--params-file {str(params_file)!r}: no section for any node of '
                         f'{setup.name} (/**, {", ".join("/" + n for n in names)}); '
                         f'found {sorted(sections) or "none"}')


def child_environment(base: Mapping[str, str], *, domain_id: int) -> dict[str, str]:
    """The environment of every child: loopback Cyclone, the domain id, unbuffered output.

    The loopback URI is forced (no traffic off the machine); the package's source root is put
    on ``PYTHONPATH`` so that ``python -m`` finds it without an install.
    """
    if not 0 <= domain_id <= 232:
        raise ValueError(f'domain_id: must be in 0..232, got {domain_id}')
    env = dict(base)
    ensure_loopback(env, force=True)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['PYTHONUNBUFFERED'] = '1'
    paths = [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p]
    if str(_REPO_ROOT) not in paths:
        env['PYTHONPATH'] = os.pathsep.join([str(_REPO_ROOT), *paths])
    return env


def _pump(name: str, stream: IO[bytes], sink: IO[str], lock: threading.Lock) -> None:
    """Copy a child's output to ``sink`` line by line, prefixed with its name."""
    for raw in iter(stream.readline, b''):
        line = raw.decode('utf-8', errors='replace').rstrip('\n')
        with lock:
            sink.write(f'[{name}] {line}\n')
            sink.flush()
    stream.close()


def _default_sigint() -> None:
    """Runs in each child between fork and exec: SIGINT back to its default.

    A shell starts a background job (``rcbf_ros launch ... &``, CI runners, ``nohup``) with
    SIGINT ignored, and an ignored signal stays ignored across exec; Python then never installs
    its KeyboardInterrupt handler. Our nodes install their own handlers (rclpy.init), but any
    other child would sit out our SIGINT and only stop at the SIGTERM escalation, skipping its
    Ctrl-C clean-up (this made the launch tests fail when CI ran in the background). Only a
    signal call, nothing that takes a lock, so it is safe with the pump threads running.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _signal_group(process: subprocess.Popen, signum: int) -> None:
    try:
        os.killpg(process.pid, signum)
    except ProcessLookupError:
        pass


def run_processes(children: Sequence[ChildSpec], *, env: Mapping[str, str],
                  sink: IO[str] | None = None, sigint_timeout_s: float = 5.0,
                  sigterm_timeout_s: float = 3.0, poll_s: float = 0.05,
                  stop_event: threading.Event | None = None) -> LaunchOutcome:
    """Start ``children``, supervise them, stop them all, report.

    Args:
        env: environment of every child.
        sink: where prefixed output goes (default stdout).
        sigint_timeout_s: seconds from SIGINT to SIGTERM for a child without its own limit.
        sigterm_timeout_s: seconds from SIGTERM to SIGKILL.
        stop_event: set from elsewhere to stop the launch (as Ctrl-C does); children not
            started yet are not started.
    """
    sink = sys.stdout if sink is None else sink
    specs = {child.name: child for child in children}
    lock = threading.Lock()
    processes: dict[str, subprocess.Popen] = {}
    pumps: list[threading.Thread] = []
    outcome = LaunchOutcome(exit_code=0)

    def say(text: str) -> None:
        with lock:
            sink.write(f'[launch] {text}\n')
            sink.flush()

    def note_failure(name: str, why: str) -> None:
        outcome.failed.append(name)
        say(f'{name} failed: {why}')

    def start(child: ChildSpec) -> None:
        process = subprocess.Popen(child.command, env=dict(env), stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   start_new_session=True, preexec_fn=_default_sigint)
        processes[child.name] = process
        pump = threading.Thread(target=_pump, args=(child.name, process.stdout, sink, lock),
                                daemon=True)
        pump.start()
        pumps[:] = [*(p for p in pumps if p.is_alive()), pump]  # a respawn loop stays bounded

    respawn_at: dict[str, float] = {}  # respawning process -> when to start it again
    try:
        for child in children:
            if stop_event is not None and stop_event.is_set():
                break
            start(child)
        while not outcome.reason:
            if stop_event is not None and stop_event.is_set():
                outcome.reason = 'stop requested'
                break
            for name, when in list(respawn_at.items()):
                if time.monotonic() >= when:
                    del respawn_at[name]
                    outcome.respawns[name] = outcome.respawns.get(name, 0) + 1
                    say(f'respawning {name}')
                    try:
                        start(specs[name])
                    except OSError as exc:  # no process now (EAGAIN, ENOMEM): try again later
                        delay = max(specs[name].respawn_delay_s, 1.0)
                        say(f'{name} could not be started ({exc.strerror or exc}); trying '
                            f'again in {delay:g} s')
                        respawn_at[name] = time.monotonic() + delay
            for name, process in processes.items():
                if name in outcome.returncodes or name in respawn_at or process.poll() is None:
                    continue
                code = process.returncode
                child = specs[name]
                if child.respawn and not child.ends_launch:
                    say(f'{name} exited with {code}; respawning in {child.respawn_delay_s:g} s')
                    respawn_at[name] = time.monotonic() + child.respawn_delay_s
                    continue
                outcome.returncodes[name] = code
                if code != 0 and child.required:
                    note_failure(name, f'exited with {code}')
                    outcome.reason = f'{name} failed'
                elif child.ends_launch:
                    outcome.reason = f'{name} exited ({code})'
            if not outcome.reason and len(outcome.returncodes) == len(processes):
                outcome.reason = 'every process exited'
            if not outcome.reason:
                time.sleep(poll_s)
    except KeyboardInterrupt:
        outcome.reason = 'interrupted'
    finally:
        limits = {name: specs[name].sigint_timeout_s or sigint_timeout_s for name in processes}
        _stop_all(processes, outcome, limits, sigterm_timeout_s, poll_s, say)
        for pump in pumps:
            pump.join(timeout=2.0)
    for name, process in processes.items():
        code = process.returncode
        if name in outcome.failed or not specs[name].required:
            continue
        stopped_by_us = name in outcome.escalations
        if specs[name].respawn and not stopped_by_us:  # would have been started again
            continue
        if outcome.escalations.get(name) == 'SIGKILL':
            note_failure(name, 'did not stop on SIGINT or SIGTERM (killed)')
        elif stopped_by_us and code not in _STOPPED_OK:
            note_failure(name, f'exited with {code} when asked to stop')
        elif not stopped_by_us and code not in (0, None):  # ended while the stop began
            note_failure(name, f'exited with {code}')
    outcome.exit_code = 1 if outcome.failed else 0
    respawned = f'respawns {outcome.respawns}; ' if outcome.respawns else ''
    say(f'stopped ({outcome.reason}); return codes {outcome.returncodes}; {respawned}'
        f'exit code {outcome.exit_code}')
    return outcome


_NEXT_SIGNAL = {signal.SIGINT: signal.SIGTERM, signal.SIGTERM: signal.SIGKILL}
_SIGKILL_WAIT_S = 5.0


def _stop_all(processes: Mapping[str, subprocess.Popen], outcome: LaunchOutcome,
              sigint_timeouts_s: Mapping[str, float], sigterm_timeout_s: float,
              poll_s: float, say: Callable[[str], None]) -> None:
    """SIGINT to every process still running; SIGTERM to each one still running after its own
    ``sigint_timeouts_s``, SIGKILL after ``sigterm_timeout_s`` more (each escalation said)."""
    sent: dict[str, tuple[signal.Signals, float]] = {}  # last signal, when to escalate
    abandoned: set[str] = set()  # not even reaped after SIGKILL

    def send(name: str, signum: signal.Signals, wait_s: float) -> None:
        if signum != signal.SIGINT:
            previous = sent[name][0]
            limit = sigint_timeouts_s[name] if previous == signal.SIGINT else sigterm_timeout_s
            say(f'{name} still running {limit:g} s after {previous.name}; sending {signum.name}')
        outcome.escalations[name] = signum.name
        _signal_group(processes[name], signum)
        sent[name] = (signum, time.monotonic() + wait_s)

    for name, process in processes.items():
        if process.poll() is None:
            send(name, signal.SIGINT, sigint_timeouts_s[name])
    while True:
        running = []
        for name, process in processes.items():  # one poll each: every exit is recorded
            if process.poll() is not None:
                outcome.returncodes.setdefault(name, process.returncode)
            elif name in sent and name not in abandoned:
                running.append(name)
        if not running:
            return
        now = time.monotonic()
        for name in running:
            signum, deadline = sent[name]
            if now < deadline:
                continue
            if signum == signal.SIGKILL:
                abandoned.add(name)
                continue
            following = _NEXT_SIGNAL[signum]
            send(name, following, sigterm_timeout_s if following == signal.SIGTERM
                 else _SIGKILL_WAIT_S)
        time.sleep(poll_s)


def _parse_override(text: str) -> tuple[str, str, Any]:
    """``node:name:=value`` -> (node, name, YAML value)."""
    target, sep, value = text.partition(':=')
    node, colon, name = target.partition(':')
    if not sep or not colon or not node or not name:
        raise argparse.ArgumentTypeError(f'-p {text!r}: expected node:parameter:=value')
    try:
        parsed = bounded_yaml.safe_load(value, source=f'-p {node}:{name}') if value else ''
    except bounded_yaml.YAMLLimitError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc
    except yaml.YAMLError as exc:
        why = ' '.join(str(exc).split())
        raise argparse.ArgumentTypeError(f'-p {text!r}: value is not YAML ({why})') from exc
    return node, name, parsed


def _seconds(text: str) -> float:
    """A timeout option: a number of seconds, > 0 and at most :data:`MAX_TIMEOUT_S`."""
    try:
        value = float(text)
    except ValueError:
        value = float('nan')
    if not 0 < value <= MAX_TIMEOUT_S:
        raise argparse.ArgumentTypeError(
            f'expected seconds > 0 and <= {MAX_TIMEOUT_S:g}, got {text!r}')
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='rcbf_ros launch', description=__doc__.split('\n\n')[0],
        epilog='launches: ' + '; '.join(f'{s.name}: {s.description}'
                                        for s in LAUNCHES.values()))
    parser.add_argument('launch', choices=sorted(LAUNCHES), help='which launch to run')
    parser.add_argument('launch_arguments', nargs='*', metavar='NAME:=VALUE',
                        help='launch arguments, as ros2 launch takes them (--show-args)')
    parser.add_argument('-s', '--show-args', action='store_true',
                        help="show the launch's arguments and exit")
    parser.add_argument('--params-file', help='params file (default: config/<system>.yaml)')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of every node (default: $ROS_DOMAIN_ID or 0)')
    parser.add_argument('-p', '--param', action='append', default=[], type=_parse_override,
                        metavar='NODE:NAME:=VALUE', help='parameter override for one node')
    parser.add_argument('--without', action='append', default=[], metavar='NODE',
                        help='do not start this node (repeatable)')
    parser.add_argument('--sigint-timeout', type=_seconds, default=None,
                        help='seconds from SIGINT to SIGTERM for every node (default: per node, '
                        'from the launch table)')
    parser.add_argument('--sigterm-timeout', type=_seconds, default=3.0,
                        help='seconds from SIGTERM to SIGKILL')
    parser.add_argument('--print', action='store_true', dest='print_only',
                        help='print the commands instead of running them')
    return parser


def show_arguments(setup: LaunchSetup) -> str:
    """The text of ``--show-args``: each argument, its description, default and choices."""
    lines = [f"Arguments of {setup.name} (pass arguments as '<name>:=<value>'):", '']
    shown = [(PARAMS_FILE_ARGUMENT, 'ROS 2 params file of every node',
              f'config/{setup.config} of the package', ())]
    shown += [(a.name, a.description, a.default, a.choices) for a in setup.arguments]
    for name, description, default, choices in shown:
        lines += [f"    '{name}':", f'        {description}']
        if choices:
            lines.append(f'        Valid choices are: {list(choices)}')
        lines += [f"        (default: '{default}')", '']
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``rcbf_ros launch`` (console script ``rcbf_ros launch``); returns the launch's exit code."""
    args = build_parser().parse_intermixed_args(argv)
    setup = launch_setup(args.launch)
    if args.show_args:
        print(show_arguments(setup))
        return 0
    try:
        given = parse_launch_arguments(args.launch_arguments)
        named_file = given.pop(PARAMS_FILE_ARGUMENT, None)
        if named_file is not None and args.params_file not in (None, named_file):
            raise ValueError(f'the params file is given twice: --params-file '
                             f'{args.params_file!r} and {PARAMS_FILE_ARGUMENT}:={named_file!r}')
    except ValueError as exc:
        print(f'rcbf_ros launch: {exc}', file=sys.stderr)
        return 2
    params_file = (named_file if named_file is not None
                   else args.params_file or str(find_config(setup.config)))
    overrides: dict[str, dict[str, Any]] = {}
    for node, name, value in args.param:
        overrides.setdefault(node, {})[name] = value
    domain_id = args.domain_id
    if domain_id is None:
        domain_id = int(os.environ.get('ROS_DOMAIN_ID', '0') or 0)
    try:
        check_params_file(setup, params_file)
        children = child_commands(setup, params_file=params_file, overrides=overrides,
                                  without=args.without, arguments=given)
        env = child_environment(os.environ, domain_id=domain_id)
    except ValueError as exc:
        print(f'rcbf_ros launch: {exc}', file=sys.stderr)
        return 2
    if args.sigint_timeout is not None:
        children = [replace(child, sigint_timeout_s=args.sigint_timeout) for child in children]
    if args.print_only:
        for child in children:
            print(f'{child.name}: ' + ' '.join(child.command))
        return 0
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    # SIGINT explicitly, not Python's KeyboardInterrupt: a shell starts a background job
    # (``rcbf_ros launch ... &``) with SIGINT ignored, and Python then installs no handler.
    # SIGHUP too (a closed terminal): each child has its own process group, so the hangup
    # reaches the launcher alone, and the launcher ending at once would leave them running.
    previous = {signum: signal.signal(signum, on_signal) for signum in stop_signals()}
    try:
        outcome = run_processes(children, env=env, sigterm_timeout_s=args.sigterm_timeout,
                                stop_event=stop)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return outcome.exit_code


if __name__ == '__main__':
    sys.exit(main())

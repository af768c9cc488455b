"""Start-up of the safety filter's path: wall time and peak memory of a fresh process.

    python benchmarks/bench_startup.py [--repeats 7] [--no-write]

Each command runs in a new Python process (the venv's interpreter), the commands interleaved
``repeats`` times; the table gives the median wall time and the median peak RSS (the child's
``ru_maxrss`` from ``wait4``). Side by side in one run:

- ``import numpy, osqp``: the floor, what the filter's per-step path needs;
- ``import rcbf_ros.ros.safety_filter_node``: the node's whole import chain, which no longer
  loads torch for the built-in systems (``rcbf_ros/core/torch_import.py``);
- the same with ``import torch`` first: what the chain costs with torch loaded;
- ``safety_filter --help`` (the console script, :data:`SAFETY_FILTER_SCRIPT`: the help from
  the node's interface module, without the middleware) and ``rcbf_ros --help`` (``python -m
  rcbf_ros --help``), as a user types them; beside them ``python -m
  rcbf_ros.ros.safety_filter_node --help``, the node module's own help, which imports the
  node class and the middleware first;
- the filter node answering (:func:`first_answer`): started as a process on the Unicycle's
  config (loopback Cyclone DDS, a domain of its own), a probe in this process publishes a
  proposal with its state every 10 ms from the moment it starts; the time from the start to
  the first ``cmd_safe``, and the node's resident memory then (``VmRSS`` of
  ``/proc/<pid>/status``; ``VmHWM``, its peak so far, beside it).

Writes the ``## Start-up of the filter's path`` section of benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import load_averages, publish_section  # noqa: E402

SAFETY_FILTER_SCRIPT = ['-c', 'import sys; from rcbf_ros.ros.node_main import safety_filter; '
                        'sys.exit(safety_filter())']
"""The interpreter's arguments of what the console script ``safety_filter`` runs (setup.py)."""
COMMANDS: tuple[tuple[str, list[str]], ...] = (
    ('`import numpy, osqp`', ['-c', 'import numpy, osqp']),
    ('`import rcbf_ros.ros.safety_filter_node`',
     ['-c', 'import rcbf_ros.ros.safety_filter_node']),
    ('`import torch` then the same',
     ['-c', 'import torch, rcbf_ros.ros.safety_filter_node']),
    ('`safety_filter --help`', [*SAFETY_FILTER_SCRIPT, '--help']),
    ('`python -m rcbf_ros.ros.safety_filter_node --help`',
     ['-m', 'rcbf_ros.ros.safety_filter_node', '--help']),
    ('`rcbf_ros --help`', ['-m', 'rcbf_ros', '--help']),
)
"""(label, the interpreter's arguments) of every measured command."""


def run_once(arguments: list[str]) -> tuple[float, float]:
    """(wall s, peak RSS MB) of one fresh ``python <arguments>`` process.

    The child's ``ru_maxrss`` counts the memory it shared with this process before its exec
    (Linux keeps the larger of the two), so these runs come before this process loads
    anything of its own (the node's probe)."""
    with tempfile.TemporaryFile() as errors:
        start = time.perf_counter()
        process = subprocess.Popen([sys.executable, *arguments], stdout=subprocess.DEVNULL,
                                   stderr=errors)
        _, status, usage = os.wait4(process.pid, 0)  # the child's own peak memory
        wall = time.perf_counter() - start
        process.returncode = code = os.waitstatus_to_exitcode(status)
        if code != 0:
            errors.seek(0)
            text = errors.read().decode(errors='replace').strip()[-300:]
            raise SystemExit(f'bench_startup: {arguments} exited {code}: {text}')
    return wall, usage.ru_maxrss / 1024.0  # KiB on Linux


TARGETS = {'`safety_filter --help`': '<= 0.3 s', '`rcbf_ros --help`': '<= 0.5 s'}
"""The start-up targets of the filter's path, by row."""
NODE_COMMAND = ['-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args', '--params-file']
"""The filter node as the console script ``safety_filter`` runs it (the config follows)."""
PROPOSAL = {'u': [1.0, 0.0], 'state': [-2.0, 0.5, 0.0]}
"""What the probe publishes on ``cmd_proposed``: a Unicycle proposal with its own state."""


class _Probe:
    """This process's DDS node: publishes proposals, notes when the first ``cmd_safe``
    arrives."""

    def __init__(self, domain_id: int) -> None:
        from rcbf_ros.messages.conversions import sections_to_msg
        from rcbf_ros.ros.runtime import get_message, Node, QoSProfile, rclpy
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node = Node('startup_probe')
        array = get_message('std_msgs/msg/Float64MultiArray')
        self.proposal = sections_to_msg(PROPOSAL)
        self.publisher = self.node.create_publisher(array, '/cmd_proposed', QoSProfile(depth=10))
        self.answered = threading.Event()
        self.answered_at = 0.0
        self.node.create_subscription(array, '/cmd_safe', self._answer, QoSProfile(depth=10))
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _answer(self, _msg: Any) -> None:
        if not self.answered.is_set():
            self.answered_at = time.perf_counter()
            self.answered.set()

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.01)

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def first_answer(probe: _Probe, config: str, environment: dict[str, str],
                 timeout_s: float = 60.0) -> tuple[float, float, float]:
    """(s from the node's start to its first answer, VmRSS MB then, VmHWM MB then) of one
    fresh filter node."""
    probe.answered.clear()
    start = time.perf_counter()
    process = subprocess.Popen([sys.executable, *NODE_COMMAND, config], env=environment,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        while not probe.answered.wait(0.01):
            if process.poll() is not None or time.perf_counter() - start > timeout_s:
                error = process.stderr.read().decode(errors='replace')[-300:]
                raise SystemExit(f'bench_startup: the filter node never answered: {error}')
            probe.publisher.publish(probe.proposal)
        status = Path(f'/proc/{process.pid}/status').read_text()
        memory = {line.split(':')[0]: float(line.split()[1]) / 1024.0
                  for line in status.splitlines() if line.startswith(('VmRSS', 'VmHWM'))}
        return probe.answered_at - start, memory['VmRSS'], memory['VmHWM']
    finally:
        process.send_signal(2)  # SIGINT: the node's own shutdown
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


INSIDE = ('numpy', 'rcbf_ros.node_logic.interface', 'rcbf_ros.messages.classes',
          'rcbf_ros.core.config', 'rcbf_ros.core.filter', 'rcbf_ros.ros.runtime', 'cyclonedds')
"""Modules whose share of the help's import time has a row of its own when they are imported
(with what they import first): the middleware's (``rcbf_ros.ros.runtime``, ``cyclonedds``)
have none while the help is answered without it."""


def help_imports(top: int = 7) -> list[str]:
    """Where ``safety_filter --help`` spends its import time: ``python -X importtime`` of it
    once, the modules its chain imports first (which partition the import time; each with what
    it imports) by cumulative ms, and inside them those of :data:`INSIDE` it imports."""
    done = subprocess.run([sys.executable, '-X', 'importtime', *SAFETY_FILTER_SCRIPT, '--help'],
                          capture_output=True, text=True, check=True)
    outermost: list[tuple[float, str]] = []
    inside: dict[str, float] = {}
    for line in done.stderr.splitlines():
        fields = line.split('|')
        if not line.startswith('import time:') or len(fields) != 3 or not fields[1].strip(
                ).isdigit():
            continue
        name = fields[2].rstrip()
        module = name.strip()
        if len(name) - len(name.lstrip()) == 1:  # one space: imported by the program itself
            outermost.append((int(fields[1]) / 1000.0, module))
        if module in INSIDE:  # with what they import
            inside.setdefault(module, int(fields[1]) / 1000.0)
    total = sum(ms for ms, _ in outermost)
    rows = ['| imported first by the chain | cumulative ms | share |', '|---|---|---|']
    for ms, module in sorted(outermost, reverse=True)[:top]:
        rows.append(f'| `{module}` | {ms:.0f} | {ms / total:.0%} |')
    rows.append(f'| all imports | {total:.0f} | 100% |')
    rows += [f'| of which `{module}` | {ms:.0f} | {ms / total:.0%} |'
             for module, ms in inside.items()]
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=7)
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error('--repeats must be >= 1')
    samples: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in COMMANDS}
    for _ in range(args.repeats):  # first, while this process is small (see run_once)
        for label, arguments in COMMANDS:
            samples[label].append(run_once(arguments))
    from rcbf_ros.parameters.rules import find_config
    from rcbf_ros.ros.loopback import ensure_loopback
    ensure_loopback(os.environ, force=True)  # this probe and the node: loopback only
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))
    os.environ['RCBF_ROS_RUNTIME'] = 'cyclone'
    environment = dict(os.environ, OMP_NUM_THREADS='1')
    probe = _Probe(int(os.environ['ROS_DOMAIN_ID']))
    try:
        answers = [first_answer(probe, str(find_config('unicycle')), environment)
                   for _ in range(args.repeats)]
    finally:
        probe.close()
    table = ['| command | wall s (median) | peak RSS MB (median) | target |', '|---|---|---|---|']
    for label, _ in COMMANDS:
        walls, rss = zip(*samples[label])
        table.append(f'| {label} | {statistics.median(walls):.2f} | '
                     f'{statistics.median(rss):.0f} | {TARGETS.get(label, "")} |')
    seconds, resident, peak = (statistics.median(values) for values in zip(*answers))
    node = ['| the `safety_filter` node (Unicycle) | median | min .. max | target |',
            '|---|---|---|---|',
            f'| first answer, s after the process starts | {seconds:.2f} | '
            f'{min(a[0] for a in answers):.2f} .. {max(a[0] for a in answers):.2f} | <= 1 s |',
            f'| resident memory then (VmRSS), MB | {resident:.0f} | '
            f'{min(a[1] for a in answers):.0f} .. {max(a[1] for a in answers):.0f} | <= 80 MB |',
            f'| its peak so far (VmHWM), MB | {peak:.0f} | '
            f'{min(a[2] for a in answers):.0f} .. {max(a[2] for a in answers):.0f} | |']
    imports = help_imports()
    publish_section(
        "Start-up of the filter's path", script='bench_startup.py', write=args.write,
        conditions=f'; {args.repeats} interleaved runs of each; {load_averages()}',
        blocks=[
            "Each command in a fresh process of the venv's Python. The node's import chain "
            'loads torch only where a system or barrier without a closed form, the '
            "interior-point fallback or learning needs it; the third row is the same chain "
            'with torch loaded, what every process paid while the constraint modules imported '
            "it at module level. `rcbf_ros --help` imports no subcommand's module.",
            table,
            'The filter node answering: started as `python -m rcbf_ros.ros.safety_filter_node '
            '--ros-args --params-file config/unicycle.yaml` (what the console script runs) '
            'on loopback Cyclone DDS; a probe in the benchmark process, started before it, '
            'publishes a proposal with its state every 10 ms until the first `cmd_safe`.',
            node,
            'Where `safety_filter --help` spends its import time (`python -X importtime` of '
            'the console script with `--help`, one run; the times under -X importtime are '
            'larger than without). The console script (`rcbf_ros.ros.node_main:safety_filter`) '
            "answers `--help` from the module that holds the node's interface without the "
            'node class (`rcbf_ros.node_logic.safety_filter_interface`): the middleware the '
            'node class derives from (`rcbf_ros.ros.runtime`: the DDS runtime and the message '
            'classes) is not imported; `python -m rcbf_ros.ros.safety_filter_node --help` '
            'still imports it, as the node module holds the class. A module of '
            f'{", ".join(f"`{m}`" for m in INSIDE)} without a row of its own was not imported.',
            imports,
            'Caveats: the machine (2 cores) is shared with other jobs, whose load the first '
            'line gives; wall times rise with it, the memory figures do not. The peak RSS of '
            "a command counts the benchmark process's own pages at the fork (Linux keeps the "
            "larger), so those run before it loads anything; the node's memory is read from "
            '/proc while it runs.',
        ])
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Start-up of the safety filter's path: wall time and peak memory of a fresh process.

    python benchmarks/bench_startup.py [--repeats 7] [--no-write]

Each command runs in a new Python process (the venv's interpreter), the commands interleaved
``repeats`` times; the table gives the median wall time and the median peak RSS (the child's
``ru_maxrss`` from ``wait4``). Side by side in one run:

- ``import numpy, osqp``: the floor, what the filter's per-step path needs;
- ``import rcbf_ros.ros.safety_filter_node``: the node's whole import chain, which no longer
  loads torch for the built-in systems (``rcbf_ros/core/torch_import.py``);
- the same with ``import torch`` first: what the chain costs with torch loaded;
- ``safety_filter --help`` (``python -m rcbf_ros.ros.safety_filter_node --help``) and
  ``rcbf_ros --help`` (``python -m rcbf_ros --help``), as a user types them.

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
import time

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402

COMMANDS: tuple[tuple[str, list[str]], ...] = (
    ('`import numpy, osqp`', ['-c', 'import numpy, osqp']),
    ('`import rcbf_ros.ros.safety_filter_node`',
     ['-c', 'import rcbf_ros.ros.safety_filter_node']),
    ('`import torch` then the same',
     ['-c', 'import torch, rcbf_ros.ros.safety_filter_node']),
    ('`safety_filter --help`', ['-m', 'rcbf_ros.ros.safety_filter_node', '--help']),
    ('`rcbf_ros --help`', ['-m', 'rcbf_ros', '--help']),
)
"""(label, the interpreter's arguments) of every measured command."""


def run_once(arguments: list[str]) -> tuple[float, float]:
    """(wall s, peak RSS MB) of one fresh ``python <arguments>`` process."""
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=7)
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error('--repeats must be >= 1')
    samples: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in COMMANDS}
    for _ in range(args.repeats):
        for label, arguments in COMMANDS:
            samples[label].append(run_once(arguments))
    table = ['| command | wall s (median) | peak RSS MB (median) |', '|---|---|---|']
    for label, _ in COMMANDS:
        walls, rss = zip(*samples[label])
        table.append(f'| {label} | {statistics.median(walls):.2f} | '
                     f'{statistics.median(rss):.0f} |')
    load = ', '.join(f'{x:.2f}' for x in os.getloadavg())
    publish_section(
        "Start-up of the filter's path", script='bench_startup.py', write=args.write,
        conditions=f'; {args.repeats} interleaved runs of each; load averages {load}',
        blocks=[
            "Each command in a fresh process of the venv's Python. The node's import chain "
            'loads torch only where a system or barrier without a closed form, the '
            "interior-point fallback or learning needs it; the third row is the same chain "
            'with torch loaded, what every process paid while the constraint modules imported '
            'it at module level.',
            table,
            "Not measured here: the filter node's memory once it answers and the time to its "
            'first answer (both need a DDS peer).',
        ])
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""The filter's main path as the tree's own call graph: one proposal to ``cmd_safe``.

    python benchmarks/edge_call_graph.py [--compare REF] [--calls 2000] [--repeat 1] [--no-write]

One ``safety_filter`` node in this process (config/unicycle.yaml, diagnostics with every
answer, publishers that keep the bytes instead of sending them), a state, three untraced
proposals to warm the caches, then one proposal traced with ``sys.setprofile`` from the
sample's bytes (``_on_proposal``) to the bytes handed to the publishers. Every Python call and
return moves "where the proposal is" to the innermost frame of a file of the tree
(``rcbf_ros/``); numpy, osqp and the standard library keep it where it was. A *stop* is a run
of events in one file; a *return* is a stop in a file the path had already left (stops minus
distinct files). Three views:

- every file: the whole path, the solver's core included;
- decide as one stop: the decision (``node_logic/safety_filter.py: decide``, the filter's
  math below it) counted as one stop, so that what is left is the message edge around it;
- hand-offs: each call the node makes counted as one stop, in the file it calls (all below
  it inside): the rooms the node passes the proposal through.

Three proposals (:data:`CASES`): one far from every obstacle (no row active), one facing an
obstacle (a row active, the QP solved), and that one again with no diagnostics due. Each is
also timed untraced (``--calls`` of them, median).
``--compare REF`` measures the tree of git revision ``REF`` too (its ``git archive`` in a
temporary directory), for a before/after table; every tree runs in a child process of its
own, ``--repeat`` times, the trees taking turns, so that the times show their spread.
Writes the ``## The filter's edge as a call graph`` section of benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TITLE = "The filter's edge as a call graph"
QUIET = 'active, diagnostics not due'
"""The case of :data:`CASES` whose answer makes no diagnostics."""
CASES = {'free': ([-3.0, 0.0, 0.0], [1.0, 0.2], 0.0),
         'active': ([-0.85, 0.0, 0.0], [1.0, 0.2], 0.0),
         QUIET: ([-0.85, 0.0, 0.0], [1.0, 0.2], 3600.0)}
"""case -> (state, proposal, ``diagnostics.min_period_s``): far from every obstacle, and facing
the one at the origin, with diagnostics with every answer; and facing it again, with the OK
diagnostics not due (the common answer: by default they go out at most every 0.1 s)."""
OPAQUE = (('node_logic/safety_filter.py', 'decide'),)
"""(file, function) counted as one stop in the view 'decide as one stop'."""
NODE_FILE = 'ros/safety_filter_node.py'
"""The node: in the view 'hand-offs', each call it makes is one stop, in the callee's file."""
VIEWS = ('every file', 'decide as one stop', 'hand-offs')


def _trace(call: Any, package: Path) -> dict[str, list[str]]:
    """The stops of ``call`` in each view of :data:`VIEWS` (files relative to ``package``)."""
    prefix = str(package) + os.sep
    views: dict[str, list[str]] = {view: [] for view in VIEWS}

    def where(frame: Any) -> tuple[str, str, str] | None:
        """The file the path is in, in each view (None: outside the tree)."""
        innermost = opaque = hand_off = None
        callee = None  # the tree frame last passed on the way out
        while frame is not None:
            name = frame.f_code.co_filename
            if name.startswith(prefix):
                relative = name[len(prefix):]
                if innermost is None:
                    innermost = opaque = relative
                if (relative, frame.f_code.co_name) in OPAQUE:
                    opaque = relative  # the outermost opaque frame wins
                if relative == NODE_FILE and hand_off is None:
                    hand_off = callee or relative
                callee = relative
            frame = frame.f_back
        if innermost is None:
            return None
        return innermost, opaque, hand_off or innermost

    def profile(frame: Any, event: str, _arg: Any) -> None:
        if event == 'call':
            here = where(frame)
        elif event == 'return':
            here = where(frame.f_back)
        else:
            return
        if here is None:
            return
        for stops, file in zip(views.values(), here):
            if not stops or stops[-1] != file:
                stops.append(file)

    sys.setprofile(profile)
    try:
        call()
    finally:
        sys.setprofile(None)
    return views


def _median_us(node: Any, state_cdr: bytes, proposal_cdr: bytes, calls: int) -> float:
    """Median microseconds of one untraced ``_on_proposal`` (a fresh state every 50)."""
    times = []
    for index in range(calls):
        if index % 50 == 0:
            node._on_state(state_cdr)
        start = time.perf_counter_ns()
        node._on_proposal(proposal_cdr)
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e3


def measure(calls: int = 2000) -> dict[str, dict[str, Any]]:
    """{case: {'views': {view: stops}, 'median_us': time per proposal}} of the tree
    ``rcbf_ros`` imports from."""
    from rcbf_ros.ros.loopback import ensure_loopback
    ensure_loopback(force=True)
    os.environ.setdefault('RCBF_ROS_RUNTIME', 'cyclone')
    import rcbf_ros
    from rcbf_ros.messages.cdr import serialize_message
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.runtime import Parameter
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode

    package = Path(rcbf_ros.__file__).resolve().parent
    config = package.parent / 'config' / 'unicycle.yaml'
    rclpy.init(args=['--ros-args', '--params-file', str(config), '-p',
                     'diagnostics.min_period_s:=0.0'],
               domain_id=1 + (os.getpid() * 7) % 200)
    node = SafetyFilterNode()
    sent: list[Any] = []
    for publisher in (node._cmd_pub, node._info_pub, node._diag_pub):
        publisher.publish = sent.append
    out = {}
    try:
        for case, (state, proposal, period) in CASES.items():
            if period != node.settings.diagnostics_min_period_s:
                node.set_parameters([Parameter('diagnostics.min_period_s',
                                               Parameter.Type.DOUBLE, period)])
            state_cdr = serialize_message(sections_to_msg({'state': state}))
            proposal_cdr = serialize_message(sections_to_msg({'u': proposal}))
            node._on_state(state_cdr)
            for _ in range(3):
                node._on_proposal(proposal_cdr)
            del sent[:]
            views = _trace(lambda data=proposal_cdr: node._on_proposal(data), package)
            expected = 3 if period == 0 else 2  # cmd_safe, filter_info (, diagnostics)
            if len(sent) != expected or not all(isinstance(b, bytes) for b in sent):
                raise SystemExit(f'edge_call_graph: {case}: expected {expected} messages as '
                                 f'bytes, got {[type(b).__name__ for b in sent]}')
            out[case] = {'views': views,
                         'median_us': _median_us(node, state_cdr, proposal_cdr, calls)}
            del sent[:]
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return out


def _measure_tree(tree: Path, calls: int) -> dict[str, dict[str, Any]]:
    """:func:`measure` of the package in directory ``tree``, in a child process."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    result = subprocess.run([sys.executable, __file__, '--json', '--calls', str(calls)],
                            env=env, cwd=tree, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f'edge_call_graph: {tree}: {result.stderr.strip()[-400:]}')
    return json.loads(result.stdout.strip().splitlines()[-1])


def measure_trees(compare: str | None, calls: int, repeat: int
                  ) -> dict[str, dict[str, dict[str, Any]]]:
    """{tree: {case: figures}} of git revision ``compare`` (its ``git archive``; None: none)
    and of this tree, each run ``repeat`` times in a process of its own, the trees taking
    turns; the times are the median of the runs' medians, with their range (``range_us``)."""
    with tempfile.TemporaryDirectory() as scratch:
        trees = {}
        if compare:
            archive = subprocess.run(['git', '-C', str(ROOT), 'archive', compare], check=True,
                                     capture_output=True).stdout
            subprocess.run(['tar', '-x', '-C', scratch], input=archive, check=True)
            trees[compare] = Path(scratch)
        trees['this tree'] = ROOT
        runs: dict[str, list[dict[str, dict[str, Any]]]] = {tree: [] for tree in trees}
        for _ in range(repeat):
            for tree, path in trees.items():
                runs[tree].append(_measure_tree(path, calls))
    measured = {}
    for tree, results in runs.items():
        measured[tree] = results[0]
        for case, figures in measured[tree].items():
            times = [result[case]['median_us'] for result in results]
            figures['median_us'] = statistics.median(times)
            figures['range_us'] = (min(times), max(times))
    return measured


def _figures(stops: list[str]) -> tuple[int, int, int]:
    """(stops, distinct files, returns to a file already left)."""
    return len(stops), len(set(stops)), len(stops) - len(set(stops))


def _path(stops: list[str]) -> str:
    """The stops as a short line: each file by its name, in order."""
    return ' > '.join(Path(s).stem for s in stops)


def report(measured: dict[str, dict[str, dict[str, Any]]]) -> list[Any]:
    """The section's blocks: the figures table, the times, then the hand-offs per tree."""
    table = ['| tree | proposal | view | stops | files | returns |',
             '|---|---|---|---:|---:|---:|']
    times = ['| tree | proposal | one proposal, median (us) | runs, min - max (us) |',
             '|---|---|---:|---:|']
    paths = []
    for tree, cases in measured.items():
        for case, figures in cases.items():
            for view, stops in figures['views'].items():
                count, files, returns = _figures(stops)
                table.append(f'| {tree} | {case} | {view} | {count} | {files} | {returns} |')
            low, high = figures['range_us']
            times.append(f"| {tree} | {case} | {figures['median_us']:.1f} | {low:.1f} - "
                         f'{high:.1f} |')
        paths.append(f'{tree}, hand-offs of the active proposal: '
                     f"{_path(cases['active']['views']['hand-offs'])}.")
    return [table, *paths, times]


def reading(before: str, measured: dict[str, dict[str, dict[str, Any]]]) -> str:
    """The before/after paragraph of the active proposal (``before``: the compared tree)."""
    figures = {}
    for tree in (before, 'this tree'):
        views = measured[tree]['active']['views']
        figures[tree] = [_figures(views[view]) for view in VIEWS]
    (e0, d0, h0), (e1, d1, h1) = figures[before], figures['this tree']
    q0, q1 = (_figures(measured[tree][QUIET]['views']['every file'])
              for tree in (before, 'this tree'))
    return (f'Reading (the active proposal, stops / files / returns): counting every file, '
            f'{before} made {e0[0]} / {e0[1]} / {e0[2]}, this tree {e1[0]} / {e1[1]} / '
            f'{e1[2]}; with the decision as one stop {d0[0]} / {d0[1]} / {d0[2]} -> {d1[0]} / '
            f'{d1[1]} / {d1[2]}; hand-offs {h0[0]} / {h0[1]} / {h0[2]} -> {h1[0]} / {h1[1]} / '
            f'{h1[2]}. The node hands the bytes to the message edge '
            '(`node_logic/filter_edge.py`: read, checked into a `Proposal`, in one pass), the '
            "sample to `decide` (`node_logic/safety_filter.py`, the filter's math in "
            '`core/filter.py` below it), and the decision back to the edge, which makes '
            '`cmd_safe`, `filter_info` and the due diagnostics in one pass '
            '(`FilterEdge.answer`); the node publishes them, the command first. What is left '
            "inside that pass is the diagnostics': their stamp from the runtime's clock "
            '(`ros/dds/clock.py`) and their bytes from `messages/conversions.py`, two stops '
            'that only an answer with diagnostics due makes (by default an OK answer at most '
            'every `diagnostics.min_period_s` = 0.1 s). With none due, every file: '
            f'{q0[0]} / {q0[1]} / {q0[2]} -> {q1[0]} / {q1[1]} / {q1[2]} ('
            f"{_path(measured['this tree'][QUIET]['views']['every file'])}). Times, this "
            f"tree against {before} (median, difference, inside or outside its runs' range): "
            + '; '.join(_time_against(case, measured[before][case], measured['this tree'][case])
                        for case in CASES) + '.')


def _time_against(case: str, before: dict[str, Any], after: dict[str, Any]) -> str:
    """``case: median us (+difference, inside / outside the compared tree's range)``."""
    (low, high), median = before['range_us'], after['median_us']
    where = 'inside' if low <= median <= high else 'outside'
    return (f"{case} {median:.1f} us ({median - before['median_us']:+.1f}, {where} "
            f'{low:.1f} - {high:.1f})')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--compare', metavar='REF', default=None,
                        help='also measure the tree of this git revision (e.g. a commit)')
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    parser.add_argument('--calls', type=int, default=2000,
                        help='untraced proposals timed per case (default 2000)')
    parser.add_argument('--repeat', type=int, default=1,
                        help='runs of each tree, taking turns (default 1)')
    parser.add_argument('--json', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.calls < 1:
        parser.error('--calls must be >= 1')
    if args.repeat < 1:
        parser.error('--repeat must be >= 1')
    if args.json:  # a child of --compare: this tree's figures, one JSON line
        print(json.dumps(measure(args.calls)))
        return 0
    measured = measure_trees(args.compare, args.calls, args.repeat)
    sys.path.insert(0, str(ROOT))
    from benchmarks._results import load_averages, publish_section
    publish_section(
        TITLE, script='edge_call_graph.py' + (f' --compare {args.compare}' if args.compare
                                              else '')
        + (f' --calls {args.calls}' if args.calls != 2000 else '')
        + (f' --repeat {args.repeat}' if args.repeat != 1 else ''),
        conditions=f'; {load_averages()}',
        write=args.write, blocks=[
            'One proposal through an in-process `safety_filter` (config/unicycle.yaml, '
            'diagnostics with every answer, then with none due) from its CDR bytes to the '
            'bytes of `cmd_safe`, `filter_info` and diagnostics, traced with '
            '`sys.setprofile`. A stop is a run of calls and returns in one file of the tree; '
            "returns: stops in a file the path had already left. 'decide as one stop' counts "
            "`decide` and the filter's math below it as one stop; 'hand-offs' counts each "
            'call the node makes as one stop in the file it calls. These figures count calls, '
            'not time: they do not vary between runs. The last table times one untraced '
            'proposal the same way (publishers that keep the bytes; a fresh state every 50; '
            'median of `--calls`), each tree in a process of its own, `--repeat` runs taking '
            "turns: the median of the runs' medians and their range. The machine is shared, "
            'so a run that meets a busy core shows as the top of the range.',
            *report(measured), *([reading(args.compare, measured)] if args.compare else [])])
    return 0


if __name__ == '__main__':
    sys.exit(main())

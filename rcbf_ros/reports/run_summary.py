"""Print what a training run left behind: returns, violations, speed, the bag and the plots.

    rcbf_ros summary bags/<run> [--params-file my_layout.yaml]

Reads ``<run>/learner/summary.json`` and ``metrics.jsonl`` (written by the learner node or
``rcbf_ros train``) and the MCAP bag under ``<run>/bag``. A bag whose recorder was killed is
recovered first (``rcbf_ros bag recover``: complete files from its whole chunks, the originals
kept as ``*.mcap.orig``), so that every bag reader accepts it.

From the bag it draws ``<run>/trajectories.png``
(:func:`rcbf_ros.reports.plots.plot_trajectories`):
the states of ``/sim/step`` (else ``/state``, split at the ``/episode`` events), the steps whose
filter answer carries a correction |u_S| > 1e-7 (``/filter_info``; in bags recorded before the
filter published it, ``/cmd_safe`` with its ``u_s`` section), over the layout of the params file
(default:
the packaged ``config/<system>.yaml`` of the system the bag's episode events name), and prints
the closest approach to an obstacle. Episodes on random layouts are not drawn (one picture
would mix layouts).
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
import json
import math
import os
from pathlib import Path
import sys
from typing import Any

import numpy as np

STEP_TOPIC = '/sim/step'
STATE_TOPIC = '/state'
COMMAND_TOPIC = '/cmd_safe'
INFO_TOPIC = '/filter_info'
EPISODE_TOPIC = '/episode'
ANSWER_SEARCH = 50
"""How far back (states) a command's ``state`` section is looked up among its episode's."""


MAX_SUMMARY_BYTES = 2**20
"""Largest ``summary.json`` read (1 MiB; the learner writes well under 1 KiB)."""
MAX_METRICS_BYTES = 64 * 2**20
"""Largest ``metrics.jsonl`` read (64 MiB: some 200,000 episodes of about 300 bytes)."""
_SUMMARY_NUMBERS = {'episodes': int, 'env_steps': int, 'steps_per_s': float,
                    'best_return': float, 'goals_reached': int}
"""Fields of ``summary.json`` this report formats, and the kind of number each must be."""


class RunFileError(ValueError):
    """A file of a run that cannot be read as the learner writes it (one line: the file, the
    line or field, and what is wrong)."""


def _read_text(path: Path, max_bytes: int) -> str:
    """The UTF-8 text of the regular file ``path``, read no further than ``max_bytes`` + 1.

    Raises:
        RunFileError: not a regular file, unreadable, larger than ``max_bytes``, not UTF-8.
    """
    from rcbf_ros.parameters import bounded_yaml
    try:
        return bounded_yaml.read_limited(path, max_bytes=max_bytes, what='run file')
    except bounded_yaml.YAMLLimitError as exc:
        raise RunFileError(f'{path}: larger than the {max_bytes}-byte limit') from exc
    except OSError as exc:
        why = exc.strerror or str(exc)
        raise RunFileError(f'{path}: {why}' if why.startswith('not a regular file') else
                           f'{path}: cannot be read ({why})') from exc
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b'\n') + 1
        raise RunFileError(f'{path}: line {line}: not UTF-8 text ({exc.reason} at byte '
                           f'{exc.start})') from exc


def _is_number(value: Any, kind: type) -> bool:
    if isinstance(value, bool):
        return False
    return isinstance(value, int) if kind is int else isinstance(value, (int, float))


def read_learner_summary(path: Path) -> dict[str, Any]:
    """``summary.json`` as the learner writes it: a JSON object whose counts and rates, where
    present, are numbers (:data:`_SUMMARY_NUMBERS`).

    Raises:
        RunFileError: one line naming the file (and the line or field).
    """
    text = _read_text(path, MAX_SUMMARY_BYTES)
    try:
        summary = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RunFileError(f'{path}: line {exc.lineno}, column {exc.colno}: not JSON '
                           f'({exc.msg})') from exc
    except RecursionError as exc:
        raise RunFileError(f'{path}: not JSON (nested too deep)') from exc
    if not isinstance(summary, dict):
        raise RunFileError(f'{path}: not a JSON object but a {type(summary).__name__}')
    for key, kind in _SUMMARY_NUMBERS.items():
        if key in summary and not _is_number(summary[key], kind):
            what = 'an integer' if kind is int else 'a number'
            raise RunFileError(f'{path}: {key}: not {what} ({str(summary[key])[:80]!r})')
    violations = summary.get('safety_violations')
    if violations is not None and not _is_number(violations, int):
        raise RunFileError(f'{path}: safety_violations: not an integer '
                           f'({str(violations)[:80]!r})')
    return summary


def read_returns(path: Path) -> tuple[list[float], str]:
    """The return (``ret``) of every episode row of ``metrics.jsonl``, and a warning ('' if
    none).

    The learner appends one row per episode and flushes it: a run killed in the middle of an
    append leaves its last line cut short (no newline at its end). That line is skipped with a
    warning; any other bad line is an error.

    Raises:
        RunFileError: one line naming the file and the line.
    """
    text = _read_text(path, MAX_METRICS_BYTES)
    lines = text.split('\n')
    cut = lines.pop()  # '' when the file ends with a newline
    returns: list[float] = []
    for number, line in enumerate(lines, start=1):
        if line.strip():
            returns.append(_row_return(path, number, line))
    warning = ''
    if cut.strip():
        try:
            returns.append(_row_return(path, len(lines) + 1, cut))
        except RunFileError:
            warning = (f'{path}: line {len(lines) + 1} is cut short (a run killed while '
                       'writing it); skipped')
    return returns, warning


def _row_return(path: Path, number: int, line: str) -> float:
    try:
        row = json.loads(line)
    except (json.JSONDecodeError, RecursionError) as exc:
        why = exc.msg if isinstance(exc, json.JSONDecodeError) else 'nested too deep'
        raise RunFileError(f'{path}: line {number}: not JSON ({why})') from exc
    if not isinstance(row, dict):
        raise RunFileError(f'{path}: line {number}: not a JSON object')
    if 'ret' not in row:
        raise RunFileError(f'{path}: line {number}: no ret (the episode return)')
    if not _is_number(row['ret'], float):
        raise RunFileError(f'{path}: line {number}: ret: not a number '
                           f'({str(row["ret"])[:80]!r})')
    return float(row['ret'])


def summarize_run(run: Path, *, params_file: str | None = None,
                  warn: Callable[[str], None] | None = None) -> str:
    """The summary text for the run directory ``run`` (drawing ``trajectories.png``).

    Args:
        run: the run directory.
        params_file: the layout to draw over (default: the system's packaged config).
        warn: takes a one-line warning (a metrics row cut short and skipped); default: none.

    Raises:
        RunFileError: ``summary.json`` or ``metrics.jsonl`` cannot be read as the learner
            writes them (one line naming the file and the line or field).
    """
    lines = [f'run: {run}']
    learner = run / 'learner'
    summary_path = learner / 'summary.json'
    if not os.path.lexists(summary_path):
        return '\n'.join(lines + [f'no {summary_path}: the learner did not finish an episode'])
    summary = read_learner_summary(summary_path)
    metrics = learner / 'metrics.jsonl'
    returns: list[float] = []
    if os.path.lexists(metrics):
        returns, warning = read_returns(metrics)
        if warning and warn is not None:
            warn(warning)
    lines.append(f"episodes: {summary.get('episodes', 0)}   env steps: "
                 f"{summary.get('env_steps', 0)}   steps/s: {summary.get('steps_per_s', 0):.1f}")
    if returns:
        lines.append('returns per episode: ' + ', '.join(f'{r:.2f}' for r in returns))
    lines.append(f"best return: {summary.get('best_return', float('nan')):.3f}   goals reached: "
                 f"{summary.get('goals_reached', 0)}")
    lines.append(f"safety violations (true barriers < 0): {summary.get('safety_violations')}")
    if 'reward_curve' in summary:
        lines.append(f"reward curve: {str(summary['reward_curve'])[:500]}")
    lines.append(f'checkpoint: {learner / "checkpoint.pt"}   policy: {learner / "policy.pt"}')
    bag_dir = run / 'bag'
    if bag_dir.exists():
        from rcbf_ros.bag import bag_info, BagError, reindex_bag
        try:
            info = bag_info(bag_dir)
            state = 'closed cleanly'
            if not info.complete:
                reindex_bag(bag_dir)
                info, state = bag_info(bag_dir), 'recorder killed: recovered from whole chunks'
        except (BagError, OSError) as exc:  # OSError: the recovery could not write
            return '\n'.join(lines + [f'bag: {exc}'])
        seconds = (info.end_time_ns - info.start_time_ns) / 1e9
        lines.append(f'bag: {bag_dir} ({info.message_count} messages, {seconds:.1f} s, {state})')
        for name, topic in sorted(info.topics.items()):
            lines.append(f'  {name:28s} {topic.message_count:7d}')
        lines.append(trajectory_line(bag_dir, run / 'trajectories.png', params_file=params_file))
    return '\n'.join(lines)


class _Episodes:
    """Episodes being collected from a bag, in the order they appear."""

    def __init__(self) -> None:
        self.states: dict[int, list[np.ndarray]] = {}
        self.corrected: dict[int, list[bool]] = {}
        self.current: int | None = None

    def open(self, episode: int) -> None:
        if episode not in self.states:
            self.states[episode], self.corrected[episode] = [], []
        self.current = episode

    def add(self, state: np.ndarray) -> None:
        assert self.current is not None
        states = self.states[self.current]
        if states and np.array_equal(states[-1], state):
            return  # the simulator published the pending state again
        states.append(state)
        self.corrected[self.current].append(False)

    def mark(self, answered: np.ndarray | None) -> None:
        """The command answering ``answered`` (None: the latest state) was corrected."""
        if self.current is None or not self.states[self.current]:
            return
        states = self.states[self.current]
        if answered is None:
            self.corrected[self.current][-1] = True
            return
        for index in range(len(states) - 1, max(len(states) - 1 - ANSWER_SEARCH, -1), -1):
            if np.array_equal(states[index], answered):
                self.corrected[self.current][index] = True
                return

    def paths(self) -> list[Any]:
        from rcbf_ros.reports.plots import EpisodePath
        return [EpisodePath(episode, np.array(states), np.array(self.corrected[episode]))
                for episode, states in self.states.items() if len(states) >= 2]


def _sections(item: Any) -> dict[str, np.ndarray] | None:
    """The labelled sections of a recorded Float64MultiArray (None: not one)."""
    from rcbf_ros.messages.cdr import deserialize_rosbags_message as deserialize_message
    from rcbf_ros.messages.conversions import msg_to_sections
    try:
        return msg_to_sections(deserialize_message(item.data, item.type_name),
                               default_label='state' if item.topic == STATE_TOPIC else 'u')
    except Exception:  # a sample of another type or layout: not part of a trajectory
        return None


def _vector(values: Any, n_x: int) -> np.ndarray | None:
    array = np.asarray(values, dtype=np.float64).reshape(-1) if values is not None else None
    if array is None or array.size != n_x or not np.all(np.isfinite(array)):
        return None
    return array


def _correction(sections: dict[str, np.ndarray]) -> float:
    """|u_S| of a recorded command (``u_s``, else ``u - u_rl``; NaN when it carries neither)."""
    if 'u_s' in sections:
        return float(np.linalg.norm(sections['u_s']))
    if 'u' in sections and 'u_rl' in sections and sections['u'].size == sections['u_rl'].size:
        return float(np.linalg.norm(sections['u'] - sections['u_rl']))
    return math.nan


def episode_events(items: Iterable[Any]) -> list[dict[str, Any]]:
    """The JSON objects of recorded ``/episode`` messages (others skipped)."""
    from rcbf_ros.messages.cdr import deserialize_rosbags_message as deserialize_message
    events = []
    for item in items:
        try:
            event = json.loads(deserialize_message(item.data, item.type_name).data)
        except Exception:  # not a JSON string message
            continue
        if isinstance(event, dict):
            events.append(event)
    return events


def episode_paths(bag: Path, *, n_x: int) -> list[Any]:
    """The episodes recorded in ``bag`` as :class:`rcbf_ros.reports.plots.EpisodePath`, in order.

    States come from ``/sim/step`` (sections ``state`` and ``episode`` in one message per step,
    so no cross-topic ordering is needed) when the bag has it, else from ``/state``,
    starting a new episode at each ``/episode`` start event or the first state after an end
    event (numbered from 1 where no start event names it). A state equal to the one before
    (published again while the simulator waited for a command) is kept once. A
    ``/filter_info`` (in a bag without one: a ``/cmd_safe`` of the earlier form, with ``u_s``
    or ``u_rl``) with |u_S| > 1e-7 marks the state its ``state`` section names (else the
    latest one) as corrected. Samples of the wrong length or with NaN are skipped, and so is
    an episode without a step (a reset the run ended at).
    """
    from rcbf_ros.bag import bag_info, read_bag
    from rcbf_ros.reports.plots import CORRECTION_THRESHOLD
    recorded = bag_info(bag).topics
    # a /sim/step the recorder subscribed to but nobody published on is no source of states
    by_steps = STEP_TOPIC in recorded and recorded[STEP_TOPIC].message_count > 0
    answers = INFO_TOPIC if INFO_TOPIC in recorded else COMMAND_TOPIC
    episodes = _Episodes()
    ended, counter = True, 0
    topics = [STEP_TOPIC if by_steps else STATE_TOPIC, answers, EPISODE_TOPIC]
    for item in read_bag(bag, topics=topics):
        if item.topic == EPISODE_TOPIC:
            if not by_steps:
                for event in episode_events([item]):
                    if event.get('event') == 'start' and isinstance(event.get('episode'), int):
                        counter = event['episode']
                        episodes.open(counter)
                        ended = False
                    elif event.get('event') == 'end':
                        ended = True
            continue
        sections = _sections(item)
        if sections is None:
            continue
        if item.topic == answers:
            if _correction(sections) > CORRECTION_THRESHOLD:
                episodes.mark(_vector(sections.get('state'), n_x) if 'state' in sections
                              else None)
            continue
        state = _vector(sections.get('state', next(iter(sections.values()))), n_x)
        if state is None:
            continue
        if by_steps:
            try:
                episodes.open(int(sections['episode'][0]))
            except (KeyError, IndexError, ValueError):
                continue
        elif ended:
            counter += 1
            episodes.open(counter)
            ended = False
        episodes.add(state)
    return episodes.paths()


def trajectory_line(bag: Path, png: Path, *, params_file: str | None = None) -> str:
    """Draw the bag's trajectories into ``png``; one line saying where, or why not."""
    from rcbf_ros.bag import BagError, read_bag
    from rcbf_ros.core.scene import scene_geometry
    from rcbf_ros.parameters.rules import find_config, load_params
    from rcbf_ros.reports.plots import plot_trajectories
    try:
        events = episode_events(read_bag(bag, topics=[EPISODE_TOPIC]))
        starts = [e for e in events if e.get('event') == 'start']
        if any(e.get('layout_seed') is not None for e in starts):
            return 'trajectories: not drawn: the episodes ran on random layouts'
        system = next((e['system'] for e in starts if isinstance(e.get('system'), str)), None)
        if params_file is None and system is None:
            return 'trajectories: not drawn: no /episode start event names the system'
        config = find_config(params_file or system)
        geometry = scene_geometry(load_params(config, 'safety_filter'))
        simulator = load_params(config, 'simulator')
        paths = episode_paths(bag, n_x=geometry.n_x)
        if not paths:
            return f'trajectories: not drawn: no state of {geometry.n_x} values in the bag'
        goal = simulator.get('goal') if geometry.system in ('unicycle', 'pvtol') else None
        picture = plot_trajectories(
            paths, geometry, png, goal=goal, dt=simulator.get('dt'),
            true_gap=simulator.get('collision_gap'),
            title=f'{geometry.system}: {len(paths)} episodes, {png.parent.name}')
    except (BagError, FileNotFoundError, ValueError, ImportError) as exc:
        return f'trajectories: not drawn: {exc}'
    except OSError as exc:  # a params file that cannot be read, or is not a regular file
        return f'trajectories: not drawn: {exc.filename}: {exc.strerror or exc}'
    closest = (f'; closest approach {picture.closest.describe()}' if picture.closest
               else '')
    return f'trajectories: {picture.path}{closest}'


USAGE = 'usage: rcbf_ros summary <run directory> [--params-file <yaml>]'
"""The command's usage line (``python -m rcbf_ros.reports.run_summary`` takes the same)."""


def main(argv: list[str] | None = None) -> int:
    """``rcbf_ros summary``: 0, or 2 with one line on stderr (bad arguments, no such run, a
    learner file that cannot be read); a metrics row cut short is skipped with one warning."""
    args = sys.argv[1:] if argv is None else list(argv)
    params_file = None
    if args in (['-h'], ['--help']):
        print(USAGE)
        return 0
    if len(args) == 3 and args[1] == '--params-file':
        params_file = args[2]
    elif len(args) != 1:
        print(USAGE, file=sys.stderr)
        return 2
    run = Path(args[0])
    if not run.is_dir():
        reason = 'not a directory' if run.exists() else 'no such directory'
        print(f'rcbf_ros summary: error: {run}: {reason} (expected a run directory)',
              file=sys.stderr)
        return 2
    try:
        text = summarize_run(run, params_file=params_file,
                             warn=lambda line: print(f'rcbf_ros summary: warning: {line}',
                                                     file=sys.stderr))
    except RunFileError as exc:
        print(f'rcbf_ros summary: error: {exc}', file=sys.stderr)
        return 2
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())

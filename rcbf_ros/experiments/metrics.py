"""Small pure metric functions of the experiments (unit-tested on hand-computed values).

All standard deviations are population standard deviations (``ddof=0``), as numpy's default
and as :func:`rcbf_ros.reports.plots.plot_reward_bands` draws its bands.

How a transfer episode ended (:data:`ENDINGS`, :func:`episode_ending`) is read from its last
``window`` steps (default 200, 4 s at the go-to-goal systems' dt of 0.02 s): an episode that did
not reach the goal stood still when its position moved less than ``still`` (0.1 m, an average
speed under 0.025 m/s) from the window's first step to its last; standing still, it was *held*
when the filter corrected the proposal on at least ``held_share`` (half) of those steps (the
policy pushes into a barrier and the filter stops it there), *stalled* otherwise (the policy's
own fixed point, the filter idle); it was *moving* when it had not stood still (wandering,
circling, leaving the arena or too slow for the time limit).
"""
from __future__ import annotations

from typing import Iterable, Mapping, NamedTuple, Sequence

import numpy as np


class Band(NamedTuple):
    """Mean and a +/- k std band of per-episode returns over seeds, all (E,)."""

    episode: np.ndarray
    """1-based episode index."""
    mean: np.ndarray
    """Mean return over seeds."""
    lower: np.ndarray
    """mean - k std."""
    upper: np.ndarray
    """mean + k std."""
    n_runs: int
    """Number of seeds that entered the statistics."""


def mean_std(values: Iterable[float]) -> tuple[float, float]:
    """(mean, population std) of a non-empty sequence.

    Raises:
        ValueError: ``values`` is empty.
    """
    data = np.asarray(list(values), dtype=np.float64)
    if data.size == 0:
        raise ValueError('values: need at least one value')
    return float(data.mean()), float(data.std())


def completion_rate(goal_reached: Iterable[bool]) -> float:
    """Share of episodes that reached the goal before the time limit, in [0, 1].

    Raises:
        ValueError: no episodes.
    """
    flags = [bool(flag) for flag in goal_reached]
    if not flags:
        raise ValueError('goal_reached: need at least one episode')
    return sum(flags) / len(flags)


def count_violations(rows: Iterable[Mapping[str, object]]) -> int:
    """Total safety violations (steps with a true clearance < 0) over episode rows.

    Raises:
        ValueError: a row has no ``violations`` field or a negative count.
    """
    total = 0
    for index, row in enumerate(rows):
        if 'violations' not in row:
            raise ValueError(f'violations: missing in row {index}')
        count = int(row['violations'])  # type: ignore[arg-type]
        if count < 0:
            raise ValueError(f'violations: negative count {count} in row {index}')
        total += count
    return total


ENDINGS = ('goal', 'held', 'stalled', 'moving')
"""How a transfer episode ended (module docstring), in report order."""


class Tail(NamedTuple):
    """Motion and filter activity over an episode's last steps."""

    moved: float
    """Distance between the position at the window's start and at the episode's end."""
    active: float
    """Share of the window's steps on which the filter changed the proposal, in [0, 1]."""
    steps: int
    """Steps in the window: ``min(window, episode steps)``."""


def episode_tail(positions: Sequence[Sequence[float]], active: Sequence[bool],
                 window: int = 200) -> Tail:
    """The :class:`Tail` of an episode of T steps.

    Args:
        positions: (T + 1, d) positions from the reset to the end.
        active: (T,) whether the filter changed step t's proposal.
        window: steps to look back (the whole episode when it is shorter).

    Raises:
        ValueError: naming ``window``, ``active`` or ``positions`` when the window is < 1,
            the episode has no step, or the two lengths disagree.
    """
    if window < 1:
        raise ValueError(f'window: must be >= 1, got {window}')
    flags = np.asarray(active, dtype=bool).reshape(-1)
    if flags.size == 0:
        raise ValueError('active: the episode has no step')
    points = np.asarray(positions, dtype=np.float64)
    if points.ndim != 2 or points.shape[0] != flags.size + 1:
        raise ValueError(f'positions: expected {flags.size + 1} rows (one per step plus the '
                         f'reset), got shape {points.shape}')
    steps = min(window, flags.size)
    moved = float(np.linalg.norm(points[-1] - points[-1 - steps]))
    return Tail(moved, float(flags[-steps:].mean()), steps)


def episode_ending(goal_reached: bool, tail: Tail, *, still: float = 0.1,
                   held_share: float = 0.5) -> str:
    """One of :data:`ENDINGS` (module docstring for the thresholds)."""
    if goal_reached:
        return 'goal'
    if tail.moved >= still:
        return 'moving'
    return 'held' if tail.active >= held_share else 'stalled'


def reward_band(curves: Sequence[Sequence[float]], k: float = 2.0) -> Band:
    """Mean +/- k std of per-episode returns over seeds, truncated to the shortest run.

    Args:
        curves: one sequence of per-episode returns per seed.
        k: band half-width in standard deviations (the paper's figures: 2).

    Raises:
        ValueError: no curves, or a curve with no episodes.
    """
    if not curves:
        raise ValueError('curves: need at least one run')
    length = min(len(curve) for curve in curves)
    if length == 0:
        raise ValueError('curves: a run has no episodes')
    data = np.asarray([list(curve)[:length] for curve in curves], dtype=np.float64)
    mean, std = data.mean(axis=0), data.std(axis=0)
    return Band(np.arange(1, length + 1), mean, mean - k * std, mean + k * std, len(curves))


def final_window_mean(curve: Sequence[float], window: int = 10) -> float:
    """Mean of the last ``window`` returns (all of them when the run is shorter).

    Raises:
        ValueError: empty curve or ``window`` < 1.
    """
    if window < 1:
        raise ValueError(f'window: must be >= 1, got {window}')
    if len(curve) == 0:
        raise ValueError('curve: no episodes')
    return float(np.mean(np.asarray(curve, dtype=np.float64)[-window:]))

"""What a safety filter's answer is reported with, besides the command: ``filter_info``.

The safety_filter node publishes the command alone on ``cmd_safe`` and these numbers on
``filter_info`` (a ``std_msgs/Float64MultiArray`` whose ``layout.dim`` labels the sections);
``rcbf_ros refilter`` and the in-process trainer's bags write the same. Pure data: the sections
of one answer as numpy arrays, no messages.

Sections, in this order (:data:`INFO_SECTIONS`). The first five are always there, so that their
indexes into ``data`` are fixed for a system (n_u = 2: ``u`` is data[0:2], ``u_rl`` data[2:4],
``u_s`` data[4:6], ``fail_safe`` data[6], ``status`` data[7]); the others only when they were
evaluated. No section ever holds NaN or inf: a value that was not evaluated is left out.
``binding_points`` is bounded (:data:`BINDING_POINTS` rows of 4) however many sensor points
the filter holds: the whole point set is one barrier, ``sensor_points``, in ``h`` and
``constraint``; these rows say which points it is.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple, Sequence

import numpy as np

BINDING_POINTS = 16
"""Most sensor points :func:`binding_points` reports (``filter_info``'s ``binding_points``)."""

INFO_SECTIONS: tuple[tuple[str, str, str], ...] = (
    ('u', 'n_u', 'the command published on cmd_safe'),
    ('u_rl', 'n_u', 'the proposal as received; u itself when it was unusable'),
    ('u_s', 'n_u', 'the correction u - u_rl'),
    ('fail_safe', '1', '1: u is the fail-safe action, 0: the filtered proposal'),
    ('status', '1', 'the solver status, or why the fail-safe was published (status codes)'),
    ('h', 'K', 'barrier values h_i at the state, in the order of the barriers (the h.<barrier> '
     'keys of diagnostics name them) (when evaluated)'),
    ('constraint', 'K', 'L_f h + L_g h u + alpha h + rho per barrier (when evaluated)'),
    ('slack', '1', 'the QP slack eps (when solved)'),
    ('needed_slack', '1', 'slack the rows need at u (when evaluated)'),
    ('solve_time_s', '1', 'solver wall time in seconds (when solved)'),
    ('state', 'n_x', 'the state the command answers (when there was a usable one)'),
    ('binding_points', '4 m', f'rows [x, y, row value, h] of the m <= {BINDING_POINTS} sensor '
     "points whose rows are closest to binding (least row value first; x, y in the state's "
     'frame; the row value as in constraint) (with sensor points)'),
)
"""(label, size, meaning) of every section, in order."""

STATUS_CODES: dict[str, int] = {
    'solved': 0, 'solved_inaccurate': 1, 'solved_interior_point': 2,
    'bad proposal': 10, 'undecodable proposal': 11, 'no state received yet': 12,
    'bad state': 13, 'stale state': 14, 'bad input': 15, 'internal error': 16,
    'source unusable': 17, 'stale proposal': 18, 'late state': 19, 'input_refused': 20,
    'unverified': 21, 'slack_exceeded': 22,
}
"""The ``status`` section: the solver status of a filtered command (0-9), or the reason the
fail-safe was published (10-19: before the QP; 20-29: the QP's outcome, as the filter's
``FilterResult.status``)."""
SOURCE_UNUSABLE = 'source unusable'
"""The status of a fail-safe for an observation source (no fresh message, a refused one, a
frame it cannot place: the reason, ``source <name>: ...``, names the source)."""
STALE_PROPOSAL = 'stale proposal'
"""The status of a fail-safe for a proposal filtered again more than ``max_proposal_age_s``
after its arrival (the controller went quiet)."""
LATE_STATE = 'late state'
"""The status of a fail-safe for a state older than ``latency_s`` at the decision, with a
sampled-data margin (``control_period_s`` or ``latency_s`` > 0): the margin assumes the state
is at most ``latency_s`` old when its command starts to act."""
UNKNOWN_STATUS = 99
"""``status`` of a status or reason not in :data:`STATUS_CODES`."""


class PointValues(NamedTuple):
    """The sensor points' rows of one answer, all (N,) float64, point i in every array: views
    of the filter's arrays, made without a copy (the filter replaces, never writes, them)."""

    x: np.ndarray
    """x of each point in the state's frame (m)."""
    y: np.ndarray
    """y of each point in the state's frame (m)."""
    h: np.ndarray
    """h of each point's row at the state."""
    values: np.ndarray
    """Each point's row value L_f h + L_g h u + alpha h + rho at the returned action (as
    ``constraint_values``; < 0 needs slack, about 0 binds)."""


_BLOCK = 64
"""Entries per group of :func:`_least`'s first pass."""


def _least(key: np.ndarray, limit: int) -> np.ndarray:
    """Indices of the ``limit`` least entries of ``key`` (all of a shorter one) by (value,
    index), in that order; NaN counts as the largest. O(N) in passes that allocate little: the
    least value of each group of 64 entries bounds the limit-th least value (``limit`` groups
    each hold a value at or below their limit-th least minimum), and only the entries up to
    that bound are partitioned. A group is every (N // 64)-th entry: the minimum over the
    first axis of a (64, N // 64) view is one pass over contiguous rows."""
    groups = key.size // _BLOCK
    candidates = None
    if groups > limit:
        least_of_group = key[:groups * _BLOCK].reshape(_BLOCK, groups).min(axis=0)
        bound = np.partition(least_of_group, limit - 1)[limit - 1]
        if bound == bound:  # else NaN: fewer than limit groups without one
            candidates = np.flatnonzero(key <= bound)
            key = key[candidates]
    if key.size > limit:
        kth = np.partition(key, limit - 1)[limit - 1]  # NaN sorts last
        index = np.flatnonzero(key <= kth) if kth == kth else np.flatnonzero(key == key)
        if index.size > limit:  # ties at the limit: the earlier points
            below = index[key[index] < kth]
            index = np.concatenate([below, index[key[index] == kth][:limit - below.size]])
    else:
        index = np.arange(key.size)
    index = index[np.lexsort((index, key[index]))]
    return index if candidates is None else candidates[index]


def binding_points(points: PointValues | None, limit: int = BINDING_POINTS) -> np.ndarray:
    """The sensor points whose rows are closest to binding: (m, 4) rows [x, y, row value, h],
    m <= ``limit``, the least row values in ascending order (ties: the earlier point first).

    A point whose row value or h is NaN or inf is left out (the others fill its place). O(N)
    (:func:`_least`), not a sort.

    Args:
        points: a result's :attr:`rcbf_ros.core.filter.FilterResult.points`, or None (no
            points: (0, 4)).
        limit: most rows returned (>= 0).
    """
    if points is None or limit <= 0 or not points.values.size:
        return np.empty((0, 4))
    values, h = points.values, points.h
    index = _least(values, limit)
    if not (np.isfinite(values[index]).all() and np.isfinite(h[index]).all()):
        # a value that is not finite among the least (the filter's data check makes this
        # rare): again with those points moved past every other
        index = _least(np.where(np.isfinite(values) & np.isfinite(h), values, math.inf),
                       limit)  # those moved past appear only where too few others are
    rows = np.stack([points.x[index], points.y[index], values[index], h[index]], axis=1)
    return rows[np.isfinite(rows).all(axis=1)]


def info_sections(*, u: Sequence[float] | np.ndarray, u_rl: Sequence[float] | np.ndarray | None,
                  fail_safe: bool, status: str, result: Any = None,
                  state: Sequence[float] | np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The sections of one answer (:data:`INFO_SECTIONS`).

    Args:
        u: (n_u,) the command published.
        u_rl: (n_u,) the proposal as received, or None when it was unusable (then, as for
            one of another length or with NaN or inf, ``u_rl`` is ``u`` and ``u_s`` zero).
        fail_safe: whether ``u`` is the fail-safe action.
        status: a key of :data:`STATUS_CODES` (a solver status or a fail-safe reason).
        result: the filter's ``FilterResult`` when the QP was set up, else None.
        state: (n_x,) the state the command answers, or None.
    """
    command = np.asarray(u, dtype=np.float64).reshape(-1)
    proposal = command if u_rl is None else np.asarray(u_rl, dtype=np.float64).reshape(-1)
    if proposal.shape != command.shape or not np.all(np.isfinite(proposal - command)):
        proposal = command  # not a usable proposal: no correction to report
    sections: dict[str, np.ndarray] = {
        'u': command, 'u_rl': proposal, 'u_s': command - proposal,
        'fail_safe': np.array([1.0 if fail_safe else 0.0]),
        'status': np.array([float(STATUS_CODES.get(status, UNKNOWN_STATUS))]),
    }
    optional: list[tuple[str, Any]] = []
    if result is not None:
        optional += [('h', result.h), ('constraint', result.constraint_values),
                     ('slack', [result.slack]), ('needed_slack', [result.needed_slack]),
                     ('solve_time_s', [result.solve_time_s])]
    if state is not None:
        optional.append(('state', state))
    if result is not None:
        optional.append(('binding_points', binding_points(getattr(result, 'points', None))))
    for label, values in optional:
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        if array.size and np.all(np.isfinite(array)):
            sections[label] = array
    return sections

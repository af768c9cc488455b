"""The Unicycle filter between samples and under latency: violations with and without the
sampled-data margin, and what the margin costs.

    python benchmarks/bench_sampled_data.py [--worlds 200] [--period 0.1] [--latency 0.05]

Fine-step simulation of the TRUE dynamics (rcbf_ros/envs/unicycle.py: x_dot = g(x) (u + u_d),
u_d = -0.1 cos(theta) [1, 0]), 1 ms Euler steps. The filter samples the state every period T;
its command acts from L after the sample and is held for T (before the first one acts the
robot stands still). Random worlds (seeded): a robot 2-3 m from a circle, driving at it at
2.5 m/s towards a goal behind it, a second circle nearby (1 m clear of the start),
alpha U[5, 15]; the same worlds with
the circles as sensor points (``footprint``, :meth:`SafetyFilter.set_points`, 24 points on
each circle). A violation is a fine step whose barrier h (the look-ahead point, margin
included) is below 0 for some circle or point. Printed per case: worlds with a violation, the
least h over every fine step, the mean correction ||u_S|| per decision and the mean distance
left to the goal after 2.5 s (the start is 3.6-5.4 m from it).

The fine-step simulation (:func:`simulate`) is also what test/unit/test_sampled_data.py runs,
on a few worlds.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
import sys
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rcbf_ros.core.barriers import CircleObstacles  # noqa: E402
from rcbf_ros.core.dynamics import Unicycle  # noqa: E402
from rcbf_ros.core.filter import SafetyFilter  # noqa: E402
from rcbf_ros.core.rcbf import RCBFProblem  # noqa: E402

FINE_STEP_S = 1e-3
"""The simulation's Euler step (s)."""
LOOKAHEAD = 0.03
"""l_p of the barriers (config/unicycle.yaml)."""
MARGIN = 0.1
"""obstacles.margin (config/unicycle.yaml)."""
SPEED = 2.5
"""The proposals' forward speed (m/s), the input limit."""
BOX_MEAN = (-0.05, 0.0, 0.0)
"""The disturbance box of config/unicycle.yaml: mean +/- 2 std covers g(x) u_d exactly."""
BOX_STD = (0.025, 0.025, 0.0)
"""Its std (k_c = 2)."""
POINTS_PER_CIRCLE = 24
"""Sensor points on each circle in the points case."""


class World(NamedTuple):
    """One random scene."""

    start: np.ndarray
    """(3,) the robot's start [x, y, theta], at least 1 m clear of every circle."""
    goal: np.ndarray
    """(2,) where the proposals steer to (behind the first circle)."""
    centers: np.ndarray
    """(2, 2) the circles' centres."""
    radii: np.ndarray
    """(2,) their radii."""
    alpha: float
    """The class-K gain of the rows."""


def random_worlds(count: int, seed: int) -> list[World]:
    """``count`` worlds (module docstring), the same for a seed."""
    rng = np.random.default_rng(seed)
    worlds = []
    for _ in range(count):
        bearing = rng.uniform(-math.pi, math.pi)
        distance = rng.uniform(2.0, 3.0)
        start_xy = -distance * np.array([math.cos(bearing), math.sin(bearing)])
        heading = bearing + rng.uniform(-0.3, 0.3)
        radii = rng.uniform(0.2, 0.6, 2)
        while True:  # the second circle at least 1 m clear of the start
            side = rng.uniform(-math.pi, math.pi)
            second = rng.uniform(1.2, 2.0) * np.array([math.cos(side), math.sin(side)])
            if np.linalg.norm(second - start_xy) > radii[1] + MARGIN + 1.0:
                break
        worlds.append(World(
            start=np.array([*start_xy, heading]), goal=-0.8 * start_xy + rng.normal(0, 0.2, 2),
            centers=np.array([[0.0, 0.0], second]), radii=radii,
            alpha=float(rng.uniform(5.0, 15.0))))
    return worlds


def circle_points(world: World) -> np.ndarray:
    """(2 POINTS_PER_CIRCLE, 2) points on the world's circles."""
    angles = np.linspace(0.0, 2.0 * math.pi, POINTS_PER_CIRCLE, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return np.concatenate([c + r * ring for c, r in zip(world.centers, world.radii)])


def build_filter(world: World, *, points: bool, period: float, latency: float
                 ) -> SafetyFilter:
    """The world's filter: its circles as rows, or (``points``) as sensor points."""
    system = Unicycle()
    circles = CircleObstacles(centers=tuple(map(tuple, world.centers.tolist())),
                              radii=tuple(world.radii.tolist()), margin=MARGIN,
                              heading_index=2, lookahead=LOOKAHEAD)
    footprint = None
    families: tuple = (circles,)
    if points:
        families = ()
        footprint = CircleObstacles(centers=((0.0, 0.0),), radii=(0.0,), margin=MARGIN,
                                    heading_index=2, lookahead=LOOKAHEAD)
    problem = RCBFProblem(system=system, families=families, alpha=world.alpha, k_c=2.0,
                          input_weight=(1.0, 0.01))
    safety_filter = SafetyFilter(problem, footprint=footprint, control_period_s=period,
                                 latency_s=latency)
    if points:
        safety_filter.set_points(circle_points(world))
    return safety_filter


def true_h(states: np.ndarray, centers: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """h at the look-ahead point of each state against each centre: states (W, 3), centers
    (W, k, 2), reach (W, k) -> (W, k)."""
    p = states[:, :2] + LOOKAHEAD * np.stack([np.cos(states[:, 2]), np.sin(states[:, 2])], 1)
    d = p[:, None, :] - centers
    return (d * d).sum(-1) - reach * reach


def true_derivative(states: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """The true x_dot of rcbf_ros/envs/unicycle.py, vectorised: (W, 3), (W, 2) -> (W, 3)."""
    theta = states[:, 2]
    v = commands[:, 0] - 0.1 * np.cos(theta)  # u + u_d, u_d = -0.1 cos(theta) [1, 0]
    return np.stack([v * np.cos(theta), v * np.sin(theta), commands[:, 1]], axis=1)


def proposal(state: np.ndarray, goal: np.ndarray) -> list[float]:
    """Drive at SPEED, steering to the goal (gain 3, within the limits)."""
    error = math.atan2(goal[1] - state[1], goal[0] - state[0]) - state[2]
    error = math.atan2(math.sin(error), math.cos(error))
    return [SPEED, max(-SPEED, min(SPEED, 3.0 * error))]


class Outcome(NamedTuple):
    """One case over its worlds."""

    violated: np.ndarray
    """(W,) bool: some fine step had h < 0."""
    least_h: np.ndarray
    """(W,) the least h over every fine step."""
    correction: float
    """Mean ||u_S|| per decision."""
    decisions: int
    """Filter calls."""
    remaining: float
    """Mean distance left to the goal at the end (m): what the margin costs in progress."""


def simulate(worlds: list[World], *, period: float, latency: float, tightened: bool,
             points: bool = False, duration: float = 2.5) -> Outcome:
    """Run every world for ``duration`` s (module docstring). ``tightened``: the filter knows
    T and L (its rows carry the margin); else its rows are the continuous-time ones, under the
    same hold and delay."""
    filters = [build_filter(w, points=points, period=period if tightened else 0.0,
                            latency=latency if tightened else 0.0) for w in worlds]
    if points:
        centers = np.stack([circle_points(w) for w in worlds])
        reach = np.full(centers.shape[:2], MARGIN)
    else:
        centers = np.stack([w.centers for w in worlds])
        reach = np.stack([w.radii for w in worlds]) + MARGIN
    states = np.stack([w.start for w in worlds])
    commands = np.zeros((len(worlds), 2))
    period_steps = max(1, round(period / FINE_STEP_S))
    delay_steps = round(latency / FINE_STEP_S)
    pending: list[tuple[int, np.ndarray]] = []  # (fine step it acts from, commands)
    least = true_h(states, centers, reach).min(axis=1)
    corrections: list[float] = []
    for step in range(round(duration / FINE_STEP_S)):
        if step % period_steps == 0:
            sampled = []
            for i, (world, safety_filter) in enumerate(zip(worlds, filters)):
                result = safety_filter.filter(states[i], proposal(states[i], world.goal),
                                              BOX_MEAN, BOX_STD)
                sampled.append(result.u_safe)
                corrections.append(float(np.linalg.norm(result.u_s)))
            pending.append((step + delay_steps, np.array(sampled)))
        while pending and pending[0][0] <= step:
            commands = pending.pop(0)[1]
        states = states + FINE_STEP_S * true_derivative(states, commands)
        least = np.minimum(least, true_h(states, centers, reach).min(axis=1))
    goals = np.stack([w.goal for w in worlds])
    remaining = float(np.linalg.norm(states[:, :2] - goals, axis=1).mean())
    return Outcome(least < 0.0, least, float(np.mean(corrections)), len(corrections),
                   remaining)


TITLE = 'Between samples and under latency: violations with and without the margin'


def run(worlds: list[World], period: float, latency: float) -> list[str]:
    """The table: violations, least h, correction and progress per case."""
    table = ['| obstacles | rows | worlds violated | least h | mean norm of u_S | decisions | '
             'mean distance left to the goal (m) |', '|---|---|---|---|---|---|---|']
    for points in (False, True):
        for tightened in (False, True):
            out = simulate(worlds, period=period, latency=latency, tightened=tightened,
                           points=points)
            table.append(f"| {'sensor points' if points else 'circles'} | "
                         f"{'with margin' if tightened else 'T = L = 0'} | "
                         f'{int(out.violated.sum())} / {len(worlds)} | '
                         f'{out.least_h.min():.4f} | {out.correction:.3f} | '
                         f'{out.decisions} | {out.remaining:.2f} |')
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--worlds', type=int, default=200)
    parser.add_argument('--period', type=float, default=0.1, help='T (s)')
    parser.add_argument('--latency', type=float, default=0.05, help='L (s)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.worlds < 1:
        parser.error('--worlds must be >= 1')
    worlds = random_worlds(args.worlds, args.seed)
    table = run(worlds, args.period, args.latency)
    from benchmarks._results import publish_section
    options = ''.join(f' --{name} {value}' for name, value, default in (
        ('worlds', args.worlds, 200), ('period', args.period, 0.1),
        ('latency', args.latency, 0.05), ('seed', args.seed, 0)) if value != default)
    publish_section(TITLE, script='bench_sampled_data.py' + options, write=args.write, blocks=[
        f'T = {args.period} s, L = {args.latency} s: {args.worlds} random worlds (seed '
        f'{args.seed}), 1 ms Euler steps of the true Unicycle over 2.5 s, commands held for T '
        'and computed from states L old. "T = L = 0": the continuous-time rows under the same '
        'hold and delay; "with margin": the rows tightened for T and L '
        '(docs/SAFETY_FILTER.md, "Between samples and under latency"). A world is violated '
        'when h at the look-ahead point (margin included) falls below 0 at a fine step. '
        'norm of u_S: the correction per decision; the last column: what the margin costs in '
        'progress (the start is 3.6-5.4 m from the goal).', table])
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

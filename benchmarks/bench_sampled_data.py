"""The Unicycle and PVTOL filters between samples and under latency: violations with and
without the sampled-data margin, and what the margin costs; and why Car Following's is refused.

    python benchmarks/bench_sampled_data.py [--worlds 200] [--period 0.1] [--latency 0.05]
        [--pvtol-worlds 50] [--pvtol-period 0.02] [--pvtol-latency 0.02]
        [--car-episodes 20] [--cars-only]

Fine-step simulation of the TRUE dynamics (rcbf_ros/envs/unicycle.py: x_dot = g(x) (u + u_d),
u_d = -0.1 cos(theta) [1, 0]), 1 ms Euler steps. The filter samples the state every period T;
its command acts from L after the sample and is held for T (before the first one acts the
robot stands still). Random worlds (seeded): a robot 2-3 m from a circle, driving at it at
2.5 m/s towards a goal behind it, a second circle nearby (1 m clear of the start),
alpha U[5, 15]; the same worlds with
the circles as sensor points (``footprint``, :meth:`SafetyFilter.set_points`, 24 points on
each circle). A violation is a fine step whose barrier h (the look-ahead point, margin
included) is below 0 for some circle or point. Printed per case: worlds with a violation, the
least h over every fine step, the mean correction ||u_S|| per decision, the mean distance
left to the goal after 2.5 s (the start is 3.6-5.4 m from it), the fail-safe decisions and the
median decision time. Each case runs without the margin (T = L = 0), with the constant margin
of the largest input (``constant margin``) and with the margin of the command, nu0 + c^T |u|
(``margin of the command``, :mod:`rcbf_ros.core.sampled_data`).

The two margins side by side (:func:`run_margins`): how close the Unicycle comes to a 0.6 m
circle it drives straight at (:func:`stopping_distance`; config/unicycle.yaml's limits and the
README's TurtleBot's, 0.3 m/s), and whether config/pvtol.yaml's filter answers a level hover
with its fail-safe at tau = 20 and 40 ms (:func:`hover_answer`).

PVTOL (:func:`simulate_pvtol`, the interval margin of its cascaded rows): random transfer
layouts, the drone in hover near a circle, aggressive proposals through it, 1 ms Euler steps of
the true PVTOL; printed with and without the margin: worlds where a row's (cascaded) barrier or
a base set (a disc with its margin, a band) was left at some fine step, the least base value,
the fail-safe decisions (rows infeasible), the median margin of the commands decided and the
median decision time, without the margin, with the constant one and with the command's.

Car Following (:func:`simulate_cars`, its own section; ``--cars-only`` runs it alone): the
bound behind the refusal of its margin (:class:`_car_following_bound.CarFollowingBound`)
on the shipped episode and random starts around it, T = L in 10, 20, 50 ms, 1 ms Euler steps of
the true cars, car 4's proposal +5 m/s^2 into car 3; printed with and without the margin: the
decisions with a command meeting every row (until a collision), the row and base sets left,
the least gap, how often each braking switch was within reach, which rows failed and what
their margins were made of (the braking terms, car 4's own input range, the box), the median
margin and the time of a decision.

The fine-step simulations are also what test/unit/test_sampled_data.py,
test/unit/test_sampled_data_interval.py and test/unit/test_sampled_data_cars.py run, on a few
worlds.
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

from _car_following_bound import CarFollowingBound  # noqa: E402  (a sibling)

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


def with_constant_margin(safety_filter: SafetyFilter, command_linear: bool) -> SafetyFilter:
    """``safety_filter`` as it is (``command_linear``), else with the constant margin of the
    largest input in place of the one that follows the command (for comparison)."""
    if safety_filter._margin is not None:
        safety_filter._margin.command_linear = command_linear
    return safety_filter


def build_filter(world: World, *, points: bool, period: float, latency: float,
                 command_linear: bool = True) -> SafetyFilter:
    """The world's filter: its circles as rows, or (``points``) as sensor points;
    ``command_linear`` False: the constant margin (:func:`with_constant_margin`)."""
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
    safety_filter = with_constant_margin(SafetyFilter(
        problem, footprint=footprint, control_period_s=period, latency_s=latency),
        command_linear)
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
    fail_safe: int = 0
    """Decisions answered with the fail-safe."""
    decision_time_s: float = 0.0
    """Median time of one decision (s)."""


def simulate(worlds: list[World], *, period: float, latency: float, tightened: bool,
             points: bool = False, duration: float = 2.5, command_linear: bool = True
             ) -> Outcome:
    """Run every world for ``duration`` s (module docstring). ``tightened``: the filter knows
    T and L (its rows carry the margin); else its rows are the continuous-time ones, under the
    same hold and delay. ``command_linear`` False: the constant margin."""
    import time
    filters = [build_filter(w, points=points, period=period if tightened else 0.0,
                            latency=latency if tightened else 0.0,
                            command_linear=command_linear) for w in worlds]
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
    times: list[float] = []
    fail_safe = 0
    for step in range(round(duration / FINE_STEP_S)):
        if step % period_steps == 0:
            sampled = []
            for i, (world, safety_filter) in enumerate(zip(worlds, filters)):
                asked = proposal(states[i], world.goal)
                started = time.perf_counter()
                result = safety_filter.filter(states[i], asked, BOX_MEAN, BOX_STD)
                times.append(time.perf_counter() - started)
                fail_safe += bool(result.fail_safe)
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
                   remaining, fail_safe, float(np.median(times)))


def stopping_distance(*, limits: tuple[float, float], period: float, latency: float,
                      command_linear: bool, radius: float = 0.6, alpha: float = 2.0,
                      start: float = 4.0) -> float:
    """How close (m) the Unicycle's centre comes to a circle's centre when it drives straight
    at it at full speed: the circle ``radius`` (obstacles.margin :data:`MARGIN`, look-ahead
    :data:`LOOKAHEAD`, as config/unicycle.yaml), the limits +/- (v, omega) ``limits``, alpha
    2, no disturbance, 1 ms Euler steps of the nominal Unicycle, commands held for T and
    computed from states L old, until the robot has stood still for a second (or 60 s).
    ``command_linear`` False: the constant margin. The circle's edge with its margin lies at
    radius + MARGIN = 0.7 m."""
    speed, turn = limits
    system = Unicycle(u_min=(-speed, -turn), u_max=(speed, turn))
    circles = CircleObstacles(centers=((0.0, 0.0),), radii=(radius,), margin=MARGIN,
                              heading_index=2, lookahead=LOOKAHEAD)
    problem = RCBFProblem(system=system, families=(circles,), alpha=alpha,
                          input_weight=(1.0, 0.01))
    safety_filter = with_constant_margin(SafetyFilter(
        problem, control_period_s=period, latency_s=latency), command_linear)
    state, command = np.array([-start, 0.0, 0.0]), np.zeros(2)
    period_steps = max(1, round(period / FINE_STEP_S))
    delay_steps = round(latency / FINE_STEP_S)
    pending: list[tuple[int, np.ndarray]] = []
    closest, still = math.inf, 0
    for step in range(round(60.0 / FINE_STEP_S)):
        if step % period_steps == 0:
            result = safety_filter.filter(state, [speed, 0.0])
            pending.append((step + delay_steps, np.array(result.u_safe)))
        while pending and pending[0][0] <= step:
            command = pending.pop(0)[1]
        state = state + FINE_STEP_S * np.array([command[0] * math.cos(state[2]),
                                                command[0] * math.sin(state[2]), command[1]])
        closest = min(closest, math.hypot(state[0], state[1]))
        still = still + 1 if abs(command[0]) < 1e-3 else 0
        if still * FINE_STEP_S >= 1.0:
            break
    return closest


def hover_answer(*, horizon: float, command_linear: bool) -> str:
    """config/pvtol.yaml's filter (alpha 1) with T = L = ``horizon`` / 2 in a level hover, the
    hover command 0 proposed: 'passes' or 'fail-safe'."""
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.parameters.rules import find_config, load_params
    problem = filter_config_from_params(load_params(find_config('pvtol'), 'safety_filter')
                                        ).problem
    safety_filter = with_constant_margin(SafetyFilter(
        problem, control_period_s=horizon / 2, latency_s=horizon / 2, slack_tolerance=1e-4),
        command_linear)
    result = safety_filter.filter([-4.5, 2.0, 0.0, 0.0, 0.0, 1.0, -4.5], [0.0, 0.0])
    return 'fail-safe' if result.fail_safe else 'passes'


# ------------------------------------------------------------------ PVTOL (cascaded rows)
PVTOL_BOX_STD = (0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0)
"""The PVTOL filter's disturbance box (mean 0, k_c = 2): 0.2 rad/s on theta covers the true
attitude error 0.1 ((f - 1) - sin th) while the thrust stays in [0, 2]."""
PVTOL_TILT = 1.3
"""The proposals' largest tilt (rad): beyond the tilt band (pi/3), so the filter must act."""


class PVTOLWorld(NamedTuple):
    """One random PVTOL scene."""

    params: dict
    """The filter's parameters (config/pvtol.yaml with a random layout)."""
    start: np.ndarray
    """(7,) the start state, a level hover."""
    goal: np.ndarray
    """(2,) where the proposals steer to."""


def pvtol_worlds(count: int, seed: int) -> list[PVTOLWorld]:
    """``count`` random PVTOL worlds: a random transfer layout (rcbf_ros/envs/layouts.py), the
    start 0.6-1.2 m from one of its circles' edges, the goal beyond that circle, so that the
    aggressive proposals (:func:`pvtol_proposal`) fly at it."""
    from rcbf_ros.envs.layouts import layout_to_params, pvtol_random_layout
    from rcbf_ros.parameters.rules import find_config, load_params
    rng = np.random.default_rng(seed)
    base = load_params(find_config('pvtol'), 'safety_filter')
    worlds = []
    while len(worlds) < count:
        obstacles, _ = pvtol_random_layout(int(rng.integers(2 ** 31 - 1)))
        target = obstacles[int(rng.integers(len(obstacles)))]
        bearing = rng.uniform(-math.pi, math.pi)
        away = np.array([math.cos(bearing), math.sin(bearing)])
        start = np.array([target.x, target.y]) + (target.radius + rng.uniform(0.6, 1.2)) * away
        clear = all(math.hypot(*(start - (o.x, o.y))) > o.radius + MARGIN + 0.3
                    for o in obstacles)
        if not (clear and abs(start[0]) < 5.0 and abs(start[1]) < 2.0):
            continue
        params = dict(base, alpha=float(rng.uniform(10.0, 25.0)))
        layout = layout_to_params(obstacles)
        layout.pop('obstacles.shape')
        params.update(layout)
        goal = np.array([target.x, target.y]) - 2.0 * away
        worlds.append(PVTOLWorld(params, np.array([*start, 0.0, 0.0, 0.0, 1.0, start[0]]),
                                 goal))
    return worlds


def pvtol_proposal(state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """An aggressive go-to-goal (rcbf_ros/envs/nominal.py, high gains, tilt up to
    :data:`PVTOL_TILT`): it flies into what lies in its way."""
    from rcbf_ros.envs.nominal import pvtol_go_to_goal
    return pvtol_go_to_goal(state, tuple(goal), position_gain=2.0, velocity_gain=0.5,
                            max_acceleration=1.5, max_tilt=PVTOL_TILT, attitude_gain=6.0)


def pvtol_true_derivative(state: np.ndarray, command: np.ndarray) -> np.ndarray:
    """The true PVTOL of rcbf_ros/envs/pvtol.py without the operator's noise: the nominal
    model plus the attitude error 0.1 ((f - 1) - sin th) on theta_dot."""
    _, _, v1, v2, theta, thrust, x_h = state
    return np.array([v1, v2, -math.sin(theta) * thrust, math.cos(theta) * thrust - 1.0,
                     command[0] + 0.1 * ((thrust - 1.0) - math.sin(theta)), command[1],
                     3.5 * (state[0] - x_h)])


class PVTOLOutcome(NamedTuple):
    """The PVTOL case over its worlds."""

    violated: np.ndarray
    """(W,) bool: some fine step left the set of some row (its cascaded barrier below 0)."""
    touched: np.ndarray
    """(W,) bool: some fine step left a base set (an obstacle's disc with its margin, a band)."""
    least_h: np.ndarray
    """(W,) the least base barrier value over every fine step."""
    verified: np.ndarray
    """(W,) bool: a row set was left while every decision so far met its rows (no fail-safe
    yet: the fail-safe action is outside the guarantee)."""
    fail_safe: int
    """Decisions answered with the fail-safe."""
    decisions: int
    """Filter calls."""
    margins: np.ndarray
    """(decisions, K) the margins of every decision (empty without them)."""
    decision_time_s: float
    """Median time of one decision (s)."""


def simulate_pvtol(worlds: list[PVTOLWorld], *, period: float, latency: float,
                   tightened: bool, duration: float = 3.0, command_linear: bool = True
                   ) -> PVTOLOutcome:
    """Run every PVTOL world for ``duration`` s under 1 ms Euler steps of the true PVTOL, the
    commands held for T and computed from states L old (as :func:`simulate`);
    ``command_linear`` False: the constant margin. The margins recorded are those of the
    commands decided."""
    import time

    from rcbf_ros.core.barriers import Cascaded
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.core.lie_closed_form import ClosedFormTerms
    from rcbf_ros.core.sampled_data import sampled_data_margin
    period_steps = max(1, round(period / FINE_STEP_S))
    delay_steps = round(latency / FINE_STEP_S)
    box = ((0.0,) * 7, PVTOL_BOX_STD)
    violated, touched, least_h, verified, margins, times = [], [], [], [], [], []
    fail_safe = decisions = 0
    for world in worlds:
        problem = filter_config_from_params(world.params).problem
        safety_filter = with_constant_margin(SafetyFilter(
            problem, control_period_s=period if tightened else 0.0,
            latency_s=latency if tightened else 0.0, slack_tolerance=1e-3), command_linear)
        margin = sampled_data_margin(problem, control_period_s=period, latency_s=latency,
                                     command_linear=command_linear)
        top = ClosedFormTerms.from_problem(problem)
        bases = RCBFProblem(system=problem.system, families=tuple(
            f.base if type(f) is Cascaded else f for f in problem.families))
        while any(type(f) is Cascaded for f in bases.families):
            bases = RCBFProblem(system=problem.system, families=tuple(
                f.base if type(f) is Cascaded else f for f in bases.families))
        base = ClosedFormTerms.from_problem(bases)
        state, command = world.start.copy(), np.zeros(2)
        pending: list[tuple[int, np.ndarray]] = []
        low_top, low_base = math.inf, math.inf
        failed = broken = False
        for step in range(round(duration / FINE_STEP_S)):
            if step % period_steps == 0:
                started = time.perf_counter()
                result = safety_filter.filter(state, pvtol_proposal(state, world.goal), *box)
                times.append(time.perf_counter() - started)
                decisions += 1
                fail_safe += bool(result.fail_safe)
                failed = failed or bool(result.fail_safe)
                if tightened:
                    rest, linear = margin.split_rows(state.tolist(), *box)
                    margins.append(rest + linear @ np.abs(result.u_safe))
                pending.append((step + delay_steps, np.array(result.u_safe)))
            while pending and pending[0][0] <= step:
                command = pending.pop(0)[1]
            state = state + FINE_STEP_S * pvtol_true_derivative(state, command)
            low_top = min(low_top, float(top.terms(state).h.min()))
            broken = broken or (low_top < 0.0 and not failed)
            low_base = min(low_base, float(base.terms(state).h.min()))
        violated.append(low_top < 0.0)
        touched.append(low_base < 0.0)
        least_h.append(low_base)
        verified.append(broken)
    return PVTOLOutcome(np.array(violated), np.array(touched), np.array(least_h),
                        np.array(verified), fail_safe, decisions, np.array(margins),
                        float(np.median(times)))


# ------------------------------------------------------------------ Car Following
CAR_LIMIT = 10.0
"""|u_4| <= 10 m/s^2 (the shipped config has no limits; the margin needs them)."""
CAR_DURATION_S = 6.0
"""The shipped episode's length: 300 steps of 20 ms."""
CAR_PERIODS = (0.01, 0.02, 0.05)
"""T = L (s) of the Car Following table."""
CAR_SETTINGS = ((50.0, 0.0), (50.0, 0.1), (10.0, 0.1))
"""(input limit (m/s^2), unknown gain d_i of cars 1, 2, 3, 5) of the Car Following table: a
limit the continuous-time rows of the shipped episode never reach, with the model exact but
for the leader's sine and with the env's gains; a road car's limit with the env's gains."""


def car_problem(limit: float = CAR_LIMIT) -> RCBFProblem:
    """config/car_following.yaml's rows (cascaded gaps 3-4 and 4-5, alpha 5, gamma 8, k_c 2)
    with input limits +/- ``limit``."""
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.parameters.rules import find_config, load_params
    params = load_params(find_config('car_following'), 'safety_filter')
    params.update({'input_limits.min': [-limit], 'input_limits.max': [limit]})
    return filter_config_from_params(params).problem


def car_box(gain: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of the disturbance box, k_c = 2: the unknown gains d_i = ``gain`` of cars 2,
    3, 5 times their largest prior accelerations near v_des (k_v 3 m/s + k_b G), the leader's
    tracking and sine (up to 25 m/s^2, the prior holds 0) on car 1; 0 on the positions and on
    car 4. The benchmark counts the fine steps where the true disturbance leaves it."""
    std = np.zeros(10)
    std[1] = 25.0 / 2.0
    std[3] = std[5] = gain * (4.0 * 3.0 + 20.0 * 6.0) / 2.0
    std[9] = gain * (4.0 * 3.0 + 20.0 * 12.0) / 2.0
    return np.zeros(10), std


def car_starts(count: int, seed: int) -> list[np.ndarray]:
    """The shipped start (config/car_following.yaml, the env's seed 0) and ``count`` random
    ones around it (seeded): every position moved by U[-1.5, 1.5] m, every car's speed by
    U[-1, 1] m/s on top of the shared draw, car 4 at 35 + U[-2, 2] m/s; a draw outside a row
    set (h* < 0 or h < 0 for a gap row) is drawn again (a filter keeps a set, it does not
    enter one)."""
    from rcbf_ros.core.lie_closed_form import ClosedFormTerms
    from rcbf_ros.envs.car_following import CarFollowingEnv
    env = CarFollowingEnv()
    env.reset(seed=0)
    starts = [env.state]
    problem = car_problem()
    terms = ClosedFormTerms.from_problem(problem)
    delta = problem.families[0].base.delta
    rng = np.random.default_rng(seed)
    while len(starts) <= count:
        state = starts[0].copy()
        state[0::2] += rng.uniform(-1.5, 1.5, 5)
        state[1::2] += rng.uniform(-1.0, 1.0, 5)
        state[7] = 35.0 + rng.uniform(-2.0, 2.0)
        gaps = np.abs(state[[4, 6]] - state[[6, 8]])
        if (terms.terms(state).h >= 0.0).all() and (gaps >= delta).all():
            starts.append(state)
    return starts


class CarOutcome(NamedTuple):
    """One Car Following case over its episodes."""

    feasible: np.ndarray
    """(E,) per episode, the decisions with a command meeting every row."""
    decided: np.ndarray
    """(E,) per episode, the decisions before it ended (6 s or a collision)."""
    first_failed: np.ndarray
    """(E,) the time of each episode's first decision without such a command (s; inf)."""
    row_left: np.ndarray
    """(E,) whether a row set (h* >= 0) was left at some fine step."""
    base_left: np.ndarray
    """(E,) whether a base set (a gap of delta = 3.75 m) was left at some fine step."""
    least_gap: np.ndarray
    """(E,) the least gap |p_3 - p_4|, |p_4 - p_5| over the fine steps (m); 0: a collision,
    where the episode ends."""
    reach_front: float
    """The fraction of decisions where car 3 may start braking within tau (row 3-4's jump)."""
    reach_rear: float
    """The same for car 5 ceasing to brake (row 4-5's jump)."""
    failed_rows: tuple[int, int]
    """(row 3-4, row 4-5): how often each had no command within the limits meeting it."""
    shares: tuple[float, float, float]
    """Median shares of nu0 over the rows that failed: the braking terms', car 4's input
    range's (nu0 less nu0 with the limits 0, in the motion only) and the box's (nu0 less nu0
    with the box 0)."""
    median_margin: float
    """Median nu0 + c |u| over the rows of the decisions (the command decided or proposed)."""
    box_left: int
    """Fine steps where the true disturbance left the box (the guarantee's premise)."""
    decision_time_s: float
    """Median time of the margin and the rows at one decision (s)."""


def car_decide(upper: np.ndarray, lg: np.ndarray, proposal: float, limit: float
               ) -> float | None:
    """The command nearest ``proposal`` within +/- ``limit`` meeting upper + lg u >= 0 (the
    QP in one input), or None where no command does."""
    low, high = -limit, limit
    for a, b in zip(upper, lg):
        if b > 0.0:
            low = max(low, -a / b)
        elif b < 0.0:
            high = min(high, -a / b)
        elif a < 0.0:
            return None
    return None if low > high else min(max(proposal, low), high)


def simulate_cars(starts: list[np.ndarray], *, period: float, latency: float,
                  tightened: bool, gain: float = 0.1, limit: float = CAR_LIMIT,
                  duration: float = CAR_DURATION_S,
                  proposal: float = 5.0) -> CarOutcome:
    """Run every start for ``duration`` s under 1 ms Euler steps of the true Car Following
    (rcbf_ros/envs/car_following.py: the leader's sine, the gains 1 + ``gain``), car 4's
    command held for T and computed from states L old (as :func:`simulate`); the proposal a
    constant ``proposal`` m/s^2 into car 3 (the env's nominal controller). A decision meets
    the rows (tightened by :class:`_car_following_bound.CarFollowingBound` when
    ``tightened``, split by the sign of u) within +/- ``limit``, or answers the fail-safe 0
    (config/car_following.yaml's fail_safe_action: car 4 coasts)."""
    from dataclasses import replace
    import time

    from rcbf_ros.core.lie_closed_form import ClosedFormTerms
    from rcbf_ros.envs.car_following import CarFollowingEnv
    problem = car_problem(limit)
    terms = ClosedFormTerms.from_problem(problem)
    horizon = period + latency
    bound = CarFollowingBound(problem, horizon)
    still = CarFollowingBound(replace(problem, system=replace(
        problem.system, u_min=(0.0,), u_max=(0.0,))), horizon)
    mean, std = car_box(gain)
    zero = np.zeros(10)
    reach_box = np.abs(mean) + problem.k_c * std
    env = CarFollowingEnv(disturbance_gain=gain)
    period_steps = max(1, round(period / FINE_STEP_S))
    delay_steps = round(latency / FINE_STEP_S)
    feasible, decided, first_failed, row_left, base_left, least_gap = [], [], [], [], [], []
    front = rear = box_left = 0
    failed_rows = np.zeros(2, dtype=np.int64)
    shares: list[list[float]] = [[], [], []]
    margins, times = [], []
    decisions = 0
    for start in starts:
        state, command = start.copy(), 0.0
        pending: list[tuple[int, float]] = []
        met, made, first = 0, 0, math.inf
        low_row = low_base = low_gap = math.inf
        for step in range(round(duration / FINE_STEP_S)):
            t = step * FINE_STEP_S
            if step % period_steps == 0:
                started = time.perf_counter()
                at = terms.terms(state)
                rho = at.grad_h @ mean - problem.k_c * np.abs(at.grad_h) @ std
                upper = at.lf_h + rho + problem.alpha * at.h
                lg = at.lg_h[:, 0]
                if tightened:  # upper - nu0 + (lg -/+ c) u >= 0 for either sign of u
                    rest, linear, jumps = bound.parts(state, mean, std)
                    answer = car_decide(np.concatenate([upper - rest] * 2),
                                        np.concatenate([lg - linear[:, 0],
                                                        lg + linear[:, 0]]),
                                        proposal, limit)
                else:
                    answer = car_decide(upper, lg, proposal, limit)
                times.append(time.perf_counter() - started)
                if not tightened:  # the margin it would have had, untimed
                    rest, linear, jumps = bound.parts(state, mean, std)
                decisions += 1
                made += 1
                front += jumps[0] > 0.0
                rear += jumps[1] > 0.0
                chosen = proposal if answer is None else answer
                margins.extend(rest + linear[:, 0] * abs(chosen))
                if answer is None:
                    first = min(first, t)
                    # a row fails alone where no command within the limits meets it
                    best = (upper - rest * tightened
                            + np.maximum(np.abs(lg) - linear[:, 0] * tightened, 0.0) * limit)
                    alone = best < 0.0
                    failed_rows += alone
                    for row in np.flatnonzero(alone):
                        shares[0].append(jumps[row] / rest[row])
                        shares[1].append(1.0 - still.parts(state, mean, std)[0][row]
                                         / rest[row])
                        shares[2].append(1.0 - bound.parts(state, zero, zero)[0][row]
                                         / rest[row])
                met += answer is not None
                pending.append((step + delay_steps, 0.0 if answer is None else answer))
            while pending and pending[0][0] <= step:
                command = pending.pop(0)[1]
            accelerations = env.true_accelerations(state, np.array([command]), t)
            f, _ = env.nominal_terms(state)
            psi = accelerations - f[1::2]
            psi[3] -= command
            box_left += bool((np.abs(psi) > reach_box[1::2] + 1e-9).any())
            derivative = np.empty(10)
            derivative[0::2], derivative[1::2] = state[1::2], accelerations
            state = state + FINE_STEP_S * derivative
            at = terms.terms(state)
            gaps = np.abs(state[[4, 6]] - state[[6, 8]])
            low_row = min(low_row, float(at.h.min()))
            low_base = min(low_base, float(gaps.min()) - problem.families[0].base.delta)
            low_gap = min(low_gap, float(gaps.min()))
            if (state[[4, 6]] <= state[[6, 8]]).any():  # a collision: car 4 at car 3 or 5
                low_gap = 0.0
                break
        feasible.append(met)
        decided.append(made)
        first_failed.append(first)
        row_left.append(low_row < 0.0)
        base_left.append(low_base < 0.0)
        least_gap.append(low_gap)
    median = [float(np.median(v)) if v else math.nan for v in shares]
    return CarOutcome(np.array(feasible), np.array(decided), np.array(first_failed),
                      np.array(row_left), np.array(base_left), np.array(least_gap),
                      front / decisions, rear / decisions,
                      (int(failed_rows[0]), int(failed_rows[1])),
                      (median[0], median[1], median[2]), float(np.median(margins)), box_left,
                      float(np.median(times)))


CAR_CASES = (('T = L = 0', False), ('with margin', True))
"""The rows of the Car Following table: (label, tightened)."""


def _share(value: float) -> str:
    """A share of nu0 as printed, or - where no row failed."""
    return '-' if math.isnan(value) else f'{value:.2f}'


def run_cars(starts: list[np.ndarray], periods: tuple[float, ...],
             settings: tuple[tuple[float, float], ...]) -> list[str]:
    """The Car Following table: per T = L and (limit, unknown gain), the shipped episode and
    the random ones, without the margin and with it."""
    table = ['| T = L | limit (m/s^2) | unknown gain | episodes | rows | decisions meeting '
             'every row (until a collision) | episodes whose every decision met them | first '
             'without (s, median) | row set left | base set left | least gap (m) | car 3 may '
             'start braking | car 5 may stop braking | rows failing alone (3-4, 4-5) | share of '
             'nu0 there: braking, own input, box | median margin | disturbance outside the box '
             '(fine steps) | median decision (ms) |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for period in periods:
        for limit, gain in settings:
            for name, chosen in (('shipped', starts[:1]),
                                 (f'{len(starts) - 1} random', starts[1:])):
                for label, tightened in CAR_CASES:
                    out = simulate_cars(chosen, period=period, latency=period,
                                        tightened=tightened, gain=gain, limit=limit)
                    first = float(np.median(out.first_failed))
                    table.append(
                        f'| {1e3 * period:g} ms | {limit:g} | {gain:g} | {name} | {label} | '
                        f'{int(out.feasible.sum())} / {int(out.decided.sum())} | '
                        f'{int((out.feasible == out.decided).sum())} / {len(chosen)} | '
                        f"{'-' if math.isinf(first) else f'{first:.2f}'} | "
                        f'{int(out.row_left.sum())} / {len(chosen)} | '
                        f'{int(out.base_left.sum())} / {len(chosen)} | '
                        f'{out.least_gap.min():.3f} | {out.reach_front:.2f} | '
                        f'{out.reach_rear:.2f} | {out.failed_rows[0]}, {out.failed_rows[1]} | '
                        f'{", ".join(_share(v) for v in out.shares)} | '
                        f'{out.median_margin:.3g} | {out.box_left} | '
                        f'{1e3 * out.decision_time_s:.3f} |')
    return table

TITLE = 'Between samples and under latency: violations with and without the margin'

PVTOL_HOVER_HORIZONS = (0.02, 0.04)
"""tau = T + L (s) of :func:`hover_answer` in the table."""


CASES = (('T = L = 0', False, True), ('constant margin', True, False),
         ('margin of the command', True, True))
"""The rows of the tables: (label, tightened, command_linear)."""


def run(worlds: list[World], period: float, latency: float) -> list[str]:
    """The table: violations, least h, correction, progress, fail-safes and decision time per
    case."""
    table = ['| obstacles | rows | worlds violated | least h | mean norm of u_S | decisions | '
             'mean distance left to the goal (m) | fail-safe decisions | '
             'median decision (ms) |', '|---|---|---|---|---|---|---|---|---|']
    for points in (False, True):
        for label, tightened, command_linear in CASES:
            out = simulate(worlds, period=period, latency=latency, tightened=tightened,
                           points=points, command_linear=command_linear)
            table.append(f"| {'sensor points' if points else 'circles'} | {label} | "
                         f'{int(out.violated.sum())} / {len(worlds)} | '
                         f'{out.least_h.min():.4f} | {out.correction:.3f} | '
                         f'{out.decisions} | {out.remaining:.2f} | {out.fail_safe} | '
                         f'{1e3 * out.decision_time_s:.3f} |')
    return table


TURTLEBOT_LIMITS = (0.3, 1.9)
"""The README's TurtleBot-sized base: |v| <= 0.3 m/s, |omega| <= 1.9 rad/s."""


def run_margins(period: float, latency: float, pvtol_horizons: tuple[float, ...]
                ) -> list[str]:
    """The constant margin against the margin of the command: the Unicycle's stopping
    distance facing a circle (:func:`stopping_distance`) and PVTOL's answer in hover
    (:func:`hover_answer`)."""
    table = ['| case | constant margin | margin of the command |', '|---|---|---|']
    for name, limits in (('config/unicycle.yaml', (SPEED, SPEED)),
                         ('TurtleBot (README)', TURTLEBOT_LIMITS)):
        closest = [stopping_distance(limits=limits, period=period, latency=latency,
                                     command_linear=command_linear)
                   for command_linear in (False, True)]
        table.append(f'| Unicycle, {name} limits {limits[0]} m/s, {limits[1]} rad/s: '
                     "closest distance of the centre to a 0.6 m circle's centre (m) | "
                     f'{closest[0]:.2f} | {closest[1]:.2f} |')
    for horizon in pvtol_horizons:
        answers = [hover_answer(horizon=horizon, command_linear=command_linear)
                   for command_linear in (False, True)]
        table.append(f'| PVTOL, config/pvtol.yaml (alpha 1), level hover, tau = '
                     f'{1e3 * horizon:g} ms | {answers[0]} | {answers[1]} |')
    return table


def run_pvtol(worlds: list[PVTOLWorld], period: float, latency: float) -> list[str]:
    """The PVTOL table: violations, fail-safes, margins and decision time with and without."""
    table = ['| rows | worlds violated (a row set) | of them before any fail-safe | '
             'worlds violated (a base set) | least base h | fail-safe decisions | '
             'median margin | median decision (ms) |', '|---|---|---|---|---|---|---|---|']
    for label, tightened, command_linear in CASES:
        out = simulate_pvtol(worlds, period=period, latency=latency, tightened=tightened,
                             command_linear=command_linear)
        median = f'{np.median(out.margins):.3g}' if out.margins.size else '-'
        table.append(f'| {label} | '
                     f'{int(out.violated.sum())} / {len(worlds)} | '
                     f'{int(out.verified.sum())} / {len(worlds)} | '
                     f'{int(out.touched.sum())} / {len(worlds)} | {out.least_h.min():.4f} | '
                     f'{out.fail_safe} / {out.decisions} | {median} | '
                     f'{1e3 * out.decision_time_s:.3f} |')
    return table


CARS_TITLE = 'Car Following between samples: why its margin is refused'


def publish_cars(episodes: int, seed: int, write: bool) -> None:
    """Run and print (and write, when ``write``) the Car Following section."""
    from benchmarks._results import publish_section
    table = run_cars(car_starts(episodes, seed), CAR_PERIODS, CAR_SETTINGS)
    options = ''.join(f' --{name} {value}' for name, value, default in (
        ('car-episodes', episodes, 20), ('seed', seed, 0)) if value != default)
    publish_section(CARS_TITLE, script=f'bench_sampled_data.py --cars-only{options}',
                    write=write, blocks=[
        "config/car_following.yaml's rows (cascaded gaps 3-4 and 4-5, alpha 5, gamma 8, k_c 2) "
        'with input limits +/- the limit; the unknown gain of cars 1, 2, 3, 5 0 (the model '
        "exact but for the leader's sine) or 0.1 (the env's); the shipped start (the env's "
        f'seed 0) and {episodes} random starts around it (seed {seed}: every position moved by '
        'U[-1.5, 1.5] m, every speed by U[-1, 1] m/s, car 4 at 35 + U[-2, 2] m/s, drawn again '
        'where a gap row starts outside its row set); 1 ms Euler steps of the true Car '
        "Following (the leader's sine, the gains 1 + the unknown gain) over 6 s or until car 4 "
        "reaches car 3 or car 5 (a collision: least gap 0), car 4's command held for T and "
        "computed from states L old, the proposal +5 m/s^2 into car 3 (the env's nominal "
        "controller). The disturbance box covers the unknown gain times the prior's "
        'accelerations (at 0.1: 13.2 m/s^2 on cars 2, 3, 25.2 on car 5) and 25 m/s^2 on the '
        'leader. The QP in one input: the proposal clipped to the interval the rows leave '
        "within the limits; none: the fail-safe, config/car_following.yaml's 0 (car 4 "
        'coasts). "with margin": the rows tightened by CarFollowingBound\'s nu0 + c |u| '
        '(rcbf_ros/core/sampled_data.py; docs/SAFETY_FILTER.md, "Not covered"). A row set: '
        'h* >= 0; a base set: a gap of at least delta = 3.75 m. "may start / stop braking": '
        'decisions whose bound finds that switch within reach. A row failing alone: no command '
        "within the limits meets it; the shares of its nu0 there (medians): the braking terms', "
        "car 4's own input range in the motion (nu0 less nu0 with the limits 0) and the box's "
        '(nu0 less nu0 with the box 0). Decision time: the rows, the bound where it tightens '
        'them and the QP, median.', table])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--worlds', type=int, default=200)
    parser.add_argument('--period', type=float, default=0.1, help='T (s)')
    parser.add_argument('--latency', type=float, default=0.05, help='L (s)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--pvtol-worlds', type=int, default=50)
    parser.add_argument('--pvtol-period', type=float, default=0.02, help='T on PVTOL (s)')
    parser.add_argument('--pvtol-latency', type=float, default=0.02, help='L on PVTOL (s)')
    parser.add_argument('--car-episodes', type=int, default=20,
                        help='random Car Following episodes beside the shipped one')
    parser.add_argument('--cars-only', action='store_true',
                        help='run (and write) the Car Following section only')
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the sections only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.pvtol_worlds < 1 or args.car_episodes < 1:
        parser.error('--worlds, --pvtol-worlds and --car-episodes must be >= 1')
    publish_cars(args.car_episodes, args.seed, args.write)
    if args.cars_only:
        return 0
    worlds = random_worlds(args.worlds, args.seed)
    table = run(worlds, args.period, args.latency)
    margins = run_margins(args.period, args.latency, PVTOL_HOVER_HORIZONS)
    pvtol = run_pvtol(pvtol_worlds(args.pvtol_worlds, args.seed), args.pvtol_period,
                      args.pvtol_latency)
    from benchmarks._results import publish_section
    options = ''.join(f' --{name} {value}' for name, value, default in (
        ('worlds', args.worlds, 200), ('period', args.period, 0.1),
        ('latency', args.latency, 0.05), ('seed', args.seed, 0),
        ('pvtol-worlds', args.pvtol_worlds, 50), ('pvtol-period', args.pvtol_period, 0.02),
        ('pvtol-latency', args.pvtol_latency, 0.02)) if value != default)
    publish_section(TITLE, script='bench_sampled_data.py' + options, write=args.write, blocks=[
        f'T = {args.period} s, L = {args.latency} s: {args.worlds} random worlds (seed '
        f'{args.seed}), 1 ms Euler steps of the true Unicycle over 2.5 s, commands held for T '
        'and computed from states L old. "T = L = 0": the continuous-time rows under the same '
        'hold and delay; "with margin": the rows tightened for T and L '
        '(docs/SAFETY_FILTER.md, "Between samples and under latency"). A world is violated '
        'when h at the look-ahead point (margin included) falls below 0 at a fine step. '
        'norm of u_S: the correction per decision; the last column: what the margin costs in '
        'progress (the start is 3.6-5.4 m from the goal). "constant margin": every row lowered '
        'by the margin of the largest input within the limits; "margin of the command": by '
        'nu0 + c^T |u|, the rows split by the signs of u (docs/SAFETY_FILTER.md).', table,
        f'The constant margin against the margin of the command (T = {args.period} s, L = '
        f'{args.latency} s on the Unicycle: straight at the circle at full speed, alpha 2, '
        'obstacles.margin 0.1, no disturbance, until it has stood still for 1 s; on PVTOL T = L '
        '= tau / 2, the hover command 0 proposed, slack tolerance 1e-4).', margins,
        f'PVTOL (cascaded rows, the interval margin): T = {args.pvtol_period} s, '
        f'L = {args.pvtol_latency} s, {args.pvtol_worlds} random worlds (config/pvtol.yaml with '
        'a random transfer layout, alpha U[10, 25], the drone in hover 0.6-1.2 m from a circle '
        'and aggressive go-to-goal proposals through it, tilt up to 1.3 rad), 1 ms Euler steps '
        'of the true PVTOL (its attitude error, the operator without noise) over 3 s. A row '
        "set: the filter's (cascaded) barrier; a base set: an obstacle's disc with its margin, "
        'a band. Fail-safe decisions: the rows infeasible (slack tolerance 1e-3), the fail-safe '
        'holds attitude and thrust (outside the guarantee; "before any fail-safe": the world '
        'left a row set while every decision so far met its rows). Decision time: the median '
        'of SafetyFilter.filter, margin included.', pvtol])
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

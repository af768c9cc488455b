"""The filter on a laser scan against a stop zone, in seeded worlds that look like a robot's.

    python benchmarks/bench_lidar_world.py [--worlds 100] [--out DIR] [--no-write]
    python benchmarks/bench_lidar_world.py --between-samples [--worlds 30] [--period 0.05]
        [--latency 0.05] [--alpha 20] [--v-max 1.0] [--no-write]

Each world (:func:`sim_nodes.lidar_world.random_world`, seeds 0..N-1: posts, a wall with
doorways, a corridor, or rooms) is driven once per set-up by a go-to-goal controller that
ignores obstacles, on a differential-drive base with actuator lag, wheel slip and drifting
odometry, seeing through a 360-beam 10 Hz lidar (:mod:`sim_nodes.lidar_world`). Set-ups:

- ``no filter``: the controller's command as it is;
- ``stop zone``: Nav2 collision_monitor's stop model, written here: the command becomes zero
  while at least ``min_points`` scan points lie in the stop polygon of its tutorial's
  parameters (a box 0.4 m ahead of base_link, 0.3 m to either side);
- ``filter, true circles``: the safety filter with the world given by hand (posts as circles
  widened by the body's radius, walls as circles sampled along them, no sensor) and the true
  pose (a map and a perfect localisation: the reference);
- ``filter, scan``: the safety filter on the scan only, through the node's path: each scan is
  encoded as LaserScan CDR bytes in frame ``laser`` (0.1 m ahead of base_link), read by
  :class:`ObservationSources` with ``/tf_static`` base_link -> laser and ``/tf``
  odom -> base_link (odometry, at the state rate and at every scan's stamp) as TFMessage CDR
  bytes, placed in ``odom`` through tf at the scan's stamp and set as circle rows.

The scan's filter takes the state from odometry (the ``odom`` frame, where the run starts:
the scan's points and the pose drift together); the controller steers by the true pose (as a
localised robot would). Collisions, goals reached and
times to goal are judged on the true pose against the true geometry.

``--between-samples`` drives the scan robot as a real one is driven (:func:`drive_held`): 1 ms
physics steps, each command held for ``--period`` T, and everything the filter sees (scans,
``/tf``, odometry) arriving ``--latency`` L late, so that the state is at most L old at a
decision; the scan's filter without and with the sampled-data margin of T and L
(``control_period_s``, ``latency_s``: docs/SAFETY_FILTER.md). A filter that lets the robot
approach fast (``--alpha`` 20, ``--v-max`` 1 m/s) shows what the margin is for: collisions
without it. The margin is derived for the unicycle's kinematics with any command within the
limits; the base's actuator lag and slip are outside that model and are left to the
disturbance box, as in the other set-ups.
"""
from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass
import math
from pathlib import Path
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rcbf_ros.core.config import filter_config_from_params  # noqa: E402
from rcbf_ros.messages import sensor  # noqa: E402
from rcbf_ros.messages.tf import TF_MESSAGE  # noqa: E402
from rcbf_ros.messages.typestore import jazzy_typestore  # noqa: E402
from rcbf_ros.node_logic.safety_filter import build_safety_filter, node_settings_from_params  # noqa: E402,E501
from rcbf_ros.node_logic.sources import ObservationSources  # noqa: E402
from rcbf_ros.parameters.rules import find_config, load_params  # noqa: E402
from sim_nodes import lidar_world as lw  # noqa: E402

TITLE = 'Lidar worlds: the filter on a scan against a stop zone'
SETUPS = ('no filter', 'stop zone', 'filter, true circles', 'filter, scan')
"""The set-ups, in the table's order."""
BASE = lw.BaseModel()
"""The robot: radius 0.2 m, |v| <= 0.5 m/s, |omega| <= 1.5 rad/s, lag 0.15 / 0.1 s."""
LIDAR = lw.Lidar(mount=(0.1, 0.0, 0.0), frame_id='laser')
"""The lidar 0.1 m ahead of base_link, in frame ``laser``: the filter places its points
through tf (:class:`TfEncoder`), the stop zone moves them to base_link by the mount."""
ODOM_FRAME, BASE_FRAME = 'odom', 'base_link'
"""The frames of the odometry and of the robot (the filter's ``odom_frame_id``,
``base_frame_id`` defaults)."""
PHYSICS_DT = 0.01
"""The base's integration step (s)."""
CONTROL_EVERY = 5
"""Physics steps per command (20 Hz)."""
SCAN_EVERY = 10
"""Physics steps per scan (10 Hz)."""
DURATION = 60.0
"""The longest run (s)."""
STUCK_WINDOW = 10.0
"""A run ends as stuck once the true position moved less than :data:`STUCK_DISTANCE` in this
long (s)."""
STUCK_DISTANCE = 0.05
GOAL_RADIUS = 0.3
"""The goal counts as reached within this distance of the true position (m)."""
STOP_POLYGON = np.array([[0.4, 0.3], [0.4, -0.3], [0.0, -0.3], [0.0, 0.3]])
"""collision_monitor's tutorial stop polygon (PolygonStop), in base_link (m)."""
STOP_MIN_POINTS = 4
"""collision_monitor's ``min_points`` of that polygon (Jazzy)."""
WALL_SPACING = 0.05
"""The distance between the circles a wall is sampled with (m)."""
DISTURBANCE_STD = (0.05, 0.05, 0.1)
"""The filter's disturbance box (mean 0, +/- k_c = 2 of these) on x, y, yaw rates: the lag and
slip the unicycle model leaves out."""


def filter_params(world: lw.World | None) -> dict:
    """config/unicycle.yaml's safety_filter parameters for the base: its input limits, a zero
    -mean disturbance box; with ``world`` its posts and walls as circles (no sensor), else one
    LaserScan source ``scan`` (placed through tf) and ``footprint.radius`` the body's."""
    out = load_params(find_config('unicycle'), 'safety_filter')
    for key in ('obstacles.x', 'obstacles.y', 'obstacles.radius'):
        out.pop(key)
    out.update({'input_limits.min': [-BASE.v_max, -BASE.omega_max],
                'input_limits.max': [BASE.v_max, BASE.omega_max],
                'disturbance.mean': [0.0, 0.0, 0.0], 'disturbance.std': list(DISTURBANCE_STD)})
    if world is None:
        out.update({'observation_sources': ['scan'], 'scan.type': 'scan',
                    'scan.topic': 'scan', 'scan.timeout_s': 0.5,
                    'footprint.radius': BASE.radius})
        return out
    circles = world_circles(world)
    out.update({'obstacles.x': circles[:, 0].tolist(), 'obstacles.y': circles[:, 1].tolist(),
                'obstacles.radius': circles[:, 2].tolist()})
    return out


def world_circles(world: lw.World) -> np.ndarray:
    """(K, 3) the world for the filter by hand: each post widened by the body's radius, each
    wall's centre line sampled every :data:`WALL_SPACING` by circles of radius
    sqrt((r + w/2)^2 + (s/2)^2), whose union covers every point within the body's radius r of
    the wall of thickness w."""
    parts = [world.circles + np.array([0.0, 0.0, BASE.radius])]
    radius = math.hypot(BASE.radius + world.wall_thickness / 2, WALL_SPACING / 2)
    for x0, y0, x1, y1 in world.segments:
        count = max(2, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / WALL_SPACING)) + 1)
        s = np.linspace(0.0, 1.0, count)
        parts.append(np.stack([x0 + s * (x1 - x0), y0 + s * (y1 - y0),
                               np.full(count, radius)], axis=1))
    return np.concatenate(parts)


class ScanEncoder:
    """LaserScan CDR bytes of :data:`LIDAR`'s scans, as a driver publishes them."""

    def __init__(self) -> None:
        self.store = jazzy_typestore()

    def __call__(self, ranges: np.ndarray, stamp_ns: int) -> bytes:
        t = self.store.types
        fields = lw.scan_fields(ranges, LIDAR, stamp_ns=stamp_ns)
        header = t['std_msgs/msg/Header'](
            stamp=t['builtin_interfaces/msg/Time'](sec=stamp_ns // 10 ** 9,
                                                   nanosec=stamp_ns % 10 ** 9),
            frame_id=fields.pop('frame_id'))
        fields.pop('stamp_ns')
        msg = t[sensor.LASER_SCAN](header=header, **fields)
        return bytes(self.store.serialize_cdr(msg, sensor.LASER_SCAN))


class TfEncoder:
    """TFMessage CDR bytes as a base's driver publishes them: ``/tf_static`` base_link ->
    laser (:data:`LIDAR`'s mount) and ``/tf`` odom -> base_link (the odometry's pose)."""

    def __init__(self) -> None:
        self.store = jazzy_typestore()

    def _message(self, parent: str, child: str, pose: np.ndarray, stamp_ns: int) -> bytes:
        t = self.store.types
        x, y, yaw = (float(v) for v in pose)
        header = t['std_msgs/msg/Header'](
            stamp=t['builtin_interfaces/msg/Time'](sec=stamp_ns // 10 ** 9,
                                                   nanosec=stamp_ns % 10 ** 9),
            frame_id=parent)
        transform = t['geometry_msgs/msg/TransformStamped'](
            header=header, child_frame_id=child,
            transform=t['geometry_msgs/msg/Transform'](
                translation=t['geometry_msgs/msg/Vector3'](x=x, y=y, z=0.0),
                rotation=t['geometry_msgs/msg/Quaternion'](
                    x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))))
        msg = t[TF_MESSAGE](transforms=[transform])
        return bytes(self.store.serialize_cdr(msg, TF_MESSAGE))

    def static(self) -> bytes:
        """``/tf_static``: the laser on base_link (stamp 0, as static transforms hold)."""
        return self._message(BASE_FRAME, LIDAR.frame_id, np.array(LIDAR.mount), 0)

    def odometry(self, odom: np.ndarray, stamp_ns: int) -> bytes:
        """``/tf``: base_link on odom at the odometry's pose ``odom`` (x, y, yaw)."""
        return self._message(ODOM_FRAME, BASE_FRAME, odom, stamp_ns)


def laser_to_base(points: np.ndarray) -> np.ndarray:
    """(N, 2) points in :data:`LIDAR`'s frame -> base_link, by its mount (what
    collision_monitor's tf lookup of the static transform does)."""
    mx, my, myaw = LIDAR.mount
    c, s = math.cos(myaw), math.sin(myaw)
    return np.stack([mx + c * points[:, 0] - s * points[:, 1],
                     my + s * points[:, 0] + c * points[:, 1]], axis=1)


def in_stop_zone(points: np.ndarray) -> int:
    """How many of ``points`` (N, 2, base_link) lie in :data:`STOP_POLYGON` (an axis-aligned
    box: collision_monitor tests the polygon, here the box it is)."""
    lo, hi = STOP_POLYGON.min(axis=0), STOP_POLYGON.max(axis=0)
    return int(np.count_nonzero(((points >= lo) & (points <= hi)).all(axis=1)))


@dataclass
class Run:
    """One world driven by one set-up."""

    setup: str
    seed: int
    kind: str
    outcome: str
    """'goal', 'collision', 'stuck' or 'timeout'."""
    time: float
    """When it ended (s)."""
    path: np.ndarray
    """(T, 2) true positions, one per command."""
    closest: float
    """The least clearance of the body (true centre's distance to a surface less the radius, m)."""
    corrected: int = 0
    """Commands the filter or the stop zone changed."""
    fail_safe: int = 0
    """Commands that were the filter's fail-safe."""
    decide_s: float = 0.0
    """Time spent deciding commands (s)."""


def decide(safety_filter, sources: ObservationSources | None, pose: np.ndarray | None,
           nominal: np.ndarray, now_ns: int, mean: np.ndarray, std: np.ndarray
           ) -> tuple[np.ndarray, object]:
    """One command of a filter set-up at ``pose`` (None: no state yet): the scan's points set
    first (``sources``; None: the map's rows only), then the filter; (command, the filter's
    result, or None for the fail-safe of a source or a missing state)."""
    reason = 'no state yet' if pose is None else '' if sources is None else sources.sense(
        safety_filter, pose, now_ns=now_ns, stamp_now_ns=now_ns)
    if reason:
        return safety_filter.fail_safe_action, None
    result = safety_filter.filter(pose, nominal, mean, std)
    return result.u_safe, result


def drive(world: lw.World, setup: str, *, seed: int = 0, duration: float = DURATION) -> Run:
    """Drive ``world`` with ``setup`` (one of :data:`SETUPS`) until the goal, a collision,
    being stuck, or ``duration``."""
    rng = np.random.default_rng(seed)
    state = lw.start_state(world)
    safety_filter = sources = encode = tf = None
    if setup.startswith('filter'):
        config = filter_config_from_params(
            filter_params(world if setup == 'filter, true circles' else None))
        safety_filter = build_safety_filter(config=config, settings=node_settings_from_params({}))
        mean, std = np.zeros(3), np.array(DISTURBANCE_STD)
        if setup == 'filter, scan':
            sources = ObservationSources(config.sources)
            tf = TfEncoder()
            reason = sources.read_tf(tf.static(), static=True)
            assert not reason, reason
    if setup in ('stop zone', 'filter, scan'):
        encode = ScanEncoder()
    scan_points = np.zeros((0, 2))
    command = np.zeros(2)
    path, closest = [state.pose[:2].copy()], math.inf
    corrected = fail_safe = 0
    decide_s = 0.0
    steps = int(round(duration / PHYSICS_DT))
    window = int(round(STUCK_WINDOW / (CONTROL_EVERY * PHYSICS_DT)))
    outcome, t = 'timeout', duration
    for k in range(steps):
        now = k * PHYSICS_DT
        now_ns = int(round(now * 1e9))
        if tf is not None and (k % CONTROL_EVERY == 0 or k % SCAN_EVERY == 0):
            # odometry's /tf at the state rate and at every scan's stamp
            reason = sources.read_tf(tf.odometry(state.odom, now_ns), static=False)
            assert not reason, reason
        if encode is not None and k % SCAN_EVERY == 0:
            data = encode(lw.scan_ranges(world, state.pose, LIDAR, rng), now_ns)
            if sources is not None:
                reason = sources.read('scan', data, received_ns=now_ns)
                assert not reason, reason
            else:
                scan_points = laser_to_base(sensor.scan_points(data).points)
        if k % CONTROL_EVERY == 0:
            if np.hypot(*(state.pose[:2] - world.goal)) <= GOAL_RADIUS:
                outcome, t = 'goal', now
                break
            if len(path) > window and np.hypot(*(path[-1] - path[-1 - window])) < STUCK_DISTANCE:
                outcome, t = 'stuck', now
                break
            nominal = lw.go_to_goal(state.pose, world.goal, BASE)
            start = time.perf_counter()
            if setup == 'no filter':
                command = nominal
            elif setup == 'stop zone':
                stop = in_stop_zone(scan_points) >= STOP_MIN_POINTS
                command = np.zeros(2) if stop else nominal
                corrected += stop
            else:
                # the scan's filter works in odom; the map's needs the pose in the map
                pose = state.odom if sources is not None else state.pose
                command, result = decide(safety_filter, sources, pose, nominal, now_ns, mean,
                                         std)
                fail_safe += result is None or bool(result.fail_safe)
                corrected += result is not None and bool(result.active)
            decide_s += time.perf_counter() - start
        state = lw.step_base(state, command, PHYSICS_DT, BASE, rng)
        gap = float(lw.clearance(world, state.pose[:2])[0]) - BASE.radius
        closest = min(closest, gap)
        if k % CONTROL_EVERY == CONTROL_EVERY - 1:
            path.append(state.pose[:2].copy())
        if gap < 0.0:
            outcome, t = 'collision', (k + 1) * PHYSICS_DT
            path.append(state.pose[:2].copy())
            break
    return Run(setup, world.seed, world.kind, outcome, t, np.array(path), closest, corrected,
               fail_safe, decide_s)


HELD_DT = 0.001
"""The physics step of :func:`drive_held` (s)."""
ODOMETRY_DT = 0.005
"""How often :func:`drive_held`'s odometry (and its ``/tf``) is sampled (s)."""


def held_filter(*, tightened: bool, period: float, latency: float, alpha: float,
                base: lw.BaseModel) -> tuple[object, ObservationSources]:
    """The scan's filter of :func:`drive_held` (``filter_params(None)``, the base's limits,
    ``alpha``) with the sampled-data margin of ``period`` and ``latency`` when ``tightened``,
    and its sources with ``/tf_static`` read."""
    params = filter_params(None)
    params.update({'alpha': alpha, 'input_limits.min': [-base.v_max, -base.omega_max],
                   'input_limits.max': [base.v_max, base.omega_max]})
    if tightened:
        params.update({'control_period_s': period, 'latency_s': latency})
    config = filter_config_from_params(params)
    safety_filter = build_safety_filter(config=config, settings=node_settings_from_params({}))
    sources = ObservationSources(config.sources)
    reason = sources.read_tf(TfEncoder().static(), static=True)
    assert not reason, reason
    return safety_filter, sources


def drive_held(world: lw.World, *, tightened: bool, period: float, latency: float,
               alpha: float = 20.0, base: lw.BaseModel | None = None, seed: int = 0,
               duration: float = 30.0) -> Run:
    """The scan robot between samples: ``world`` driven with 1 ms physics steps
    (:data:`HELD_DT`), a command decided every ``period`` and held until the next, from data
    that arrive ``latency`` - :data:`ODOMETRY_DT` after they were taken (scans at 10 Hz,
    odometry and its ``/tf`` every :data:`ODOMETRY_DT`), so that the newest state is at most
    ``latency`` old at a decision. The filter (:func:`held_filter`) decides on that state and
    the scans placed through tf; a run ends at the goal, a collision (any fine step), or
    ``duration``."""
    base = base or BASE
    if not latency >= ODOMETRY_DT:
        raise ValueError(f'latency: at least {ODOMETRY_DT} s (the odometry period), got {latency}')
    rng = np.random.default_rng(seed)
    state = lw.start_state(world)
    safety_filter, sources = held_filter(tightened=tightened, period=period, latency=latency,
                                         alpha=alpha, base=base)
    tf, encode = TfEncoder(), ScanEncoder()
    mean, std = np.zeros(3), np.array(DISTURBANCE_STD)
    delay = latency - ODOMETRY_DT
    arriving: collections.deque = collections.deque()  # (arrival s, kind, data, stamp ns)
    every_odometry = int(round(ODOMETRY_DT / HELD_DT))
    every_scan = int(round(SCAN_EVERY * PHYSICS_DT / HELD_DT))
    every_command = max(1, int(round(period / HELD_DT)))
    odometry = None
    command = np.zeros(2)
    path, closest = [state.pose[:2].copy()], math.inf
    corrected = fail_safe = 0
    decide_s = 0.0
    outcome, t = 'timeout', duration
    for k in range(int(round(duration / HELD_DT))):
        now = k * HELD_DT
        now_ns = int(round(now * 1e9))
        if k % every_odometry == 0:
            arriving.append((now + delay, 'odometry', state.odom.copy(), now_ns))
        if k % every_scan == 0:
            arriving.append((now + delay, 'scan', lw.scan_ranges(world, state.pose, LIDAR, rng),
                             now_ns))
        while arriving and arriving[0][0] <= now + 1e-9:
            _, kind, data, stamp_ns = arriving.popleft()
            if kind == 'odometry':
                reason = sources.read_tf(tf.odometry(data, stamp_ns), static=False)
                odometry = data
            else:
                reason = sources.read('scan', encode(data, stamp_ns), received_ns=now_ns)
            assert not reason, reason
        if k % every_command == 0:
            if np.hypot(*(state.pose[:2] - world.goal)) <= GOAL_RADIUS:
                outcome, t = 'goal', now
                break
            nominal = lw.go_to_goal(state.pose, world.goal, base)
            start = time.perf_counter()
            command, result = decide(safety_filter, sources, odometry, nominal, now_ns, mean,
                                     std)
            decide_s += time.perf_counter() - start
            fail_safe += result is None or bool(result.fail_safe)
            corrected += result is not None and bool(result.active)
            path.append(state.pose[:2].copy())
        state = lw.step_base(state, command, HELD_DT, base, rng)
        gap = float(lw.clearance(world, state.pose[:2])[0]) - base.radius
        closest = min(closest, gap)
        if gap < 0.0:
            outcome, t = 'collision', (k + 1) * HELD_DT
            path.append(state.pose[:2].copy())
            break
    setup = 'filter, scan, margin' if tightened else 'filter, scan'
    return Run(setup, world.seed, world.kind, outcome, t, np.array(path), closest, corrected,
               fail_safe, decide_s)


def held_table(runs: list[Run]) -> list[str]:
    """:func:`drive_held`'s table: per set-up, collisions, goals, the least clearance, the
    share of decisions that were the fail-safe or corrected."""
    lines = ['| set-up | worlds | collisions | goals reached | closest approach, least (m) | '
             'fail-safe decisions | commands changed |', '|---|---:|---:|---:|---:|---:|---:|']
    for setup in ('filter, scan', 'filter, scan, margin'):
        mine = [r for r in runs if r.setup == setup]
        decisions = max(sum(len(r.path) - 1 for r in mine), 1)
        lines.append(f'| {setup} | {len(mine)} | '
                     f'{sum(r.outcome == "collision" for r in mine)} | '
                     f'{sum(r.outcome == "goal" for r in mine)} | '
                     f'{min(r.closest for r in mine):.3f} | '
                     f'{sum(r.fail_safe for r in mine) / decisions:.0%} | '
                     f'{sum(r.corrected for r in mine) / decisions:.0%} |')
    return lines


def summary(runs: list[Run]) -> list[str]:
    """The table: per set-up, collisions, goals, stuck, time to goal (over its own goals, and
    over the worlds where every set-up without a collision reached the goal), closest
    approach."""
    lines = ['| set-up | worlds | collisions | goals reached | stuck / timeout | time to goal, '
             'median (s) | time to goal where all reached, median (s) | closest approach, '
             'least (m) | commands changed | decision, median per command (us) |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|']
    safe = [s for s in SETUPS if any(r.setup == s for r in runs)
            and not any(r.setup == s and r.outcome == 'collision' for r in runs)]
    reached = {seed for seed in {r.seed for r in runs}
               if all(any(r.setup == s and r.seed == seed and r.outcome == 'goal' for r in runs)
                      for s in safe)}
    for setup in SETUPS:
        mine = [r for r in runs if r.setup == setup]
        if not mine:
            continue
        goals = [r.time for r in mine if r.outcome == 'goal']
        common = [r.time for r in mine if r.outcome == 'goal' and r.seed in reached]
        commands = sum(len(r.path) for r in mine)
        lines.append(
            f'| {setup} | {len(mine)} | {sum(r.outcome == "collision" for r in mine)} | '
            f'{len(goals)} | {sum(r.outcome in ("stuck", "timeout") for r in mine)} | '
            f'{np.median(goals) if goals else float("nan"):.1f} | '
            + (f'{np.median(common):.1f} ({len(common)}) | ' if setup in safe and common
               else '- | ') +
            f'{min(r.closest for r in mine):.3f} | '
            f'{sum(r.corrected for r in mine) / max(commands, 1):.0%} | '
            f'{np.median([r.decide_s / max(len(r.path), 1) for r in mine]) * 1e6:,.0f} |')
    return lines


def by_kind(runs: list[Run]) -> list[str]:
    """Goals reached (and collisions) per kind of world and set-up."""
    kinds = [k for k in lw.KINDS if any(r.kind == k for r in runs)]
    lines = ['| kind of world | worlds | ' + ' | '.join(SETUPS) + ' |',
             '|---|---:|' + '---:|' * len(SETUPS)]
    for kind in kinds:
        cells = []
        for setup in SETUPS:
            mine = [r for r in runs if r.kind == kind and r.setup == setup]
            cells.append(f'{sum(r.outcome == "goal" for r in mine)} goals, '
                         f'{sum(r.outcome == "collision" for r in mine)} hits')
        worlds = len({r.seed for r in runs if r.kind == kind})
        lines.append(f'| {kind} | {worlds} | ' + ' | '.join(cells) + ' |')
    return lines


OUTCOME_STYLE = {'goal': ('tab:green', '*'), 'collision': ('tab:red', 'X'),
                 'stuck': ('tab:orange', 's'), 'timeout': ('tab:orange', 's')}


def plot_setup(worlds: dict[int, lw.World], runs: list[Run], path: Path, *, panels: int = 12
               ) -> Path:
    """A grid of the first ``panels`` worlds with this set-up's trajectories (true positions):
    posts, walls, start, goal, and where each run ended (goal, collision, stuck)."""
    from rcbf_ros.reports.plots import _pyplot
    plt = _pyplot()
    runs = runs[:panels]
    columns = 4
    rows = max(1, math.ceil(len(runs) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows), dpi=100,
                             squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, run in zip(axes.ravel(), runs):
        world = worlds[run.seed]
        ax.set_axis_on()
        for x, y, r in world.circles:
            ax.add_patch(plt.Circle((x, y), r, color='0.4'))
        for x0, y0, x1, y1 in world.segments:
            ax.plot([x0, x1], [y0, y1], color='0.2', linewidth=2.0, solid_capstyle='round')
        ax.plot(run.path[:, 0], run.path[:, 1], color='tab:blue', linewidth=1.0)
        ax.plot(*world.start[:2], 'o', color='tab:blue', markersize=4)
        ax.plot(*world.goal, 'o', color='tab:green', markersize=5, fillstyle='none')
        colour, marker = OUTCOME_STYLE[run.outcome]
        ax.plot(*run.path[-1], marker, color=colour, markersize=8)
        ax.set_title(f'seed {run.seed} ({run.kind}): {run.outcome} {run.time:.0f} s',
                     fontsize=8)
        ax.set_aspect('equal')
        h = world.half_size
        ax.set_xlim(-h, h)
        ax.set_ylim(-h, h)
        ax.tick_params(labelsize=6)
    fig.suptitle(f'{run.setup}: true paths (green star goal, red X collision, orange square '
                 'stuck)', fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def run(worlds: int, *, first_seed: int = 0) -> tuple[dict[int, lw.World], list[Run]]:
    """Every set-up on worlds of seeds ``first_seed`` .. ``first_seed + worlds - 1`` (the
    base's noise seeded by the world's seed, the same for every set-up)."""
    built = {seed: lw.random_world(seed) for seed in range(first_seed, first_seed + worlds)}
    runs = []
    for setup in SETUPS:
        for seed, world in built.items():
            runs.append(drive(world, setup, seed=seed))
    return built, runs


HELD_TITLE = 'Lidar worlds between samples: the scan robot with and without the margin'


def between_samples(args: argparse.Namespace) -> int:
    """``--between-samples``: :func:`drive_held` on ``args.worlds`` worlds, both set-ups."""
    for name, value, low, high in (('--period', args.period, 0.001, 1.0),
                                   ('--latency', args.latency, ODOMETRY_DT, 1.0),
                                   ('--alpha', args.alpha, 0.01, 1000.0),
                                   ('--v-max', args.v_max, 0.01, 10.0)):
        if not low <= value <= high:
            print(f'bench_lidar_world.py: {name} must be in {low:g}..{high:g}, got {value}',
                  file=sys.stderr)
            return 2
    base = lw.BaseModel(v_max=args.v_max)
    start, start_cpu = time.perf_counter(), time.process_time()
    runs = [drive_held(lw.random_world(seed), tightened=tightened, period=args.period,
                       latency=args.latency, alpha=args.alpha, base=base, seed=seed)
            for tightened in (False, True) for seed in range(args.worlds)]
    elapsed, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    from benchmarks._results import load_averages, publish_section
    options = (f' --between-samples --worlds {args.worlds} --period {args.period:g} '
               f'--latency {args.latency:g} --alpha {args.alpha:g} --v-max {args.v_max:g}')
    publish_section(
        HELD_TITLE, script='bench_lidar_world.py' + options,
        conditions=f'; {load_averages()}; {elapsed:.0f} s for the whole run, {cpu:.0f} s of '
                   'CPU',
        write=args.write, blocks=[
            f'The worlds of the section above (seeds 0-{args.worlds - 1}), each driven for at '
            f'most 30 s by the go-to-goal controller on the same base (lag, slip, drifting '
            f'odometry), with |v| <= {args.v_max:g} m/s, through the scan only '
            f'(`drive_held`): 1 ms physics steps, each command held for T = {args.period:g} '
            f's, scans, /tf and odometry arriving {args.latency - ODOMETRY_DT:g} s after they '
            f'were taken (odometry every {ODOMETRY_DT:g} s: the state is at most '
            f'L = {args.latency:g} s old at a decision). The filter lets the robot approach '
            f'fast (alpha {args.alpha:g}); "margin": the same filter with `control_period_s` '
            f'{args.period:g} and `latency_s` {args.latency:g} (the sampled-data margin, '
            'docs/SAFETY_FILTER.md). A collision is any 1 ms step of the true body inside the '
            'true geometry.',
            held_table(runs),
            'The margin covers the unicycle kinematics under any command within the limits '
            "over L + T; the base's lag and slip are outside it, left to the disturbance box "
            '(as in the section above). It is a worst case over the input box: near an '
            'obstacle the tightened rows admit no command within the limits and the filter '
            'answers with its fail-safe (zero velocity), so the robot stops farther out, and '
            'a blind controller that keeps pushing at the obstacle keeps it there (without '
            'the margin too: the fail-safe share of both set-ups is mostly robots held at a '
            'wall), which is why robots with the margin reach fewer goals here.'])
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--worlds', type=int, default=None,
                        help='seeded worlds, seeds 0..N-1 (default 100; 30 between samples)')
    parser.add_argument('--between-samples', action='store_true',
                        help='the scan robot with held commands and late data, without and '
                             'with the sampled-data margin (drive_held)')
    parser.add_argument('--period', type=float, default=0.05,
                        help='between samples: how long a command is held, T (s)')
    parser.add_argument('--latency', type=float, default=0.05,
                        help='between samples: how late the data arrive, L (s)')
    parser.add_argument('--alpha', type=float, default=20.0, help='between samples: alpha')
    parser.add_argument('--v-max', type=float, default=1.0,
                        help="between samples: the base's |v| limit (m/s)")
    parser.add_argument('--out', type=Path, default=Path('lidar_world_runs'),
                        help='directory of the trajectory pictures (default lidar_world_runs)')
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    args = parser.parse_args(argv)
    if args.worlds is None:
        args.worlds = 30 if args.between_samples else 100
    if not 1 <= args.worlds <= 10_000:
        parser.error('--worlds must be in 1..10000')
    if args.between_samples:
        return between_samples(args)
    if args.out.exists() and not args.out.is_dir():
        parser.error(f'--out: {args.out} is not a directory')
    start, start_cpu = time.perf_counter(), time.process_time()
    worlds, runs = run(args.worlds)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    table, kinds = summary(runs), by_kind(runs)
    pictures = []
    for setup in SETUPS:
        name = setup.replace(', ', '_').replace(' ', '_') + '.png'
        pictures.append(plot_setup(worlds, [r for r in runs if r.setup == setup],
                                   args.out / name))
    print('pictures: ' + ', '.join(str(p) for p in pictures), flush=True)
    from benchmarks._results import load_averages, publish_section
    publish_section(
        TITLE, script='bench_lidar_world.py'
        + (f' --worlds {args.worlds}' if args.worlds != 100 else ''),
        conditions=f'; {load_averages()}; {elapsed:.0f} s for the whole run, {cpu:.0f} s of '
                   'CPU',
        write=args.write, blocks=[
            f'{args.worlds} seeded worlds (seeds 0-{args.worlds - 1}; 10 x 10 m arenas of '
            'posts, a wall with one or two doorways, a corridor, or two rooms; '
            '`sim_nodes/lidar_world.py`), each driven once per set-up by a go-to-goal '
            'controller blind to obstacles on a differential-drive base (radius 0.2 m, '
            '|v| <= 0.5 m/s, |omega| <= 1.5 rad/s, first-order lag 0.15 / 0.1 s, wheel slip '
            '3 +/- 2 %, odometry from noisy encoders), commands at 20 Hz, a 360-beam lidar at '
            '10 Hz (8 m, 1 cm noise, 0.2 % dropped beams). A run ends at the goal (0.3 m), at '
            f'a collision (true pose against true geometry), stuck (< 5 cm in 10 s) or after '
            f'{DURATION:.0f} s. "stop zone": collision_monitor\'s stop model written here '
            "(zero command while >= 4 scan points lie in its tutorial's PolygonStop, a box "
            "0.4 x 0.6 m ahead of base_link). Filters: config/unicycle.yaml's (alpha 2, "
            "margin 0.1 m, look-ahead 0.03 m, steering 100x cheaper) with the base's input "
            'limits and a zero-mean disturbance box (k_c 2 x std 0.05, 0.05, 0.1) for the lag '
            'and slip. "true circles": the map by hand and the true pose (the reference): '
            "posts widened by the body's radius, walls (10 cm thick) as circles sampled every "
            '5 cm along their centre lines (radius sqrt(0.25^2 + 0.025^2)); "scan": the state '
            'from odometry, each scan as LaserScan CDR bytes in frame `laser` (0.1 m ahead of '
            'base_link) through ObservationSources, placed in `odom` through tf at the '
            "scan's stamp (`/tf_static` base_link -> laser once, `/tf` odom -> base_link from "
            "odometry at 20 Hz and at every scan's stamp, as TFMessage CDR bytes through "
            '`read_tf`; `transform_tolerance` 0.1 s), into `SafetyFilter.set_points`, '
            '`footprint.radius` 0.2 m. The stop zone moves the scan to base_link by the '
            "laser's mount.",
            table, kinds,
            'Caveats: a scan is taken at one instant, without the sweep of a spinning lidar '
            "(its points are placed with the odometry's pose at the scan's stamp; a real "
            "sweep of 0.1 s smears them by the robot's motion meanwhile), and /tf comes "
            'without delay or loss. Between scans (up to 0.1 s) the filter decides on the '
            "latest scan's points, placed where they were seen: what the robot sees anew "
            "meanwhile waits for the next scan. The scan's filter works in odometry, which "
            "drifts from the truth (slip; it moves the points with it); the map's filter is "
            'given the true pose. The '
            'controller is blind: with a wall between start and goal, no set-up reaches the '
            'goal unless a doorway lies near the straight line, and a post dead ahead can '
            "park the filter (the QP's symmetric equilibrium) as it parks the stop zone. The "
            'decision time is per command on a shared, loaded machine: for the scan it holds '
            "the sources' step (the tf look-up at the scan's stamp, points into the odom "
            "frame, rows set) and the QP, not the encoding or reading of scans and /tf; a "
            'world takes 0.2-2 s of wall time per set-up.',
            'Pictures: `--out` holds one per set-up (the first 12 worlds).'])
    return 0


if __name__ == '__main__':
    sys.exit(main())

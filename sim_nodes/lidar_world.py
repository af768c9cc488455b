"""A robot's world in plain numpy: seeded rooms of posts, walls, corridors and doorways, a
differential-drive base with actuator lag, wheel slip and drifting odometry, a 2-D lidar ray
cast against the true geometry, and a go-to-goal controller that ignores every obstacle.

No middleware: a node or a benchmark turns these arrays into messages. Units and frames follow
REP 103 (m, rad, x forward, yaw counter-clockwise) and REP 105 (the world's frame is where
``odom`` starts: the start pose); the scan's ranges follow REP 117 (+inf: no return within
``range_max``, -inf: closer than ``range_min``, NaN: a dropped beam).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math
from typing import NamedTuple

import numpy as np

KINDS = ('posts', 'wall', 'corridor', 'rooms')
"""The kinds of world :func:`random_world` builds."""
KIND_WEIGHTS = (0.4, 0.2, 0.2, 0.2)
"""How often :func:`random_world` draws each of :data:`KINDS` when none is asked for."""


@dataclass(frozen=True)
class World:
    """One world: its obstacles (the true geometry), where the robot starts and its goal."""

    half_size: float
    """The arena is the square [-half_size, half_size]^2 (m); its sides are in ``segments``."""
    circles: np.ndarray
    """(C, 3) posts: x, y, radius (m)."""
    segments: np.ndarray
    """(S, 4) walls' centre lines: x0, y0, x1, y1 (m), the arena's four sides first."""
    start: np.ndarray
    """(3,) the start pose x, y, yaw (m, rad)."""
    goal: np.ndarray
    """(2,) the goal position (m)."""
    wall_thickness: float = 0.1
    """Every wall's thickness (m): a wall is the set of points within half of it from its
    centre line, rounded at its ends (a wall seen end-on still returns its end)."""
    kind: str = 'posts'
    """Which of :data:`KINDS` built it."""
    seed: int = 0
    """The seed that built it."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def clearance(world: World, points: np.ndarray) -> np.ndarray:
    """The distance (m) of each point to the nearest obstacle surface, negative inside a post.
    points: (N, 2) -> (N,); inf for a world without obstacles."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    best = np.full(len(points), np.inf)
    if len(world.circles):
        centre = world.circles[None, :, :2]
        gap = np.linalg.norm(points[:, None, :] - centre, axis=2) - world.circles[None, :, 2]
        best = np.minimum(best, gap.min(axis=1))
    if len(world.segments):
        a, b = world.segments[None, :, :2], world.segments[None, :, 2:]
        edge = b - a
        length2 = np.maximum((edge ** 2).sum(axis=2), 1e-18)
        s = np.clip(((points[:, None, :] - a) * edge).sum(axis=2) / length2, 0.0, 1.0)
        nearest = a + s[..., None] * edge
        distance = np.linalg.norm(points[:, None, :] - nearest, axis=2).min(axis=1)
        best = np.minimum(best, distance - world.wall_thickness / 2)
    return best


def wall_outline(segments: np.ndarray, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """The surface of walls of ``thickness`` about their centre lines ``segments`` (S, 4): the
    two sides as segments (2S, 4) and the rounded ends as circles (2S, 3); for thickness 0,
    the centre lines themselves and no circles."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    half = thickness / 2
    if half <= 0.0 or not len(segments):
        return segments, np.zeros((0, 3))
    edge = segments[:, 2:] - segments[:, :2]
    normal = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-18)
    shift = np.concatenate([normal, normal], axis=1) * half
    ends = np.concatenate([segments[:, :2], segments[:, 2:]])
    return (np.concatenate([segments + shift, segments - shift]),
            np.concatenate([ends, np.full((len(ends), 1), half)], axis=1))


def cast_rays(origin: np.ndarray, angles: np.ndarray, circles: np.ndarray,
              segments: np.ndarray) -> np.ndarray:
    """The distance along each ray from ``origin`` (2,) at world ``angles`` (B,) to the first
    obstacle surface in front of it, inf where it meets none. circles (C, 3), segments
    (S, 4) of no thickness (:func:`wall_outline` gives a thick wall's) -> (B,). From inside a
    post a ray meets the post's surface on its way out; a ray along a segment's own line does
    not meet it."""
    origin = np.asarray(origin, dtype=np.float64)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (B, 2), unit
    best = np.full(len(angles), np.inf)
    if len(circles):
        offset = origin - circles[:, :2]  # (C, 2)
        b = d @ offset.T  # (B, C): d . (o - c)
        c = (offset ** 2).sum(axis=1) - circles[:, 2] ** 2  # (C,)
        disc = b * b - c
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = -b - root, -b + root
        t = np.where(near > 0.0, near, far)
        t = np.where((disc >= 0.0) & (t > 0.0), t, np.inf)
        best = np.minimum(best, t.min(axis=1))
    if len(segments):
        a, edge = segments[:, :2], segments[:, 2:] - segments[:, :2]  # (S, 2)
        denom = _cross(d[:, None, :], edge[None, :, :])  # (B, S)
        to_a = a - origin  # (S, 2)
        with np.errstate(divide='ignore', invalid='ignore'):
            t = _cross(to_a[None, :, :], edge[None, :, :]) / denom
            s = _cross(to_a[None, :, :], d[:, None, :]) / denom
        hit = (denom != 0.0) & (t > 0.0) & (s >= 0.0) & (s <= 1.0)
        best = np.minimum(best, np.where(hit, t, np.inf).min(axis=1))
    return best


@dataclass(frozen=True)
class Lidar:
    """A 2-D lidar's geometry and noise (defaults: a 360-beam, 10 Hz, 8 m indoor lidar)."""

    beams: int = 360
    """Beams over a full turn, the first at ``angle_min``."""
    rate_hz: float = 10.0
    """Scans per second."""
    angle_min: float = -math.pi
    """The first beam's angle in the laser frame (rad)."""
    range_min: float = 0.12
    """Returns closer than this are reported as -inf (m)."""
    range_max: float = 8.0
    """No return beyond this: +inf (m)."""
    range_noise: float = 0.01
    """Standard deviation of the range noise (m)."""
    dropout: float = 0.002
    """The chance of a beam giving no reading (NaN)."""
    mount: tuple[float, float, float] = (0.1, 0.0, 0.0)
    """The laser frame's pose on base_link: x, y, yaw (m, rad)."""
    frame_id: str = 'laser'
    """The scan's frame."""

    @property
    def angle_increment(self) -> float:
        """The angle between two beams (rad)."""
        return 2.0 * math.pi / self.beams

    @property
    def angles(self) -> np.ndarray:
        """(beams,) the beams' angles in the laser frame (rad)."""
        return self.angle_min + np.arange(self.beams) * self.angle_increment


def laser_pose(pose: np.ndarray, lidar: Lidar) -> np.ndarray:
    """The laser frame's pose x, y, yaw in the world for the base's ``pose`` (3,)."""
    mx, my, myaw = lidar.mount
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * mx - s * my, pose[1] + s * mx + c * my, pose[2] + myaw])


def scan_ranges(world: World, pose: np.ndarray, lidar: Lidar,
                rng: np.random.Generator | None = None) -> np.ndarray:
    """One scan from the base's true ``pose`` (3,): (beams,) float32 ranges in the laser frame
    with noise (no noise without ``rng``), REP 117's +inf / -inf / NaN where there is no
    reading."""
    at = laser_pose(np.asarray(pose, dtype=np.float64), lidar)
    sides, ends = wall_outline(world.segments, world.wall_thickness)
    true = cast_rays(at[:2], lidar.angles + at[2], np.concatenate([world.circles, ends]), sides)
    ranges = true.copy()
    if rng is not None:
        ranges = ranges + rng.normal(0.0, lidar.range_noise, len(ranges))
    ranges = np.where(true > lidar.range_max, np.inf, ranges)
    ranges = np.where(ranges < lidar.range_min, -np.inf, ranges)
    if rng is not None and lidar.dropout > 0.0:
        ranges = np.where(rng.random(len(ranges)) < lidar.dropout, np.nan, ranges)
    return ranges.astype(np.float32)


def scan_fields(ranges: np.ndarray, lidar: Lidar, *, stamp_ns: int) -> dict:
    """The sensor_msgs/LaserScan fields of one scan (header as frame_id and stamp_ns)."""
    return {'frame_id': lidar.frame_id, 'stamp_ns': int(stamp_ns),
            'angle_min': lidar.angle_min,
            'angle_max': lidar.angle_min + (lidar.beams - 1) * lidar.angle_increment,
            'angle_increment': lidar.angle_increment, 'time_increment': 0.0,
            'scan_time': 1.0 / lidar.rate_hz, 'range_min': lidar.range_min,
            'range_max': lidar.range_max, 'ranges': np.asarray(ranges, dtype=np.float32),
            'intensities': np.zeros(0, np.float32)}


@dataclass(frozen=True)
class BaseModel:
    """A differential-drive base (defaults: a small indoor robot, about a TurtleBot's size)."""

    radius: float = 0.2
    """The body's radius (m): a collision is the true centre closer than this to a surface."""
    v_max: float = 0.5
    """|v| limit (m/s)."""
    omega_max: float = 1.5
    """|omega| limit (rad/s)."""
    tau_v: float = 0.15
    """Time constant of the wheels' first-order lag on v (s)."""
    tau_omega: float = 0.1
    """Time constant of the lag on omega (s)."""
    slip: float = 0.03
    """Mean wheel slip: the ground moves by (1 - slip) of what the wheels turn."""
    slip_std: float = 0.02
    """Standard deviation of the slip, drawn per step and clipped to [0, 0.5]."""
    odom_noise: float = 0.02
    """Relative standard deviation of the wheel encoders' v and omega."""


@dataclass
class BaseState:
    """The base's true pose, its odometry and its wheels' velocities."""

    pose: np.ndarray
    """(3,) the true x, y, yaw."""
    odom: np.ndarray
    """(3,) odometry's x, y, yaw: integrated from the encoders, drifting from ``pose``."""
    wheels: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """(2,) v, omega the wheels turn at (after the lag, before slip)."""


def start_state(world: World) -> BaseState:
    """The base at rest on the world's start, odometry starting there."""
    return BaseState(pose=world.start.astype(np.float64).copy(),
                     odom=world.start.astype(np.float64).copy())


def wrap(angle: float | np.ndarray) -> float | np.ndarray:
    """An angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def step_base(state: BaseState, command: np.ndarray, dt: float, model: BaseModel,
              rng: np.random.Generator | None = None) -> BaseState:
    """Advance ``state`` by ``dt`` under ``command`` (v, omega; clipped to the limits): the
    wheels follow the command through a first-order lag, the ground moves the base by the
    wheels' motion less the slip, odometry integrates the encoders' noisy reading of the
    wheels (slip unseen). Without ``rng`` no slip noise and no encoder noise."""
    v_cmd = float(np.clip(command[0], -model.v_max, model.v_max))
    w_cmd = float(np.clip(command[1], -model.omega_max, model.omega_max))
    v, w = state.wheels
    v += (v_cmd - v) * (1.0 - math.exp(-dt / model.tau_v))
    w += (w_cmd - w) * (1.0 - math.exp(-dt / model.tau_omega))
    if rng is None:
        slip_v = slip_w = model.slip
        read_v, read_w = v, w
    else:
        slip_v, slip_w = np.clip(rng.normal(model.slip, model.slip_std, 2), 0.0, 0.5)
        read_v, read_w = (np.array([v, w]) * (1.0 + rng.normal(0.0, model.odom_noise, 2)))
    pose = _integrate(state.pose, v * (1.0 - slip_v), w * (1.0 - slip_w), dt)
    odom = _integrate(state.odom, float(read_v), float(read_w), dt)
    return BaseState(pose=pose, odom=odom, wheels=np.array([v, w]))


def _integrate(pose: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    """Exact unicycle motion over ``dt`` at constant v, omega (an arc)."""
    x, y, yaw = pose
    if abs(w) < 1e-9:
        return np.array([x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw), yaw])
    yaw2 = yaw + w * dt
    r = v / w
    return np.array([x + r * (math.sin(yaw2) - math.sin(yaw)),
                     y - r * (math.cos(yaw2) - math.cos(yaw)), float(wrap(yaw2))])


def go_to_goal(pose: np.ndarray, goal: np.ndarray, model: BaseModel, *,
               heading_gain: float = 2.0, slow_radius: float = 0.5) -> np.ndarray:
    """v, omega straight at ``goal``, blind to obstacles: turn towards it, drive forward as
    far as the heading error's cosine allows, slowing within ``slow_radius``."""
    to_goal = np.asarray(goal, dtype=np.float64) - pose[:2]
    distance = float(np.hypot(*to_goal))
    error = float(wrap(math.atan2(to_goal[1], to_goal[0]) - pose[2]))
    v = model.v_max * max(math.cos(error), 0.0) * min(1.0, distance / slow_radius)
    omega = float(np.clip(heading_gain * error, -model.omega_max, model.omega_max))
    return np.array([v, omega])


# --- worlds -----------------------------------------------------------------------------------

class _Free(NamedTuple):
    """An occupancy grid of where the base's centre may be."""

    free: np.ndarray
    """(n, n) bool."""
    cell: float
    half_size: float

    def index(self, xy: np.ndarray) -> tuple[int, int]:
        n = self.free.shape[0]
        i = int(np.clip((xy[0] + self.half_size) / self.cell, 0, n - 1))
        j = int(np.clip((xy[1] + self.half_size) / self.cell, 0, n - 1))
        return i, j


def _free_grid(world: World, inflation: float, cell: float) -> _Free:
    n = int(round(2 * world.half_size / cell))
    centres = -world.half_size + (np.arange(n) + 0.5) * cell
    gx, gy = np.meshgrid(centres, centres, indexing='ij')
    points = np.stack([gx.ravel(), gy.ravel()], axis=1)
    free = (clearance(world, points) > inflation).reshape(n, n)
    return _Free(free, cell, world.half_size)


def reachable(world: World, inflation: float, *, cell: float = 0.05) -> bool:
    """Whether the goal can be reached from the start by a disc of radius ``inflation``
    (4-connected cells of ``cell`` m whose centres are farther than ``inflation`` from every
    surface)."""
    grid = _free_grid(world, inflation, cell)
    start, goal = grid.index(world.start[:2]), grid.index(world.goal)
    if not (grid.free[start] and grid.free[goal]):
        return False
    n = grid.free.shape[0]
    seen = np.zeros_like(grid.free)
    seen[start] = True
    queue = deque([start])
    while queue:
        i, j = queue.popleft()
        if (i, j) == goal:
            return True
        for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if 0 <= a < n and 0 <= b < n and grid.free[a, b] and not seen[a, b]:
                seen[a, b] = True
                queue.append((a, b))
    return False


def _arena(half: float) -> list[list[float]]:
    h = half
    return [[-h, -h, h, -h], [h, -h, h, h], [h, h, -h, h], [-h, h, -h, -h]]


def _posts(rng: np.random.Generator, half: float, count: int, low: float = 0.15,
           high: float = 0.5) -> list[list[float]]:
    return [[float(rng.uniform(-half + 0.5, half - 0.5)), float(rng.uniform(-half + 0.5,
                                                                           half - 0.5)),
             float(rng.uniform(low, high))] for _ in range(count)]


def _wall_with_doors(x: float, low: float, high: float, doors: list[tuple[float, float]]
                     ) -> list[list[float]]:
    """Vertical wall x = ``x`` from y ``low`` to ``high`` with gaps (centre, width)."""
    out, y = [], low
    for centre, width in sorted(doors):
        if centre - width / 2 > y:
            out.append([x, y, x, centre - width / 2])
        y = centre + width / 2
    if y < high:
        out.append([x, y, x, high])
    return out


def _layout(kind: str, rng: np.random.Generator, half: float
            ) -> tuple[list[list[float]], list[list[float]], np.ndarray, np.ndarray]:
    """Posts, inner walls, start xy and goal xy of one world of ``kind``."""
    edge = half - 0.6
    if kind == 'posts':
        start = np.array([-edge, rng.uniform(-edge, edge)])
        goal = np.array([edge, rng.uniform(-edge, edge)])
        return _posts(rng, half, int(rng.integers(8, 20))), [], start, goal
    if kind == 'wall':
        # a wall across the arena, one or two doorways, posts on either side
        doors = [(float(rng.uniform(-edge + 0.5, edge - 0.5)), float(rng.uniform(0.8, 1.4)))
                 for _ in range(int(rng.integers(1, 3)))]
        x = float(rng.uniform(-1.0, 1.0))
        walls = _wall_with_doors(x, -half, half, doors)
        start = np.array([-edge, rng.uniform(-edge, edge)])
        goal = np.array([edge, rng.uniform(-edge, edge)])
        return _posts(rng, half, int(rng.integers(3, 8))), walls, start, goal
    if kind == 'corridor':
        # a corridor along x, posts standing out of its walls; start and goal at its ends
        width = float(rng.uniform(1.2, 1.8))
        y0 = float(rng.uniform(-half + 1.5, half - 1.5))
        length = 2 * half - 1.0
        walls = [[-length / 2, y0 - width / 2, length / 2, y0 - width / 2],
                 [-length / 2, y0 + width / 2, length / 2, y0 + width / 2]]
        posts = [[float(rng.uniform(-length / 2 + 1.5, length / 2 - 1.5)),
                  y0 + float(rng.choice([-1, 1])) * width / 2, float(rng.uniform(0.2, 0.4))]
                 for _ in range(int(rng.integers(1, 4)))]
        start = np.array([-length / 2 + 0.4, y0 + rng.uniform(-0.1, 0.1)])
        goal = np.array([length / 2 - 0.4, y0 + rng.uniform(-0.1, 0.1)])
        return posts, walls, start, goal
    # rooms: two walls across, each with a doorway, posts in the rooms
    walls = []
    for x in (-half / 3, half / 3):
        x += float(rng.uniform(-0.4, 0.4))
        walls += _wall_with_doors(x, -half, half, [(float(rng.uniform(-edge + 0.5, edge - 0.5)),
                                                    float(rng.uniform(0.9, 1.4)))])
    start = np.array([-edge, rng.uniform(-edge, edge)])
    goal = np.array([edge, rng.uniform(-edge, edge)])
    return _posts(rng, half, int(rng.integers(2, 6))), walls, start, goal


def random_world(seed: int, *, kind: str | None = None, half_size: float = 5.0,
                 robot_radius: float = 0.2, start_clearance: float = 0.3,
                 attempts: int = 200) -> World:
    """A seeded world of ``kind`` (one of :data:`KINDS`; None: drawn from the seed) in an
    arena of side 2 ``half_size``, whose goal a disc of ``robot_radius`` + 0.15 m reaches from
    the start and whose start and goal are ``start_clearance`` m clear of every surface
    beyond the body. Posts that leave no such world are redrawn (``attempts`` times at most).

    Raises:
        ValueError: an unknown ``kind``, or no such world after ``attempts``.
    """
    if kind is not None and kind not in KINDS:
        raise ValueError(f'kind: {kind!r} is none of {", ".join(KINDS)}')
    rng = np.random.default_rng(seed)
    chosen = kind or KINDS[int(rng.choice(len(KINDS), p=KIND_WEIGHTS))]
    for _attempt in range(attempts):
        posts, walls, start_xy, goal = _layout(chosen, rng, half_size)
        to_goal = goal - start_xy
        yaw = float(wrap(math.atan2(to_goal[1], to_goal[0]) + rng.uniform(-1.0, 1.0)))
        world = World(half_size=half_size,
                      circles=np.array(posts, dtype=np.float64).reshape(-1, 3),
                      segments=np.array(_arena(half_size) + walls, dtype=np.float64),
                      start=np.array([start_xy[0], start_xy[1], yaw]), goal=goal,
                      kind=chosen, seed=seed)
        ends = clearance(world, np.stack([start_xy, goal]))
        if (ends > robot_radius + start_clearance).all() and reachable(world,
                                                                       robot_radius + 0.15):
            return world
    raise ValueError(f'seed: {seed} gives no reachable {chosen} world in {attempts} attempts')

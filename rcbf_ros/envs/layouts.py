"""Obstacle layouts: the shapes the simulators check exactly, and seeded random transfer layouts.

A layout is a tuple of :class:`Obstacle`. Each obstacle has a centre c, a *barrier radius* r (what
the safety filter sees under ``obstacles.radius``) and a shape:

- ``circle``: the disc ||p - c|| <= r.
- ``square``: the axis-aligned square of half-size s = r / sqrt(2); the barrier circle of radius
  r is its circumscribed circle.
- ``triangle<k>`` (k in 0..3): that square with its vertex k removed (vertices ordered
  (-s, -s), (-s, +s), (+s, +s), (+s, -s) around c), a right triangle whose hypotenuse is a
  diagonal of the square. Its circumscribed circle has the hypotenuse as diameter, i.e. it is the
  square's: centre c, radius s sqrt(2) = r.

So the filter keeps the robot out of the circumscribed circles (conservative), and the simulator
checks violations against the true polygon (:func:`signed_clearance`, exact).

Random layouts (paper's zero-shot transfer, ENVIRONMENTS.md) depend only on the seed: every draw
comes from ``numpy.random.default_rng(seed)``.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

SHAPES = ('circle', 'square', 'triangle0', 'triangle1', 'triangle2', 'triangle3')
"""Every shape name accepted in ``obstacles.shape``."""

UNICYCLE_GOAL = (2.5, 2.5)
"""Goal of the Unicycle arena (ref)."""
UNICYCLE_STARTS = ((-2.5, -2.5), (-2.5, 2.5), (2.5, -2.5), (-2.5, 0.0), (0.0, -2.5))
"""Start positions of the Unicycle (training start first; the rest: random-start option)."""
PVTOL_GOAL = (5.0, -1.5)
"""Goal of the PVTOL arena (ref)."""
PVTOL_STARTS = ((-4.5, 2.0), (-4.5, -2.0), (4.5, 2.0))
"""Start positions of the PVTOL (training start first; the rest: random-start option) (ref)."""


@dataclass(frozen=True)
class Obstacle:
    """One keep-out zone of a layout."""

    x: float
    """Centre x [m]."""
    y: float
    """Centre y [m]."""
    radius: float
    """Barrier radius r [m]: the disc itself, or the circumscribed circle of a polygon."""
    shape: str = 'circle'
    """One of :data:`SHAPES`."""

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f'obstacles.shape: unknown shape {self.shape!r}; use one of {SHAPES}')
        if not self.radius > 0:
            raise ValueError(f'obstacles.radius: must be > 0, got {self.radius}')

    @property
    def half_size(self) -> float:
        """s = r / sqrt(2) for squares and triangles."""
        return self.radius / math.sqrt(2.0)

    def vertices(self) -> np.ndarray:
        """Polygon vertices (V, 2) counter-clockwise-agnostic; empty (0, 2) for a circle."""
        if self.shape == 'circle':
            return np.zeros((0, 2))
        s = self.half_size
        square = np.array([[-s, -s], [-s, s], [s, s], [s, -s]]) + [self.x, self.y]
        if self.shape == 'square':
            return square
        return np.delete(square, int(self.shape[-1]), axis=0)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def _inside_convex(p: np.ndarray, vertices: np.ndarray) -> bool:
    """Whether p lies in the closed convex polygon (any vertex orientation)."""
    crosses = []
    for i in range(len(vertices)):
        a, b = vertices[i], vertices[(i + 1) % len(vertices)]
        crosses.append((b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]))
    crosses = np.asarray(crosses)
    return bool(np.all(crosses >= 0.0) or np.all(crosses <= 0.0))


def signed_clearance(obstacle: Obstacle, point: Sequence[float]) -> float:
    """Signed distance [m] from a point to the obstacle's TRUE shape: > 0 outside, < 0 inside.

    Circle: ||p - c|| - r. Polygon: distance to the boundary, negated inside.
    """
    p = np.asarray(point, dtype=np.float64)
    if obstacle.shape == 'circle':
        return float(np.hypot(p[0] - obstacle.x, p[1] - obstacle.y) - obstacle.radius)
    vertices = obstacle.vertices()
    boundary = min(_segment_distance(p, vertices[i], vertices[(i + 1) % len(vertices)])
                   for i in range(len(vertices)))
    return -boundary if _inside_convex(p, vertices) else boundary


def layout_from_params(xs: Sequence[float], ys: Sequence[float], radii: Sequence[float],
                       shapes: Sequence[str] | None = None) -> tuple[Obstacle, ...]:
    """Obstacles from the flat ``obstacles.x/.y/.radius(/.shape)`` parameter lists.

    Raises:
        ValueError: naming the key whose length differs from ``obstacles.x``.
    """
    n = len(xs)
    if len(ys) != n:
        raise ValueError(f'obstacles.y: expected {n} values (one per obstacles.x), got {len(ys)}')
    if len(radii) != n:
        raise ValueError(f'obstacles.radius: expected {n} values, got {len(radii)}')
    shapes = list(shapes) if shapes else ['circle'] * n
    if len(shapes) != n:
        raise ValueError(f'obstacles.shape: expected {n} values, got {len(shapes)}')
    return tuple(Obstacle(float(x), float(y), float(r), str(s))
                 for x, y, r, s in zip(xs, ys, radii, shapes))


def layout_to_params(layout: Sequence[Obstacle]) -> dict[str, list]:
    """The inverse of :func:`layout_from_params`: flat ``obstacles.*`` keys."""
    return {
        'obstacles.x': [o.x for o in layout],
        'obstacles.y': [o.y for o in layout],
        'obstacles.radius': [o.radius for o in layout],
        'obstacles.shape': [o.shape for o in layout],
    }


def _far_enough(centre: np.ndarray, others: Sequence[Sequence[float]], distance: float) -> bool:
    return all(float(np.hypot(*(centre - np.asarray(o)))) > distance for o in others)


@dataclass(frozen=True)
class RandomLayoutRules:
    """Rules of a random transfer layout (defaults: Unicycle, ENVIRONMENTS.md)."""

    attempts: int = 6
    """Obstacles tried; one that finds no valid centre in ``centre_tries`` draws is dropped."""
    centre_tries: int = 100
    """Centre draws per obstacle before giving up on it."""
    base_size: float = 0.6
    """Nominal half-size (circle radius) before the U[0.8, 1.2] scale."""
    scale_range: tuple[float, float] = (0.8, 1.2)
    """Uniform range of the size scale."""
    centre_low: tuple[float, float] = (-2.4, -2.4)
    """Lower corner of the uniform centre box."""
    centre_high: tuple[float, float] = (2.4, 2.4)
    """Upper corner of the uniform centre box."""
    separation: float = 2.1
    """Minimum distance between centres (strict)."""
    clearance: float = 1.2
    """Minimum distance of a centre from the goal and every start (strict)."""
    shapes: tuple[str, ...] = ('circle', 'square', 'triangle')
    """Shape kinds drawn uniformly (``triangle`` picks the removed vertex uniformly too)."""


UNICYCLE_RULES = RandomLayoutRules()
"""Unicycle transfer layouts: 6 attempts, circle/square/triangle of half-size 0.6 U[0.8, 1.2]."""
PVTOL_RULES = RandomLayoutRules(
    attempts=8, base_size=0.4, centre_low=(-5.6, -2.6), centre_high=(5.6, 2.6), separation=1.4,
    clearance=1.2, shapes=('circle',))
"""PVTOL transfer layouts: 8 circles r = 0.4 U[0.8, 1.2], separation 1.4, inside the arena
[-6, 6] x [-3, 3] shrunk by the nominal radius."""


def random_layout(seed: int, rules: RandomLayoutRules, goal: Sequence[float],
                  starts: Sequence[Sequence[float]]) -> tuple[Obstacle, ...]:
    """A random layout that depends only on ``seed`` (and the rules, goal and starts).

    Per attempt: shape, size scale, then up to ``centre_tries`` centres until one is farther
    than ``separation`` from every kept centre and farther than ``clearance`` from the goal and
    every start. For squares and triangles the half-size s is drawn and the barrier radius is
    s sqrt(2) (circumscribed circle); for circles the radius is the drawn size.
    """
    rng = np.random.default_rng(seed)
    kept: list[Obstacle] = []
    keep_out = [tuple(goal)] + [tuple(s[:2]) for s in starts]
    for _ in range(rules.attempts):
        kind = rules.shapes[int(rng.integers(len(rules.shapes)))]
        size = rules.base_size * float(rng.uniform(*rules.scale_range))
        removed = int(rng.integers(4))
        for _ in range(rules.centre_tries):
            centre = rng.uniform(rules.centre_low, rules.centre_high)
            if (_far_enough(centre, [(o.x, o.y) for o in kept], rules.separation)
                    and _far_enough(centre, keep_out, rules.clearance)):
                break
        else:
            continue
        if kind == 'circle':
            kept.append(Obstacle(float(centre[0]), float(centre[1]), size, 'circle'))
        else:
            shape = 'square' if kind == 'square' else f'triangle{removed}'
            kept.append(Obstacle(float(centre[0]), float(centre[1]), size * math.sqrt(2.0),
                                 shape))
    return tuple(kept)


def unicycle_random_layout(seed: int) -> tuple[Obstacle, ...]:
    """Unicycle transfer layout for ``seed`` (goal and all Unicycle starts kept clear)."""
    return random_layout(seed, UNICYCLE_RULES, UNICYCLE_GOAL, UNICYCLE_STARTS)


def pvtol_random_layout(seed: int) -> tuple[tuple[Obstacle, ...], bool]:
    """PVTOL transfer layout for ``seed``: (obstacles, operator present with probability 0.5).

    The operator coin comes from its own stream (``default_rng([seed, 1])``) so that it does
    not shift the obstacle draws.
    """
    obstacles = random_layout(seed, PVTOL_RULES, PVTOL_GOAL, PVTOL_STARTS)
    operator = bool(np.random.default_rng([seed, 1]).random() < 0.5)
    return obstacles, operator

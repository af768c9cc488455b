"""Seeded transfer layouts: separation rules, seed-only dependence, exact true geometry."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from rcbf_ros.envs.layouts import (
    Obstacle,
    PVTOL_GOAL,
    pvtol_random_layout,
    PVTOL_STARTS,
    signed_clearance,
    UNICYCLE_GOAL,
    unicycle_random_layout,
    UNICYCLE_STARTS,
)


def _dist(a, b) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def test_unicycle_layouts_follow_their_rules_for_100_seeds():
    counts = []
    for seed in range(100):
        layout = unicycle_random_layout(seed)
        counts.append(len(layout))
        assert 1 <= len(layout) <= 6
        for a, b in itertools.combinations(layout, 2):
            assert _dist((a.x, a.y), (b.x, b.y)) > 2.1
        for o in layout:
            assert -2.4 <= o.x <= 2.4 and -2.4 <= o.y <= 2.4
            for point in (UNICYCLE_GOAL, *UNICYCLE_STARTS):
                assert _dist((o.x, o.y), point) > 1.2
            size = o.radius if o.shape == 'circle' else o.half_size
            assert 0.6 * 0.8 <= size <= 0.6 * 1.2
    shapes = {o.shape[:8] for seed in range(100) for o in unicycle_random_layout(seed)}
    assert shapes == {'circle', 'square', 'triangle'}
    assert len(set(counts)) > 1  # the number of kept obstacles varies with the seed


def test_pvtol_layouts_follow_their_rules_for_100_seeds():
    operators = 0
    for seed in range(100):
        layout, operator = pvtol_random_layout(seed)
        operators += operator
        assert 1 <= len(layout) <= 8
        for a, b in itertools.combinations(layout, 2):
            assert _dist((a.x, a.y), (b.x, b.y)) > 1.4
        for o in layout:
            assert o.shape == 'circle' and 0.4 * 0.8 <= o.radius <= 0.4 * 1.2
            assert -6.0 < o.x < 6.0 and -3.0 < o.y < 3.0
            for point in (PVTOL_GOAL, *PVTOL_STARTS):
                assert _dist((o.x, o.y), point) > 1.2
    assert 30 <= operators <= 70  # probability 0.5


def test_layouts_depend_only_on_the_seed():
    np.random.seed(1)  # the global generator must not matter
    a = unicycle_random_layout(42)
    np.random.seed(2)
    assert unicycle_random_layout(42) == a
    assert unicycle_random_layout(43) != a
    assert pvtol_random_layout(42) == pvtol_random_layout(42)
    assert pvtol_random_layout(42) != pvtol_random_layout(43)


@pytest.mark.parametrize('shape', ['square', 'triangle0', 'triangle1', 'triangle2', 'triangle3'])
def test_polygons_lie_in_their_barrier_circle_and_clearance_is_exact(shape):
    o = Obstacle(1.0, -0.5, 0.8, shape)
    vertices = o.vertices()
    # Circumscribed: every vertex on the barrier circle.
    np.testing.assert_allclose(np.hypot(vertices[:, 0] - 1.0, vertices[:, 1] + 0.5), 0.8)
    s = o.half_size
    # A point 0.3 off the middle of a full side (right side unless the cut removed a vertex of
    # it, then the left side) is 0.3 from the polygon.
    side = -1.0 if shape in ('triangle2', 'triangle3') else 1.0
    assert signed_clearance(o, (1.0 + side * (s + 0.3), -0.5)) == pytest.approx(0.3)
    corner = vertices[0] + np.sign(vertices[0] - [1.0, -0.5]) * 0.1
    assert signed_clearance(o, corner) == pytest.approx(0.1 * math.sqrt(2))


def test_triangle_clearance_sign_on_the_cut_corner():
    o = Obstacle(0.0, 0.0, math.sqrt(2), 'triangle2')  # unit square without (+1, +1)
    assert signed_clearance(o, (0.6, 0.6)) > 0  # in the removed half: outside
    assert signed_clearance(o, (-0.6, -0.6)) == pytest.approx(-0.4)  # inside
    assert signed_clearance(o, (0.6, 0.6)) == pytest.approx(1.2 / math.sqrt(2))  # hypotenuse
    circle = Obstacle(0.0, 0.0, 0.5)
    assert signed_clearance(circle, (0.0, 0.2)) == pytest.approx(-0.3)


def test_bad_shape_names_the_key():
    with pytest.raises(ValueError, match='obstacles.shape'):
        Obstacle(0.0, 0.0, 1.0, 'hexagon')

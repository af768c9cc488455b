"""Ball arithmetic encloses: the exact value at any point inside the operands' balls lies in
the result's ball (exact rationals for the field operations), jets' gradients enclose the
derivatives, and undecided comparisons are run both ways."""
from __future__ import annotations

from fractions import Fraction
import math

from hypothesis import example, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.core.ball import (
    Ball,
    ball_cos,
    BALL_NAMESPACE,
    ball_sin,
    hull_over_branches,
    Jet,
    JET_NAMESPACE,
    Undecided,
)
from rcbf_ros.core.dynamics import CarFollowing, PVTOL, state_names

centres = st.floats(-1e3, 1e3)
radii = st.floats(0.0, 10.0)
fractions = st.floats(0.0, 1.0)


def _point(ball: Ball, t: float) -> Fraction:
    """The exact point of the ball at t in [0, 1] from its low end."""
    return Fraction(ball.centre) - Fraction(ball.radius) + 2 * Fraction(ball.radius) * Fraction(t)


def _holds(ball: Ball, value: Fraction | float) -> bool:
    """Whether the exact reals [c - r, c + r] hold ``value`` (all of them: r = inf)."""
    if ball.radius == math.inf:
        return True
    return abs(Fraction(value) - Fraction(ball.centre)) <= Fraction(ball.radius)


@settings(max_examples=300, deadline=None)
@given(a=centres, ra=radii, b=centres, rb=radii, k=st.floats(-1e3, 1e3), ta=fractions,
       tb=fractions, power=st.integers(0, 5))
def test_every_operation_encloses_its_exact_value(a, ra, b, rb, k, ta, tb, power):
    x, y = Ball(a, ra), Ball(b, rb)
    p, q = _point(x, ta), _point(y, tb)
    exact_k = Fraction(k)
    assert _holds(x + y, p + q) and _holds(x - y, p - q) and _holds(x * y, p * q)
    assert _holds(x + k, p + exact_k) and _holds(k - x, exact_k - p)
    assert _holds(k * x, exact_k * p) and _holds(-x, -p) and _holds(abs(x), abs(p))
    assert _holds(x ** power, p ** power)
    if k != 0.0:
        assert _holds(x / k, p / exact_k)


@settings(max_examples=300, deadline=None)
@given(a=st.floats(-50, 50), ra=st.floats(0, 5), t=fractions)
@example(a=15.75, ra=1e-14, t=0.0)  # the float nearest c - r lies outside the exact ball
def test_sin_and_cos_enclose_their_values(a, ra, t):
    x = Ball(a, ra)
    point = float(_point(x, t))
    # the float nearest an end may lie just outside the exact ball: take the one inside
    point = point if _holds(x, point) else x.centre
    for function, exact in ((ball_sin, math.sin), (ball_cos, math.cos)):
        out = function(x)
        assert _holds(out, exact(point))
        assert out.low >= -1.0 - 1e-12 and out.high <= 1.0 + 1e-12


def test_sin_and_cos_of_an_unbounded_ball_are_the_whole_range():
    for centre in (math.inf, -math.inf, math.nan):
        for function in (ball_sin, ball_cos):
            out = function(Ball(centre, 1.0))
            assert out.low <= -1.0 and out.high >= 1.0


def test_the_rounding_of_a_sum_is_covered():
    # 1 + 2^-60 rounds to 1: the radius must still hold the exact sum
    total = Ball(1.0) + Ball(2.0 ** -60)
    assert _holds(total, Fraction(1) + Fraction(2) ** -60)
    assert total.radius > 0.0


def test_a_comparison_outside_a_hull_is_refused_when_undecided():
    assert (Ball(1.0, 0.5) < 2.0) is True and (Ball(1.0, 0.5) >= 2.0) is False
    with pytest.raises(Undecided):
        assert Ball(1.0, 0.5) < 1.2
    with pytest.raises(TypeError):
        bool(Ball(1.0))


def _run(source_lines: list[str], n_x: int, returned: str, namespace: dict):
    text = '\n'.join(['def run(values):', f'    {", ".join(state_names(n_x))}, = values',
                      *(f'    {line}' for line in source_lines), f'    return {returned}', ''])
    scope = dict(namespace)
    exec(compile(text, '<test>', 'exec'), scope)  # noqa: S102 - the test's own source
    return scope['run']


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_the_drift_over_a_switch_is_the_hull_of_both_branches(data):
    """Car Following's prior over a ball straddling a braking switch: every point's f (either
    branch) lies in the joined result, and the run says it was not smooth."""
    source = CarFollowing().closed_form_source()
    f = ', '.join(e if isinstance(e, str) else repr(e) for e in source.f)
    over_balls = _run(list(source.lines), 10, f'[{f}]', BALL_NAMESPACE)
    at_points = _run(list(source.lines), 10, f'[{f}]', {'cos': math.cos, 'sin': math.sin})
    gap = data.draw(st.floats(5.5, 6.5))
    centre = [34.0, 30.0, 34.0 - gap, 31.0, 22.0, 29.0, 16.0, 35.0, 10.0, 30.0]
    radius = data.draw(st.lists(st.floats(0.0, 0.6), min_size=10, max_size=10))
    box = [Ball(c, r) for c, r in zip(centre, radius)]
    joined, smooth = hull_over_branches(over_balls, box)
    straddles = box[0].low - box[2].high < 6.0 <= box[0].high - box[2].low
    if straddles and radius[0] + radius[2] > 0.0:
        assert not smooth
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    for _ in range(50):
        point = [c + r * rng.uniform(-1.0, 1.0) for c, r in zip(centre, radius)]
        for value, enclosure in zip(at_points(point), joined):
            inside = enclosure if isinstance(enclosure, Ball) else Ball(enclosure)
            assert inside.low <= value <= inside.high


@settings(max_examples=60, deadline=None)
@given(x=st.tuples(*[st.floats(-3, 3)] * 7), r=st.tuples(*[st.floats(0, 0.3)] * 7),
       t=st.tuples(*[fractions] * 7))
def test_jets_enclose_the_values_and_the_gradient_of_the_pvtol_drift(x, r, t):
    """f and its Jacobian (the source's own J, an independent derivation) at any point of the
    box lie in the jets' value and grad."""
    source = PVTOL().closed_form_source()
    f = ', '.join(e if isinstance(e, str) else repr(e) for e in source.f)
    over_jets = _run(list(source.lines), 7, f'[{f}]', JET_NAMESPACE)
    jets, smooth = hull_over_branches(over_jets, [Jet.variable(c, w, k)
                                                  for k, (c, w) in enumerate(zip(x, r))])
    assert smooth
    point = [c + w * (2.0 * s - 1.0) for c, w, s in zip(x, r, t)]
    point = np.array([p if _holds(Ball(c, w), p) else c for p, c, w in zip(point, x, r)])
    jet = source.function()(point)
    for i, value in enumerate(jet.f):
        out = jets[i]
        if not isinstance(out, Jet):
            assert value == out
            continue
        assert _holds(out.value, value)
        for k in range(7):
            assert _holds(out.grad.get(k, Ball(0.0)), jet.jacobian[i, k])

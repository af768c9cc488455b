"""Sensor points in the filter: rows replaced per message, no rebuild (SafetyFilter.set_points).

The oracle is a filter built from scratch with the same points as a static circle family (the
generated per-row code): the two must give the same command."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
from point_oracle import points_filter
import pytest

from rcbf_ros.core import filter as filter_module
from rcbf_ros.core.config import filter_config_from_params, MIN_VOXEL_SIZE
from rcbf_ros.core.filter import POINTS_BARRIER, SafetyFilter
from rcbf_ros.messages import sensor

_BASE = {
    'system': 'unicycle', 'alpha': 2.0, 'input_weight': [1.0, 0.01],
    'input_limits.min': [-2.5, -2.5], 'input_limits.max': [2.5, 2.5],
    'obstacles.x': [0.0], 'obstacles.y': [4.0], 'obstacles.radius': [0.5],
    'obstacles.margin': 0.1, 'obstacles.lookahead': 0.03, 'obstacles.heading_index': 2,
    'obstacles.speed_input': 0,
    'observation_sources': ['front'], 'front.type': 'scan', 'front.topic': 'scan',
    'footprint.radius': 0.2,
}


def _config(**changes):
    params = dict(_BASE)
    params.update(changes)
    return filter_config_from_params(params)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), n=st.integers(1, 12),
       v=st.floats(-2.5, 2.5), w=st.floats(-2.5, 2.5), heading=st.floats(-math.pi, math.pi))
def test_points_give_the_command_of_the_same_static_circles(seed, n, v, w, heading):
    rng = np.random.default_rng(seed)
    config = _config()
    points = rng.uniform(-2.0, 2.0, (n, 2))
    state = [0.0, 0.0, heading]
    points = points[np.linalg.norm(points, axis=1) > 0.6]  # the robot starts outside
    if not len(points):
        return
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(rng.uniform(-5, 5, (30, 2)))  # replaced, not kept
    fast.set_points(points)
    mine = fast.filter(state, [v, w], [-0.05, 0, 0], [0.025, 0.025, 0])
    theirs = points_filter(config, points).filter(state, [v, w], [-0.05, 0, 0], [0.025, 0.025, 0])
    assert mine.fail_safe == theirs.fail_safe
    np.testing.assert_allclose(mine.u_safe, theirs.u_safe, atol=2e-5)
    k = config.problem.n_barriers
    assert mine.barrier_names[-1] == POINTS_BARRIER and len(mine.h) == k + 1
    assert mine.h[-1] == pytest.approx(theirs.h[k:].min(), abs=1e-9)
    assert mine.constraint_values[-1] == pytest.approx(theirs.constraint_values[k:].min(),
                                                       abs=1e-5)
    # every point's own row, whether the proposal passes through or is solved for
    np.testing.assert_allclose(mine.points.h, theirs.h[k:], atol=1e-9)
    np.testing.assert_allclose(mine.points.values, theirs.constraint_values[k:], atol=1e-5)
    np.testing.assert_array_equal(np.stack([mine.points.x, mine.points.y], 1), points)


def test_without_points_the_answer_is_the_problems_own():
    config = _config()
    with_sources = SafetyFilter(config.problem, footprint=config.footprint)
    without = SafetyFilter(config.problem)
    for u in ([1.0, 0.0], [2.5, -1.0], [-1.0, 2.0]):
        mine, theirs = with_sources.filter([0.0, 3.0, 1.5], u), without.filter([0.0, 3.0, 1.5], u)
        np.testing.assert_allclose(mine.u_safe, theirs.u_safe, atol=1e-6)
        assert mine.h[-1] == math.inf and with_sources.point_count == 0


def test_a_wall_of_points_ahead_slows_the_robot_and_every_row_holds():
    config = _config()
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    wall = np.stack([np.full(4000, 1.0), np.linspace(-20.0, 20.0, 4000)], axis=1)
    fast.set_points(wall)
    result = fast.filter([0.4, 0.0, 0.0], [2.5, 0.0])
    assert not result.fail_safe and result.u_safe[0] < 1.0
    # every row holds up to the slack the QP's soft rows trade (weight slack_weight)
    assert result.needed_slack <= 1e-5
    assert result.constraint_values.min() >= -result.needed_slack - 1e-12
    assert fast.point_count == 4000


def test_the_fallback_solve_on_the_rows_that_bind_matches(monkeypatch):
    config = _config()
    points = np.array([[1.0, 0.0], [1.0, 0.3], [0.9, -0.4]])
    expected = points_filter(config, points).filter([0.2, 0.0, 0.1], [2.0, 0.5])
    monkeypatch.setattr(filter_module, '_active_set_steps', lambda *args: None)
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    result = fast.filter([0.2, 0.0, 0.1], [2.0, 0.5])
    assert result.status == 'solved' and not result.fail_safe
    np.testing.assert_allclose(result.u_safe, expected.u_safe, atol=1e-4)


@pytest.mark.parametrize('points', [np.zeros((3, 3)), np.array([[0.0, math.nan]]),
                                    np.zeros(4)])
def test_set_points_refuses_what_is_not_finite_n_by_2(points):
    config = _config()
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    with pytest.raises(ValueError, match='set_points'):
        fast.set_points(points)
    with pytest.raises(ValueError, match='without a footprint'):
        SafetyFilter(config.problem).set_points(np.zeros((1, 2)))


@pytest.mark.parametrize('points', [
    np.array([[1e200, -1e300], [0.0, 1e-300]]),  # finite, their squares' sum is not
    np.array([[1.7e308, -1.7e308]] * 3), np.zeros((0, 2)),
    np.asfortranarray(np.arange(8.0).reshape(4, 2)), np.arange(8.0).reshape(2, 4).T])
def test_set_points_takes_every_finite_n_by_2_whatever_its_size_or_layout(points):
    # finiteness is checked by one sum of squares, each entry where the sum is not finite
    config = _config()
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    assert fast.point_count == len(points)
    for bad in (math.inf, -math.inf, math.nan):
        spoiled = np.array(points, order='K')
        if spoiled.size:
            spoiled[-1, 0] = bad
            with pytest.raises(ValueError, match='finite'):
                fast.set_points(spoiled)


@pytest.mark.parametrize(('changes', 'key'), [
    ({'observation_sources': ['obstacles']}, 'observation_sources'),
    ({'observation_sources': ['a.b']}, 'observation_sources'),
    ({'front.type': 'sonar'}, 'front.type'),
    ({'front.type': ''}, 'front.type'),
    ({'front.topic': ''}, 'front.topic'),
    ({'front.timeout_s': 0.0}, 'front.timeout_s'),
    ({'front.voxel_size': MIN_VOXEL_SIZE / 2}, 'front.voxel_size'),
    ({'front.min_height': 1.0, 'front.max_height': 0.0}, 'front.min_height'),
    ({'observation_sources': ['front', 'back'], 'back.type': 'pointcloud',
      'back.topic': 'scan'}, 'observation_sources'),
    ({'footprint.radius': 0.0, 'obstacles.margin': 0.0, 'obstacles.lookahead': 0.0,
      'obstacles.speed_input': -1},
     'footprint.radius'),
    ({'base_frame_id': 'odom'}, 'base_frame_id'),
])
def test_bad_source_parameters_name_the_key(changes, key):
    with pytest.raises(ValueError) as caught:
        _config(**changes)
    text = str(caught.value)
    assert text.startswith(key) and '\n' not in text


def test_the_voxel_floor_is_the_readers():
    assert MIN_VOXEL_SIZE == sensor.MIN_VOXEL_SIZE
    from rcbf_ros.core.config import MIN_OBSTACLES_ANGLE
    assert MIN_OBSTACLES_ANGLE == sensor.MIN_OBSTACLES_ANGLE


# --- many rows that can bind: the exact answer, else fewer rows that imply them all ----------

def _corridor(rng: np.random.Generator, n: int, half_width: float = 0.45) -> np.ndarray:
    """``n`` points on two walls along x, ``half_width`` (to 5 cm more) either side."""
    side = rng.choice([-1.0, 1.0], n)
    return np.stack([rng.uniform(-3.0, 3.0, n),
                     side * (half_width + rng.uniform(0.0, 0.05, n))], axis=1)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), v=st.floats(-2.5, 2.5), w=st.floats(-2.5, 2.5),
       heading=st.floats(-0.3, 0.3))
def test_many_binding_points_give_the_answer_of_the_exact_solve_on_all(seed, v, w, heading):
    config = _config()
    points = _corridor(np.random.default_rng(seed), 3000)
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    state = [0.0, 0.0, heading]
    mine = fast.filter(state, [v, w])
    saved = filter_module.EXACT_ROWS
    try:
        filter_module.EXACT_ROWS = 10**9  # every row that can bind in one solve
        theirs = fast.filter(state, [v, w])
    finally:
        filter_module.EXACT_ROWS = saved
    assert mine.fail_safe == theirs.fail_safe
    np.testing.assert_allclose(mine.u_safe, theirs.u_safe, atol=1e-6)


@settings(max_examples=20, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), v=st.floats(-2.5, 2.5), w=st.floats(-2.5, 2.5),
       heading=st.floats(-0.3, 0.3), far=st.floats(1e3, 1e6), many=st.booleans())
def test_a_far_point_changes_nothing(seed, v, w, heading, far, many):
    """A point 1e3 to 1e6 m away (its row's right-hand side up to about 1e12) leaves the
    answer as it is without it: every row is met to its own scale, in the exact solve on few
    rows and in the one that adds rows (``many``: a corridor of 3,000 points), and in the row
    check; the far row's scale loosened them all."""
    rng = np.random.default_rng(seed)
    points = _corridor(rng, 3000) if many else rng.uniform(-2.0, 2.0, (8, 2))
    points = points[np.linalg.norm(points, axis=1) > 0.6]
    fast = SafetyFilter(_config().problem, footprint=_config().footprint)
    state = [0.0, 0.0, heading]
    fast.set_points(points)
    near = fast.filter(state, [v, w])
    fast.set_points(np.vstack([points, [[far, -far]]]))
    with_far = fast.filter(state, [v, w])
    assert (with_far.fail_safe, with_far.status) == (near.fail_safe, near.status)
    np.testing.assert_allclose(with_far.u_safe, near.u_safe, rtol=0, atol=1e-9)


def test_rows_merged_when_the_exact_solve_cannot_finish_still_meet_every_row(monkeypatch):
    config = _config()
    points = _corridor(np.random.default_rng(3), 20_000)
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    monkeypatch.setattr(SafetyFilter, '_generated', lambda *args: None)
    for u in ([2.5, 0.0], [2.5, 2.5], [-2.5, -1.0]):
        result = fast.filter([0.0, 0.0, 0.1], u)
        binding = fast.point_count + config.problem.n_barriers - fast._pruned
        assert binding > filter_module.EXACT_ROWS
        assert not result.fail_safe, result.reason
        assert result.needed_slack <= 1e-5
        assert result.constraint_values.min() >= -result.needed_slack - 1e-12


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_u=st.integers(1, 3), rows=st.integers(1, 400),
       count=st.integers(2, 40))
def test_merged_rows_are_below_every_row_at_every_action_in_the_box(seed, n_u, rows, count):
    rng = np.random.default_rng(seed)
    low = rng.uniform(-3.0, 0.0, n_u)
    high = low + rng.uniform(0.0, 4.0, n_u)
    applied = rng.uniform(low, high)
    lg = rng.normal(0.0, rng.uniform(0.1, 10.0), (rows, n_u))
    upper = rng.normal(0.0, 5.0, rows)
    merged_lg, merged_upper = filter_module.merged_rows(
        lg=lg, upper=upper, applied=applied, u_min=low, u_max=high, count=count)
    assert merged_upper.size <= count and merged_lg.shape == (merged_upper.size, n_u)
    actions = np.concatenate([rng.uniform(low, high, (200, n_u)),
                              np.where(rng.random((50, n_u)) < 0.5, low, high)])
    steps = actions - applied
    original = upper + steps @ lg.T            # (actions, rows)
    merged = merged_upper + steps @ merged_lg.T
    # an action meeting every merged row with a slack meets every row with it
    scale = 1.0 + np.abs(original).max()
    assert np.all(merged.min(axis=1) <= original.min(axis=1) + 1e-12 * scale)


def _terms_by_comparison(circles, x, u):
    """The look-ahead rows' (h, grads) of _Circles.terms, the point behind chosen by comparing
    every dx^2 + dy^2 with delta^2 (the oracle of its test for the least h)."""
    cos, sin = math.cos(x[circles.heading]), math.sin(x[circles.heading])
    offset = circles.lookahead
    if u[circles.speed] < 0.0:
        dx = (x[circles.i] - offset * cos) - circles.cx
        dy = (x[circles.j] - offset * sin) - circles.cy
        if bool((dx * dx + dy * dy >= circles.delta_sq).all()):
            offset = -offset
    dx = (x[circles.i] + offset * cos) - circles.cx
    dy = (x[circles.j] + offset * sin) - circles.cy
    h = dx * dx + dy * dy - circles.delta_sq
    d_heading = dy * (2.0 * offset * cos) - dx * (2.0 * offset * sin)
    return h, np.array([2.0 * dx, 2.0 * dy, d_heading])


_HOSTILE = st.sampled_from([0.0, -0.0, 3.0, 4.0, 1e-300, 1e150, -1e155, 1e200, 1e307,
                            math.inf, math.nan])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), n=st.integers(0, 40), backwards=st.booleans(),
       heading=st.sampled_from([0.0, 1.0, -2.5]), spread=st.sampled_from([0.0, 1.0, 1e160]),
       per_point=st.booleans(), far=st.booleans(),
       specials=st.lists(st.tuples(st.integers(0, 80), _HOSTILE), max_size=6))
def test_the_point_behind_is_taken_exactly_where_every_point_is_clear(
        seed, n, backwards, heading, spread, per_point, far, specials):
    # the point behind is chosen from the least h (dx^2 + dy^2 - delta^2 >= 0 for every point)
    # where the comparisons of every dx^2 + dy^2 with delta^2 choose it: points on the circle
    # (h exactly 0), overflow to inf on either side (inf - inf is NaN), NaN, no point
    rng = np.random.default_rng(seed)
    circles = SafetyFilter(_config().problem, footprint=_config().footprint)._points._circles
    lookahead = circles.lookahead
    x = [lookahead * math.cos(heading), lookahead * math.sin(heading), heading]
    values = rng.uniform(5.0, 50.0, 2 * n) * rng.choice([-1.0, 1.0], 2 * n)  # clear, most
    if far:  # every dx^2 + dy^2 inf: inf - inf where delta^2 is inf too
        values *= 1e200
    elif n:
        values[0], values[n] = 3.0, 4.0  # 5 m from the point behind, at the origin
    for where, special in specials:
        if n:
            values[where % values.size] = special
    circles.cx, circles.cy = values[:n].copy(), values[n:].copy()
    delta = 5.0 + spread * (rng.uniform(0.0, 1.0, n) if per_point else 1.0)
    u = [-1.0 if backwards else 1.0, 0.0]
    with np.errstate(all='ignore'):
        circles.delta_sq = delta * delta
        h, index, grads = circles.terms(x, u, None, None)
        want_h, want_grads = _terms_by_comparison(circles, x, u)
    assert index == [circles.i, circles.j, circles.heading]
    assert h.tobytes() == want_h.tobytes() and grads.tobytes() == want_grads.tobytes()


def test_where_the_scaled_rows_are_not_certified_the_rows_as_they_are_answer(monkeypatch):
    """The many-row path's exact solve on rows scaled to their own scale may fail its
    certificate (round-off in rows of large gradient); the rows as they are are then solved,
    before any QP is set up: the same answer, no OSQP."""
    config = _config()
    points = np.array([[1.0, 0.0], [1.0, 0.3], [0.9, -0.4]])
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    expected = fast.filter([0.2, 0.0, 0.1], [2.0, 0.5])
    assert not expected.fail_safe and expected.status == 'solved'
    scaled = []

    def uncertifiable(rows, upper, k, largest=None):
        scaled.append(len(rows))
        return [list(row) for row in rows], list(upper), -1.0  # no answer meets it
    monkeypatch.setattr(filter_module, '_each_row_own', uncertifiable)
    monkeypatch.setattr(filter_module, '_solve_once', lambda *args: pytest.fail('OSQP used'))
    result = fast.filter([0.2, 0.0, 0.1], [2.0, 0.5])
    assert scaled and result.status == 'solved'
    np.testing.assert_array_equal(result.u_safe, expected.u_safe)

"""Which sensor points bind: FilterResult.points, binding_points and filter_info's section.

The oracle for the row values is a filter built from scratch with the same points as a static
circle family (one barrier per point, the generated per-row code): the points reported must be
those of least row value in its rows, with its values. The bound of the section is checked
with 100,000 points, and the bytes the node writes are read back by rosbags' own decoder.
"""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
from point_oracle import points_filter
import pytest

from rcbf_ros.core import filter_info
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import BINDING_POINTS, binding_points, PointValues
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.filter_edge import FilterEdge

_BASE = {
    'system': 'unicycle', 'alpha': 2.0, 'input_weight': [1.0, 0.01],
    'input_limits.min': [-2.5, -2.5], 'input_limits.max': [2.5, 2.5],
    'obstacles.x': [0.0], 'obstacles.y': [4.0], 'obstacles.radius': [0.5],
    'obstacles.margin': 0.1, 'obstacles.lookahead': 0.03, 'obstacles.heading_index': 2,
    'obstacles.speed_input': 0,
    'observation_sources': ['front'], 'front.type': 'scan', 'front.topic': 'scan',
    'footprint.radius': 0.2,
}
BOX = ([-0.05, 0.0, 0.0], [0.025, 0.025, 0.0])


def _sections(data: bytes) -> dict[str, np.ndarray]:
    """filter_info's sections as rosbags' decoder reads them (the independent reader)."""
    message = jazzy_typestore().deserialize_cdr(data, 'std_msgs/msg/Float64MultiArray')
    values, out, offset = np.asarray(message.data), {}, message.layout.data_offset
    for dim in message.layout.dim:
        out[dim.label] = values[offset:offset + dim.size]
        offset += dim.size
    return out


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), n=st.integers(1, 60), v=st.floats(-2.5, 2.5),
       w=st.floats(-2.5, 2.5), heading=st.floats(-math.pi, math.pi))
def test_the_points_reported_are_those_of_least_row_value(seed, n, v, w, heading):
    rng = np.random.default_rng(seed)
    config = filter_config_from_params(_BASE)
    points = rng.uniform(-2.0, 2.0, (n, 2))
    points = points[np.linalg.norm(points, axis=1) > 0.6]  # the robot starts outside
    if not len(points):
        return
    state = [0.0, 0.0, heading]
    fast = SafetyFilter(config.problem, footprint=config.footprint)
    fast.set_points(points)
    mine = fast.filter(state, [v, w], *BOX)
    theirs = points_filter(config, points).filter(state, [v, w], *BOX)
    assert mine.fail_safe == theirs.fail_safe
    k = config.problem.n_barriers
    values, h = theirs.constraint_values[k:], theirs.h[k:]
    rows = binding_points(mine.points)
    m = min(BINDING_POINTS, len(points))
    assert rows.shape == (m, 4) and np.isfinite(rows).all()
    # each row is one of the points, exactly, and no point is reported twice
    index = [int(np.flatnonzero((points == row[:2]).all(axis=1))[0]) for row in rows]
    assert len(set(index)) == m
    np.testing.assert_allclose(rows[:, 2], values[index], atol=1e-5)
    np.testing.assert_allclose(rows[:, 3], h[index], atol=1e-9)
    # they are the least: the oracle's m smallest values, in ascending order
    np.testing.assert_allclose(rows[:, 2], np.sort(values)[:m], atol=1e-5)
    assert np.all(np.diff(rows[:, 2]) >= 0.0)
    if m < len(points):
        left_out = np.delete(values, index)
        assert values[index].max() <= left_out.min() + 1e-5
    # the least of them is the one sensor_points barrier the result reports
    assert rows[0, 2] == pytest.approx(mine.constraint_values[-1], abs=1e-12)


def test_binding_points_closed_forms():
    """Ascending by row value, ties by the earlier point, NaN or inf left out, at most limit."""
    x = np.arange(6.0)
    values = np.array([0.5, -0.1, np.nan, 0.5, np.inf, 0.2])
    h = np.array([1.0, 2.0, 3.0, 4.0, 5.0, np.nan])
    rows = binding_points(PointValues(x, -x, h, values), limit=3)
    np.testing.assert_array_equal(rows, [[1.0, -1.0, -0.1, 2.0], [0.0, 0.0, 0.5, 1.0],
                                         [3.0, -3.0, 0.5, 4.0]])
    assert binding_points(PointValues(x, -x, h, values), limit=10).shape == (3, 4)
    tie = binding_points(PointValues(x, -x, h, values), limit=2)
    np.testing.assert_array_equal(tie[:, 0], [1.0, 0.0])  # of the two 0.5s, point 0
    assert binding_points(None).shape == (0, 4)
    assert binding_points(PointValues(x, x, h, values), limit=0).shape == (0, 4)
    empty = np.empty(0)
    assert binding_points(PointValues(empty, empty, empty, empty)).shape == (0, 4)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 3000), levels=st.integers(1, 2000),
       limit=st.integers(0, 40), bad=st.floats(0.0, 0.05), order=st.sampled_from(
           ['random', 'ascending', 'descending']))
def test_binding_points_are_the_least_of_a_sort(seed, n, levels, limit, bad, order):
    """Against a sort of every point by (row value, index), among those with finite values:
    many ties (values from ``levels`` levels), NaN and inf in the values and in h, any order
    and any size either side of the groups of the first pass."""
    rng = np.random.default_rng(seed)
    values = rng.integers(0, levels, n).astype(float) - levels / 3
    if order != 'random':
        values = np.sort(values)[::1 if order == 'ascending' else -1].copy()
    h = rng.uniform(-1.0, 1.0, n)
    for array in (values, h):
        hit = rng.random(n) < bad
        array[hit] = rng.choice([np.nan, np.inf, -np.inf], int(hit.sum()))
    x = np.arange(float(n))
    rows = binding_points(PointValues(x, -x, h, values), limit=limit)
    eligible = [i for i in range(n) if math.isfinite(values[i]) and math.isfinite(h[i])]
    expected = sorted(eligible, key=lambda i: (values[i], i))[:limit]
    assert rows[:, 0].astype(int).tolist() == expected
    np.testing.assert_array_equal(rows[:, 2], values[expected])
    np.testing.assert_array_equal(rows[:, 3], h[expected])


def _decision(safety_filter: SafetyFilter, state: list[float], u: list[float]):
    return logic.decide(safety_filter=safety_filter, proposal=logic.Proposal(u=np.array(u)),
                        latest_state=logic.StateSample(0, np.array(state)), now_ns=0,
                        max_state_age_s=1.0)


def test_filter_info_stays_bounded_with_100000_points():
    """100,000 points in the filter: filter_info holds the first five sections at their
    fixed indexes and at most BINDING_POINTS rows of points, all finite, in both ways the
    edge writes it (the one-step layout and the sections)."""
    config = filter_config_from_params(_BASE)
    safety_filter = SafetyFilter(config.problem, footprint=config.footprint)
    rng = np.random.default_rng(3)
    angle = rng.uniform(-math.pi, math.pi, 100_000)
    distance = rng.uniform(0.7, 8.0, 100_000)
    safety_filter.set_points(np.stack([distance * np.cos(angle),
                                       distance * np.sin(angle)], axis=1))
    edge = FilterEdge(state_type='array', command_type='array', system='unicycle', n_x=3,
                      n_u=2)
    for u in ([2.5, 0.0], [0.0, 0.0]):  # corrected, then passed through
        decision = _decision(safety_filter, [0.0, 0.0, 0.0], u)
        assert not decision.fail_safe and len(decision.result.points.values) == 100_000
        data = edge.info_cdr(decision)
        sections = _sections(data)
        n_barriers = len(safety_filter.barrier_names)
        bound = 3 * 2 + 2 + 2 * n_barriers + 3 + 3 + 4 * BINDING_POINTS
        values = np.concatenate(list(sections.values()))
        assert values.size <= bound and np.isfinite(values).all()
        assert len(data) < 4096
        assert list(sections)[:5] == ['u', 'u_rl', 'u_s', 'fail_safe', 'status']
        assert sections['binding_points'].size == 4 * BINDING_POINTS
        expected = filter_info.info_sections(
            u=decision.u_safe, u_rl=decision.u_rl, fail_safe=False, status='solved',
            result=decision.result, state=decision.state)
        assert {k: v.tolist() for k, v in sections.items()} == {
            k: v.tolist() for k, v in expected.items()}


def test_without_points_there_is_no_section():
    """A filter without a footprint, or with a footprint and no points: no binding_points."""
    config = filter_config_from_params(_BASE)
    edge = FilterEdge(state_type='array', command_type='array', system='unicycle', n_x=3,
                      n_u=2)
    for safety_filter in (SafetyFilter(config.problem),
                          SafetyFilter(config.problem, footprint=config.footprint)):
        decision = _decision(safety_filter, [0.0, 0.0, 0.0], [1.0, 0.0])
        assert 'binding_points' not in _sections(edge.info_cdr(decision))

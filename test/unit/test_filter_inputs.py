"""The safety filter's one-pass input and QP data checks, and how it treats the caller's arrays.

The fused checks only decide whether the field-by-field checks must run: an input or QP data
that fails them for a harmless reason (a sum of large finite values that overflows) must still
be filtered, and the refusals must name the field whichever check sees the input first.
"""
from __future__ import annotations

import warnings

from filter_paths import osqp_only
import numpy as np
import pytest

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import InputBounds, QP_DATA_LIMIT, SafetyFilter
from rcbf_ros.parameters.rules import find_config, load_params

STATE, PROPOSAL = [-0.85, 0.0, 0.0], [2.5, 0.0]
"""A unicycle state whose rows bind at full speed (the filter brakes)."""


def unicycle_problem():
    return filter_config_from_params(load_params(find_config('unicycle'), 'safety_filter')).problem


def read_only(values) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    array.setflags(write=False)
    return array


def test_inputs_whose_sum_overflows_are_filtered_not_refused():
    # Each value lies within the (wide) bounds; only their sum overflows. The heading enters
    # the rows through sin and cos only, and the proposal is clipped to the limits.
    problem = unicycle_problem()
    bounds = InputBounds(state=1.7e308, command=1.7e308)
    state = [-0.85, 0.0, 1.5e308]
    result = SafetyFilter(problem, input_bounds=bounds).filter(state, [1.5e308, 0.0])
    assert result.status == 'solved' and result.proposal_clipped, result.reason
    at_limit = SafetyFilter(problem, input_bounds=bounds).filter(state, [2.5, 0.0])
    assert not at_limit.proposal_clipped
    np.testing.assert_allclose(result.u_safe, at_limit.u_safe, rtol=0, atol=1e-9)


@pytest.mark.parametrize('field, index, value, reason', [
    ('state', 1, np.nan, 'state: contains NaN or inf'),
    ('state', 0, -np.inf, 'state: contains NaN or inf'),
    ('u_rl', 1, np.nan, 'u_rl: contains NaN or inf'),
    ('u_rl', 0, 2e6, 'u_rl: |value| 2e+06 beyond the bound 1e+06'),
    ('mean', 2, np.inf, 'disturbance_mean: contains NaN or inf'),
    ('std', 0, -1e-300, 'disturbance_std: must be >= 0'),
    ('std', 2, np.nan, 'disturbance_std: contains NaN or inf'),
    ('std', 1, 2e6, 'disturbance_std: |value| 2e+06 beyond the bound 1e+06'),
])
def test_each_bad_value_is_refused_naming_its_field(field, index, value, reason):
    safety_filter = SafetyFilter(unicycle_problem())
    args = {'state': list(STATE), 'u_rl': list(PROPOSAL), 'mean': [0.0] * 3, 'std': [0.0] * 3}
    args[field][index] = value
    result = safety_filter.filter(args['state'], args['u_rl'], args['mean'], args['std'])
    assert result.fail_safe and result.status == 'input_refused'
    assert result.reason == reason


def test_qp_data_just_beyond_the_limit_is_refused():
    problem = unicycle_problem()
    bounds = InputBounds(state=1e300, disturbance=1e300)
    safety_filter = SafetyFilter(problem, input_bounds=bounds)
    # std on x: the margin -k_c |d h / d x| std grows linearly in std
    small = safety_filter.filter(STATE, PROPOSAL, std=[1.0, 0.0, 0.0])
    assert small.status != 'input_refused', small.reason
    refused = safety_filter.filter(STATE, PROPOSAL, std=[1e3 * QP_DATA_LIMIT, 0.0, 0.0])
    assert refused.status == 'input_refused'
    assert refused.reason.startswith('constraint bounds: not finite or beyond 1e+15')


def test_read_only_inputs_are_filtered_and_left_unchanged():
    problem = unicycle_problem()
    reference = SafetyFilter(problem).filter(STATE, PROPOSAL)
    inputs = [read_only(STATE), read_only([9.0, 0.0]), read_only([0.0] * 3),
              read_only([0.0] * 3)]
    copies = [a.copy() for a in inputs]
    for fallback_only in (False, True):
        # max_iter=1: OSQP stops early and the interior-point fallback takes the inputs
        safety_filter = SafetyFilter(problem, max_iter=1 if fallback_only else 4000)
        if fallback_only:
            osqp_only(safety_filter)
        with warnings.catch_warnings():
            warnings.simplefilter('error')
            result = safety_filter.filter(*inputs)
        assert not result.fail_safe and result.proposal_clipped
        assert result.status == ('solved_interior_point' if fallback_only else 'solved')
        np.testing.assert_allclose(result.u_safe, reference.u_safe, atol=1e-6)
        np.testing.assert_allclose(result.u_s, result.u_safe - inputs[1], rtol=0, atol=0)
    for array, copy in zip(inputs, copies):
        np.testing.assert_array_equal(array, copy)


@pytest.mark.parametrize('closed_form', [True, False])
def test_defaults_and_read_only_inputs_give_no_warning_on_either_assembly(closed_form):
    problem = unicycle_problem()
    safety_filter = SafetyFilter(problem, closed_form=closed_form)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        plain = safety_filter.filter(read_only(STATE), read_only(PROPOSAL))
        boxed = safety_filter.filter(STATE, PROPOSAL, read_only([0.0] * 3), read_only([0.0] * 3))
    assert plain.status == boxed.status == 'solved'
    np.testing.assert_allclose(plain.u_safe, boxed.u_safe, rtol=0, atol=1e-9)


def test_qp_data_beyond_the_limit_is_refused_without_warning():
    # Each square is finite (about 1.4e308), their sum overflows.
    safety_filter = SafetyFilter(unicycle_problem())
    assemble = safety_filter._assemble

    def huge(x, u, mean, std):
        h_values, rows, upper, _ = assemble(x, u, mean, std)
        h_values, upper = [0.0] * len(h_values), [0.0] * len(upper)
        h_values[0] = upper[0] = 1.2e154
        return h_values, rows, upper, 2.0 * 1.2e154 ** 2

    safety_filter._assemble = huge
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        result = safety_filter.filter(STATE, PROPOSAL)
    assert result.fail_safe and result.status == 'input_refused'
    assert result.reason == 'barrier values: not finite or beyond 1e+15 at this input'


def test_qp_data_beyond_the_limit_only_in_sum_is_filtered_not_refused():
    # Each value lies within the limit, their sum of magnitudes beyond it: the one-sum check
    # fails, the value-by-value check passes.
    safety_filter = SafetyFilter(unicycle_problem())
    assemble = safety_filter._assemble

    def large(x, u, mean, std):
        h_values, rows, upper, _ = assemble(x, u, mean, std)
        h_values, upper = [0.6 * QP_DATA_LIMIT] * len(h_values), [QP_DATA_LIMIT] * len(upper)
        return h_values, rows, upper, sum(v * v for v in h_values + upper)

    safety_filter._assemble = large
    result = safety_filter.filter(STATE, PROPOSAL)
    assert result.status == 'solved' and not result.fail_safe, result.reason
    np.testing.assert_array_equal(result.h, 0.6 * QP_DATA_LIMIT)

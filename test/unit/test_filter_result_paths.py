"""The per-call shortcuts of SafetyFilter.filter give what the general path gives.

- A pass-through (every RCBF row holds at z = 0, no solve) returns what the row check at z = 0
  returns: the clipped proposal, the rows' right-hand sides as their values, no slack.
- Every result, whichever path built it, carries every field of FilterResult, as its
  constructor sets them.
"""
from __future__ import annotations

import dataclasses

from filter_paths import qp_arrays, random_call, shipped_filter
import numpy as np
import pytest

from rcbf_ros.core.filter import FilterResult

SYSTEMS = ('unicycle', 'car_following', 'pvtol')
FIELDS = {f.name for f in dataclasses.fields(FilterResult)}


@pytest.mark.parametrize('system', SYSTEMS)
def test_a_pass_through_answers_as_the_row_check_at_zero(system):
    rng = np.random.default_rng(11)
    safety_filter = shipped_filter(system)
    n_u, k = safety_filter.n_u, safety_filter.n_barriers
    low, high = safety_filter._u_min, safety_filter._u_max
    seen = {'clipped': 0, 'as proposed': 0}
    for _ in range(400):
        x, u, mean, std = random_call(system, rng)
        applied = np.clip(u, low, high)
        _, g_matrix, upper = qp_arrays(safety_filter, x, applied, mean, std)
        if upper.min() < 0.0:
            continue  # the solver's path
        result = safety_filter.filter(x, u, mean, std)
        want = safety_filter._check(np.zeros(n_u + 1),
                                    (upper[:k].tolist(), g_matrix[:k].tolist(), applied.tolist()))
        assert want is not None
        u_safe, values, needed = (np.array(v) for v in want)
        assert result.status == 'solved' and not result.fail_safe and result.reason == ''
        np.testing.assert_array_equal(result.u_safe, u_safe)
        np.testing.assert_array_equal(result.u_s, u_safe - u)
        np.testing.assert_array_equal(result.constraint_values, values)
        assert result.needed_slack == needed == 0.0 and result.slack == 0.0
        assert result.proposal_clipped == bool(np.any(applied != u))
        seen['clipped' if result.proposal_clipped else 'as proposed'] += 1
    if not safety_filter.problem.has_limits:  # nothing to clip (the cars' input)
        del seen['clipped']
    assert min(seen.values()) >= 10, seen


@pytest.mark.parametrize('system', SYSTEMS)
def test_every_result_carries_every_field(system):
    rng = np.random.default_rng(12)
    safety_filter = shipped_filter(system)
    seen = set()
    calls = [random_call(system, rng) for _ in range(60)]
    x, u, mean, std = calls[0]
    calls.append((x, u, mean, -std))  # refused: fail-safe
    for x, u, mean, std in calls:
        result = safety_filter.filter(x, u, mean, std)
        assert set(vars(result)) == FIELDS
        rebuilt = FilterResult(**vars(result))
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(rebuilt, name), getattr(result, name))
        with pytest.raises(dataclasses.FrozenInstanceError):
            result.status = 'changed'
        seen.add('fail-safe' if result.fail_safe
                 else 'pass-through' if result.slack == 0.0 and not result.active else 'solved')
    assert seen == {'fail-safe', 'pass-through', 'solved'}

"""Decision logic of the safety_filter node (rcbf_ros.node_logic.safety_filter), without
any middleware.

A real SafetyFilter (real OSQP) built from config/unicycle.yaml stands behind every decision.
"""
from __future__ import annotations

import math

from filter_paths import osqp_only
import numpy as np
import pytest

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import STATUS_CODES
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as fl
from rcbf_ros.parameters.rules import find_config, load_params

SECOND = 1_000_000_000


@pytest.fixture(scope='module')
def unicycle_params() -> dict:
    return load_params(find_config('unicycle'), 'safety_filter')


@pytest.fixture(scope='module')
def config(unicycle_params):
    return filter_config_from_params(unicycle_params)


@pytest.fixture
def safety_filter(config) -> SafetyFilter:
    return SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action)


FREE_STATE = np.array([-2.5, -2.5, -0.75 * np.pi])  # in a corner, heading away from obstacles
FACING_OBSTACLE = np.array([-0.85, 0.0, 0.0])       # 0.25 m from the centre obstacle, facing it


def fresh(state: np.ndarray, now_ns: int = 10 * SECOND) -> fl.StateSample:
    return fl.StateSample(received_ns=now_ns, state=state)


# --- parameters --------------------------------------------------------------------------------

def test_declarations_cover_config_keys_and_open_families_from_overrides():
    names = dict(fl.parameter_declarations(['bands.operator.index', 'system_params.with_operator',
                                            'alpha', 'unrelated.key']))
    for key in fl.FILTER_PARAMETER_KEYS + tuple(fl.NODE_PARAMETER_DEFAULTS):
        assert key in names
    assert 'bands.operator.index' in names and 'system_params.with_operator' in names
    assert 'unrelated.key' not in names
    assert names['alpha'] is None and names['qos.depth'] == 10


def test_collect_parameters_drops_unset_so_config_defaults_apply(unicycle_params):
    declared = {key: None for key, _ in fl.parameter_declarations()}
    declared.update(unicycle_params)
    declared['obstacles.radius'] = tuple(declared['obstacles.radius'])
    flat = fl.collect_parameters(declared)
    assert 'input_limits.min' in flat and 'gaps.a' not in flat
    assert flat['obstacles.radius'] == [0.6] * 5
    # Dropping unset keys matters: an explicit input_limits.min of None would mean 'unbounded'.
    problem = filter_config_from_params(flat).problem
    assert problem.has_limits and problem.n_barriers == 5


@pytest.mark.parametrize('key, value', [
    ('command_type', 'pose'),
    ('twist_fields', ['linear.x', 'angular.w']),
    ('twist_fields', ['linear.x', 'linear.x']),
    ('twist_fields', 'linear.x'),
    ('max_state_age_s', 0.0),
    ('max_state_age_s', float('nan')),
    ('max_state_age_s', 'soon'),
    ('qos.reliable', 'yes'),
    ('qos.depth', 0),
    ('qos.depth', 2.5),
    ('osqp.max_iter', True),
    ('osqp.eps_abs', -1.0),
    ('diagnostics.name', 3),
    ('diagnostics.min_period_s', -0.1),
])
def test_bad_node_parameter_names_the_key(key, value):
    with pytest.raises(ValueError, match=f'^{key}:'):
        fl.node_settings_from_params({key: value})


def test_node_settings_defaults_and_values():
    settings = fl.node_settings_from_params({'command_type': 'twist', 'qos.depth': 1,
                                             'twist_fields': ['linear.x', 'angular.z']})
    assert settings.command_type == 'twist' and settings.qos_depth == 1
    assert settings.twist_fields == ('linear.x', 'angular.z')
    assert settings.max_state_age_s == fl.NODE_PARAMETER_DEFAULTS['max_state_age_s']


@pytest.mark.parametrize('key, value', [
    ('alpha', -1.0), ('k_c', 'big'), ('obstacles.y', [0.0]), ('system', 'submarine'),
    ('input_limits.max', [1.0]), ('fail_safe_action', [0.0, 0.0, 0.0]),
])
def test_bad_filter_parameter_names_the_key(unicycle_params, key, value):
    params = fl.collect_parameters({**unicycle_params, key: value})
    with pytest.raises(ValueError, match=key.split('.')[0]):
        filter_config_from_params(params)


# --- message sections ---------------------------------------------------------------------------

def test_state_prefers_state_section_else_first():
    x = np.array([1.0, 2.0, 3.0])
    assert np.array_equal(fl.state_from_sections(sections={'h_true': np.ones(5), 'state': x},
                                                 n_x=3), x)
    assert np.array_equal(fl.state_from_sections(sections={'data': x}, n_x=3), x)


@pytest.mark.parametrize('sections, match', [
    ({}, 'state: empty'),
    ({'state': np.ones(2)}, 'state: expected 3'),
    ({'state': np.array([0.0, np.nan, 0.0])}, 'state: contains NaN'),
])
def test_bad_state_is_rejected_naming_state(sections, match):
    with pytest.raises(ValueError, match=match):
        fl.state_from_sections(sections=sections, n_x=3)


def test_proposal_sections_parsed():
    proposal = fl.proposal_from_sections(
        sections={'u': [1.0, 0.5], 'disturbance_mean': [0.1, 0.0, 0.0],
                  'disturbance_std': [0.0, 0.2, 0.0], 'state': [0.0, 1.0, 2.0]}, n_u=2, n_x=3)
    assert np.array_equal(proposal.u, [1.0, 0.5])
    assert np.array_equal(proposal.state, [0.0, 1.0, 2.0])
    assert np.array_equal(proposal.disturbance_std, [0.0, 0.2, 0.0])


@pytest.mark.parametrize('sections, field', [
    ({'u': [np.nan, 0.0]}, 'u'),
    ({'u': [1.0]}, 'u'),
    ({'disturbance_mean': [0.0] * 3}, 'u'),
    ({'u': [0.0, 0.0], 'state': [0.0, np.inf, 0.0]}, 'state'),
    ({'u': [0.0, 0.0], 'disturbance_std': [0.0, -1.0, 0.0]}, 'disturbance_std'),
    ({'u': [0.0, 0.0], 'disturbance_mean': [0.0]}, 'disturbance_mean'),
    ({'u': [0.0, 0.0], 'gain': [1.0]}, 'gain'),
])
def test_bad_proposal_names_the_section(sections, field):
    with pytest.raises(ValueError, match=f'^{field}:'):
        fl.proposal_from_sections(sections=sections, n_u=2, n_x=3)


# --- decisions ---------------------------------------------------------------------------------

def test_pass_through_far_from_obstacles(safety_filter):
    u = np.array([1.0, 0.3])
    decision = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=u),
                         latest_state=fresh(FREE_STATE), now_ns=10 * SECOND,
                         max_state_age_s=0.5)
    assert decision.level == fl.OK and not decision.fail_safe
    assert np.array_equal(decision.u_safe, u) and decision.state_source == 'topic'
    level, message, values = fl.diagnostic_values(decision=decision,
                                                  barrier_names=safety_filter.barrier_names)
    assert (level, message) == (fl.OK, 'pass-through') and values['active'] is False


def test_unsafe_proposal_is_corrected_with_ok(safety_filter):
    u = np.array([2.5, 0.0])  # full speed into the centre obstacle
    decision = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=u),
                         latest_state=fresh(FACING_OBSTACLE), now_ns=10 * SECOND,
                         max_state_age_s=0.5)
    assert decision.level == fl.OK and decision.u_safe[0] < u[0]
    level, message, values = fl.diagnostic_values(decision=decision,
                                                  barrier_names=safety_filter.barrier_names)
    assert message == 'filtering' and values['active'] is True
    # Every barrier by name, with the filter's own values.
    for name, h, c in zip(safety_filter.barrier_names, decision.result.h,
                          decision.result.constraint_values):
        assert values[f'h.{name}'] == pytest.approx(h)
        assert values[f'constraint.{name}'] == pytest.approx(c)
        assert c >= -1e-5  # -eps: the soft slack of an active row
    assert values['min_h'] == pytest.approx(min(decision.result.h))
    assert values['status'] == 'solved' and values['fail_safe'] is False
    assert values['solve_time_s'] > 0 and values['total_time_s'] >= values['solve_time_s']


def test_proposal_state_wins_over_topic_state(safety_filter):
    u = np.array([2.5, 0.0])
    # The topic says "free space", the proposal says "facing the obstacle": the proposal's wins.
    decision = fl.decide(safety_filter=safety_filter,
                         proposal=fl.Proposal(u=u, state=FACING_OBSTACLE),
                         latest_state=fresh(FREE_STATE), now_ns=10 * SECOND,
                         max_state_age_s=0.5)
    assert decision.state_source == 'proposal' and decision.u_safe[0] < u[0]
    # ...and needs no topic state at all (no staleness check either).
    slow = np.array([1.0, 0.3])
    alone = fl.decide(safety_filter=safety_filter,
                      proposal=fl.Proposal(u=slow, state=FREE_STATE),
                      latest_state=None, now_ns=10 * SECOND, max_state_age_s=0.5)
    assert alone.level == fl.OK and np.array_equal(alone.u_safe, slow)


def test_learned_disturbance_wins_over_static_box(safety_filter):
    u = np.array([1.0, 0.0])
    state = np.array([-1.2, 0.0, 0.0])
    static = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=u),
                       latest_state=fresh(state), now_ns=10 * SECOND, max_state_age_s=0.5,
                       static_mean=[0.0, 0.0, 0.0], static_std=[0.0, 0.0, 0.0])
    learned = fl.decide(safety_filter=safety_filter,
                        proposal=fl.Proposal(u=u, disturbance_mean=np.array([0.5, 0.0, 0.0]),
                                             disturbance_std=np.array([0.3, 0.3, 0.0])),
                        latest_state=fresh(state), now_ns=10 * SECOND, max_state_age_s=0.5,
                        static_mean=[0.0, 0.0, 0.0], static_std=[0.0, 0.0, 0.0])
    expected = safety_filter.filter(state, u, [0.5, 0.0, 0.0], [0.3, 0.3, 0.0])
    assert np.allclose(learned.u_safe, expected.u_safe, atol=1e-9)
    assert not np.allclose(learned.u_safe, static.u_safe, atol=1e-3)
    # Static box alone is used when the proposal carries none.
    static_box = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=u),
                           latest_state=fresh(state), now_ns=10 * SECOND, max_state_age_s=0.5,
                           static_mean=[0.5, 0.0, 0.0], static_std=[0.3, 0.3, 0.0])
    assert np.allclose(static_box.u_safe, expected.u_safe, atol=1e-9)


@pytest.mark.parametrize('latest, now_ns, reason', [
    (None, 10 * SECOND, 'no state received yet'),
    (fl.StateSample(received_ns=10 * SECOND, state=None, error='state: contains NaN or inf'),
     10 * SECOND, 'bad state: state: contains NaN'),
    (fresh(FREE_STATE, now_ns=10 * SECOND), 10 * SECOND + SECOND // 2 + 1, 'stale state'),
])
def test_missing_bad_or_stale_state_gives_fail_safe(safety_filter, latest, now_ns, reason):
    u = np.array([2.5, 1.0])
    decision = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=u),
                         latest_state=latest, now_ns=now_ns, max_state_age_s=0.5)
    assert decision.fail_safe and decision.level == fl.ERROR
    assert np.array_equal(decision.u_safe, safety_filter.fail_safe_action)
    assert decision.reason.startswith(reason)
    assert np.array_equal(decision.u_rl, u)
    level, message, values = fl.diagnostic_values(decision=decision,
                                                  barrier_names=safety_filter.barrier_names)
    assert level == fl.ERROR and message == decision.reason
    assert values['status'] == 'not solved' and values['fail_safe'] is True
    assert all(values[f'h.{n}'] == '' for n in safety_filter.barrier_names)  # not evaluated


def test_state_exactly_at_max_age_is_still_used(safety_filter):
    decision = fl.decide(safety_filter=safety_filter, proposal=fl.Proposal(u=np.ones(2)),
                         latest_state=fresh(FREE_STATE, now_ns=0), now_ns=SECOND // 2,
                         max_state_age_s=0.5)
    assert decision.level == fl.OK


def test_rejected_proposal_gives_fail_safe_without_a_proposal(safety_filter):
    decision = fl.decide(safety_filter=safety_filter, proposal=None,
                         proposal_error='u: contains NaN or inf',
                         latest_state=fresh(FREE_STATE), now_ns=10 * SECOND,
                         max_state_age_s=0.5)
    assert decision.fail_safe and decision.level == fl.ERROR
    assert decision.reason == 'bad proposal: u: contains NaN or inf'
    assert decision.u_rl is None and np.array_equal(decision.u_s, [0.0, 0.0])
    assert np.array_equal(decision.u_safe, safety_filter.fail_safe_action)


def test_failed_solve_gives_fail_safe_with_status(config):
    starved = osqp_only(SafetyFilter(config.problem, fail_safe_action=[0.1, -0.2], max_iter=1,
                                     fallback=False))
    decision = fl.decide(safety_filter=starved, proposal=fl.Proposal(u=np.array([2.5, 0.0])),
                         latest_state=fresh(FACING_OBSTACLE), now_ns=10 * SECOND,
                         max_state_age_s=0.5)
    assert decision.fail_safe and decision.level == fl.ERROR
    assert np.array_equal(decision.u_safe, [0.1, -0.2])
    assert decision.reason.startswith('unverified: ') and 'iterations' in decision.reason
    _, _, values = fl.diagnostic_values(decision=decision, barrier_names=starved.barrier_names)
    assert values['status'] == decision.result.status and values['fail_safe'] is True


@pytest.mark.parametrize('filter_tolerance', [None, 1e-4])
def test_infeasible_rows_give_the_fail_safe(config, filter_tolerance):
    # Deep inside the centre obstacle: the row asks for v <= -2.7 but the limit is -2.5, so the
    # QP needs real slack (an active feasible row only needs eps ~ 1e-6, the price of the soft
    # penalty l eps^2 with l = 1e6). The rows are checked whether or not the filter itself
    # was built with the tolerance.
    filt = SafetyFilter(config.problem, fail_safe_action=[0.0, 0.3],
                        slack_tolerance=filter_tolerance)
    state = np.array([-0.2, 0.0, 0.0])
    decision = fl.decide(safety_filter=filt, proposal=fl.Proposal(u=np.array([2.5, 0.0])),
                         latest_state=fresh(state), now_ns=10 * SECOND, max_state_age_s=0.5)
    assert decision.result.needed_slack > 1e-2
    assert decision.level == fl.ERROR and decision.fail_safe
    assert decision.reason.startswith('slack_exceeded: ')
    np.testing.assert_array_equal(decision.u_safe, [0.0, 0.3])


def test_diagnostics_due():
    due = fl.diagnostics_due
    assert due(level=fl.OK, now_ns=5, last_ok_ns=4, min_period_s=0.0)
    assert due(level=fl.OK, now_ns=5, last_ok_ns=None, min_period_s=1.0)
    assert not due(level=fl.OK, now_ns=SECOND - 1, last_ok_ns=0, min_period_s=1.0)
    assert due(level=fl.OK, now_ns=SECOND, last_ok_ns=0, min_period_s=1.0)
    assert due(level=fl.WARN, now_ns=1, last_ok_ns=0, min_period_s=1.0)
    assert due(level=fl.ERROR, now_ns=1, last_ok_ns=0, min_period_s=1.0)


def test_log_throttle():
    throttle = fl.LogThrottle(1.0)
    assert throttle.should_log(key='stale state', now_ns=0)
    assert not throttle.should_log(key='stale state', now_ns=SECOND // 2)
    assert throttle.should_log(key='bad proposal', now_ns=SECOND // 2)
    assert throttle.should_log(key='stale state', now_ns=SECOND)
    assert throttle.pop_suppressed('stale state') == 1
    assert fl.reason_key('bad proposal: u: contains NaN') == 'bad proposal'


# --- filter_info and the fail-safe without NaN ----------------------------------------------

def _failure_decisions(config) -> dict[str, fl.Decision]:
    """One decision per way the node can end up publishing the fail-safe."""
    fail_safe = [0.1, -0.2]
    filt = SafetyFilter(config.problem, fail_safe_action=fail_safe)
    starved = osqp_only(SafetyFilter(config.problem, fail_safe_action=fail_safe, max_iter=1,
                                     fallback=False))
    u = np.array([2.5, 0.0])

    def decide(proposal, latest, *, safety_filter=filt, now_ns=10 * SECOND, error=''):
        return fl.decide(safety_filter=safety_filter, proposal=proposal, proposal_error=error,
                         latest_state=latest, now_ns=now_ns, max_state_age_s=0.5)
    return {
        'bad proposal': decide(None, fresh(FACING_OBSTACLE), error='u: expected 2 values, got 3'),
        'undecodable proposal': fl.fail_safe_decision(safety_filter=filt,
                                                      reason='undecodable proposal: x'),
        'internal error': fl.fail_safe_decision(safety_filter=filt,
                                                reason='internal error: RuntimeError: x'),
        'no state received yet': decide(fl.Proposal(u=u), None),
        'bad state': decide(fl.Proposal(u=u), fl.StateSample(10 * SECOND, None, 'state: NaN')),
        'stale state': decide(fl.Proposal(u=u), fresh(FREE_STATE, now_ns=0)),
        'input_refused': decide(fl.Proposal(u=np.array([1e7, 0.0])), fresh(FREE_STATE)),
        'unverified': decide(fl.Proposal(u=u), fresh(FACING_OBSTACLE), safety_filter=starved),
        'slack_exceeded': decide(fl.Proposal(u=u), fresh(np.array([-0.2, 0.0, 0.0]))),
    }


def test_the_fail_safe_carries_no_nan_for_any_failure_class(config):
    decisions = _failure_decisions(config)
    barrier_names = config.problem.barrier_names
    for reason, decision in decisions.items():
        assert decision.fail_safe and decision.reason.startswith(reason), (reason, decision)
        info = fl.info_sections(decision)
        assert list(info)[:5] == ['u', 'u_rl', 'u_s', 'fail_safe', 'status'], reason
        for label, values in info.items():
            assert np.all(np.isfinite(values)), (reason, label, values)
        np.testing.assert_array_equal(info['u'], [0.1, -0.2])
        np.testing.assert_array_equal(info['u_s'], info['u'] - info['u_rl'])
        assert info['fail_safe'][0] == 1.0
        assert info['status'][0] == STATUS_CODES[reason], reason
        _, _, values = fl.diagnostic_values(decision=decision, barrier_names=barrier_names)
        for key, value in values.items():
            assert not (isinstance(value, float) and math.isnan(value)), (reason, key)
            if key != 'reason':  # the reason may name NaN in words ("contains NaN or inf")
                assert 'nan' not in str(value).lower(), (reason, key, value)


def test_filter_info_of_a_filtered_command(safety_filter):
    u = np.array([2.5, 0.0])
    decision = fl.decide(safety_filter=safety_filter,
                         proposal=fl.Proposal(u=u, state=FACING_OBSTACLE),
                         latest_state=None, now_ns=10 * SECOND, max_state_age_s=0.5)
    info = fl.info_sections(decision)
    assert list(info) == ['u', 'u_rl', 'u_s', 'fail_safe', 'status', 'h', 'constraint', 'slack',
                          'needed_slack', 'solve_time_s', 'state']
    np.testing.assert_array_equal(info['u'], decision.u_safe)
    np.testing.assert_array_equal(info['u_rl'], u)
    np.testing.assert_array_equal(info['u_s'], decision.u_safe - u)
    np.testing.assert_array_equal(info['h'], decision.result.h)
    np.testing.assert_array_equal(info['state'], FACING_OBSTACLE)
    assert info['status'][0] == STATUS_CODES['solved'] and info['fail_safe'][0] == 0.0


def test_the_unicycle_filter_box_is_the_simulated_slope(unicycle_params):
    """config/unicycle.yaml's /safety_filter box, mean +/- k_c std, is the smallest box holding
    the slope the simulator applies, g(x) u_d(x), at every heading."""
    import torch

    from rcbf_ros.core.dynamics import Unicycle
    from rcbf_ros.envs.unicycle import unicycle_slope_disturbance
    config = filter_config_from_params(unicycle_params)
    k_c = config.problem.k_c
    low = np.array(config.static_mean) - k_c * np.array(config.static_std)
    high = np.array(config.static_mean) + k_c * np.array(config.static_std)
    headings = np.linspace(-np.pi, np.pi, 3601)
    states = np.stack([np.zeros_like(headings), np.zeros_like(headings), headings], axis=1)
    g = Unicycle().g(torch.from_numpy(states)).numpy()                       # (N, 3, 2)
    slope = np.stack([unicycle_slope_disturbance(x) for x in states])         # (N, 2)
    moved = np.einsum('nij,nj->ni', g, slope)                                 # (N, 3)
    assert np.all(moved >= low - 1e-12) and np.all(moved <= high + 1e-12)
    np.testing.assert_allclose(moved.min(axis=0), low, atol=1e-6)   # tight: every face reached
    np.testing.assert_allclose(moved.max(axis=0), high, atol=1e-6)


def test_obstacle_rows_become_the_obstacles_parameters():
    from rcbf_ros.node_logic.safety_filter import obstacle_parameters
    assert obstacle_parameters(data=[1.0, 2.0, 0.5, 3.0, 4.0, 0.25]) == {
        'obstacles.x': [1.0, 3.0], 'obstacles.y': [2.0, 4.0], 'obstacles.radius': [0.5, 0.25]}
    assert obstacle_parameters(data=[1, 2, 3], dims=[('o', 1, 3), ('xyr', 3, 3)]) == {
        'obstacles.x': [1.0], 'obstacles.y': [2.0], 'obstacles.radius': [3.0]}
    assert obstacle_parameters(data=[]) == {
        'obstacles.x': [], 'obstacles.y': [], 'obstacles.radius': []}
    for kwargs, field in (({'data': [1.0, 2.0]}, 'data'),
                          ({'data': [1.0, 2.0, 3.0], 'dims': [('a', 3, 3)]}, 'layout.dim'),
                          ({'data': [1.0, 2.0, 3.0], 'dims': [('a', 1, 3), ('b', 2, 2)]},
                           'layout.dim'),
                          ({'data': [1.0, 2.0, 3.0], 'data_offset': 1}, 'layout.data_offset')):
        with pytest.raises(ValueError, match=f'^obstacles: {field}'):
            obstacle_parameters(**kwargs)


def test_read_only_and_filter_parameters():
    from rcbf_ros.node_logic.safety_filter import (
        feeds_the_filter,
        is_read_only,
        PARAMETERS,
        READ_ONLY_PARAMETERS,
    )
    assert is_read_only('system') and is_read_only('system_params.with_operator')
    assert not is_read_only('k_c') and not is_read_only('obstacles.x')
    for spec in PARAMETERS:  # --help and the README say which ones are read-only
        assert spec.description.endswith('read-only') == is_read_only(
            spec.name.replace('<name>', 'any')), spec.name
    assert set(READ_ONLY_PARAMETERS) <= {spec.name for spec in PARAMETERS}
    assert feeds_the_filter('k_c') and feeds_the_filter('bands.tilt.index')
    assert not feeds_the_filter('use_sim_time') and not feeds_the_filter('frame_id')
    # an observation source's keys: fixed at start (the subscriptions are made once)
    for key in ('front.type', 'front.topic', 'front.timeout_s', 'cloud.min_height',
                'cloud.max_height', 'cloud.voxel_size', 'front.best_effort'):
        assert is_read_only(key) and feeds_the_filter(key), key
    for key in ('obstacles.margin', 'footprint.radius', 'osqp.max_iter', 'front.radius'):
        assert not is_read_only(key), key


def test_describe_changes_lists_each_changed_key():
    from rcbf_ros.node_logic.safety_filter import describe_changes, merged_parameters
    old = {'k_c': 2.0, 'alpha': 1.0, 'obstacles.x': [0.0]}
    new = merged_parameters(current=old, changes={'k_c': 0.5, 'obstacles.x': None, 'q': 1})
    assert new == {'k_c': 0.5, 'alpha': 1.0, 'q': 1}
    assert describe_changes(old=old, new=new) == (
        'k_c: 2.0 -> 0.5; obstacles.x: [0.0] -> not set; q: not set -> 1')
    assert describe_changes(old=old, new=old) == ''
    assert describe_changes(old={'x': list(range(100))}, new={}, width=20) == (
        'x: [0, 1, 2, 3, 4, 5... -> not set')


def test_checked_vector_refuses_exactly_the_vectors_with_a_nan_or_inf():
    """Short vectors (checked one value at a time) and long ones (by numpy) alike: a copy of
    every finite vector of the right size, the same words for the others."""
    rng = np.random.default_rng(4)
    for size in (1, 2, 3, filter_edge._FEW_VALUES, filter_edge._FEW_VALUES + 1, 100):
        values = rng.normal(size=size) * 10.0 ** rng.integers(-300, 300, size)
        checked = fl.checked_vector('u', tuple(values), size)
        assert checked.dtype == np.float64 and checked.flags.writeable
        assert checked.tobytes() == values.tobytes()
        for bad in (np.nan, np.inf, -np.inf):
            for index in {0, size // 2, size - 1}:
                broken = values.copy()
                broken[index] = bad
                with pytest.raises(ValueError, match='^u: contains NaN or inf$'):
                    fl.checked_vector('u', broken, size)
        with pytest.raises(ValueError, match=f'^u: expected {size} values, got {size + 1}$'):
            fl.checked_vector('u', np.zeros(size + 1), size)


def test_the_static_disturbance_box_is_the_configs_read_only():
    config = filter_config_from_params(load_params(find_config('unicycle'), 'safety_filter'))
    params = load_params(find_config('unicycle'), 'safety_filter')
    active = fl.build_active_filter(params=params)
    for name in ('static_mean', 'static_std'):
        array = getattr(active, name)
        assert array.tolist() == list(getattr(config, name)) and array.dtype == np.float64
        assert not array.flags.writeable

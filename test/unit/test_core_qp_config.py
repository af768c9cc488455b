"""The QP builder, systems and configuration parsing."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.config import filter_config_from_params, flatten
from rcbf_ros.core.dynamics import CarFollowing, load_system, PVTOL, step_euler, Unicycle
from rcbf_ros.core.qp import build_rcbf_qp
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.parameters.rules import find_config, load_params


def test_qp_rows_encode_the_rcbf_inequality():
    """For any z, G z <= h  <=>  the paper's RCBF row and the actuator limits hold."""
    gen = torch.Generator().manual_seed(0)
    b, k, m = 4, 3, 2
    h = torch.randn(b, k, generator=gen, dtype=torch.float64)
    lf = torch.randn(b, k, generator=gen, dtype=torch.float64)
    lg = torch.randn(b, k, m, generator=gen, dtype=torch.float64)
    rho = torch.randn(b, k, generator=gen, dtype=torch.float64)
    u_rl = torch.randn(b, m, generator=gen, dtype=torch.float64)
    alpha, lo, hi = 1.5, (-1.0, -2.0), (1.0, 2.0)
    qp = build_rcbf_qp(h=h, lf_h=lf, lg_h=lg, rho=rho, u_rl=u_rl, alpha=alpha,
                       slack_weight=1e3, u_min=lo, u_max=hi)
    assert qp.G.shape == (b, k + 2 * m, m + 1) and qp.h.shape == (b, k + 2 * m)
    z = torch.randn(b, m + 1, generator=gen, dtype=torch.float64)
    u_s, eps = z[:, :m], z[:, m]
    slack_lhs = (qp.G @ z.unsqueeze(-1)).squeeze(-1) - qp.h
    # Paper eq. QP: L_f h + L_g h (u_RL + u_S) >= -alpha h - rho + eps ... (written as <= 0)
    rcbf = -(lf + torch.einsum('bkm,bm->bk', lg, u_rl + u_s) + alpha * h + rho) - eps[:, None]
    torch.testing.assert_close(slack_lhs[:, :k], rcbf)
    u = u_rl + u_s
    torch.testing.assert_close(slack_lhs[:, k:k + m], u - torch.tensor(hi, dtype=torch.float64))
    torch.testing.assert_close(slack_lhs[:, k + m:], torch.tensor(lo, dtype=torch.float64) - u)
    # Objective ||u_S||^2 + l eps^2 = 1/2 z^T P z.
    obj = 0.5 * torch.einsum('bi,bij,bj->b', z, qp.P, z)
    torch.testing.assert_close(obj, (u_s ** 2).sum(-1) + 1e3 * eps ** 2)


def test_qp_is_differentiable_in_the_proposal():
    lg = torch.tensor([[[2.0, -1.0]]], dtype=torch.float64)
    u_rl = torch.tensor([[0.3, 0.4]], dtype=torch.float64, requires_grad=True)
    qp = build_rcbf_qp(h=torch.ones(1, 1, dtype=torch.float64),
                       lf_h=torch.zeros(1, 1, dtype=torch.float64), lg_h=lg,
                       rho=torch.zeros(1, 1, dtype=torch.float64), u_rl=u_rl, alpha=1.0,
                       slack_weight=10.0)
    (grad,) = torch.autograd.grad(qp.h.sum(), u_rl)
    torch.testing.assert_close(grad, lg[0])


def test_euler_step_of_the_unicycle():
    x = torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64)
    u = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    nxt = step_euler(Unicycle(), x, u, 0.1)
    torch.testing.assert_close(nxt, torch.tensor([[0.0, 0.1, math.pi / 2 + 0.05]],
                                                 dtype=torch.float64), atol=1e-12, rtol=0)


def test_car_following_nominal_accelerations():
    sys = CarFollowing()
    x = torch.tensor([[34.0, 30.0, 30.0, 29.0, 22.0, 30.0, 16.0, 30.0, 10.0, 31.0]])
    a = sys.nominal_accelerations(x)[0]
    # car 2 is 4 m behind car 1 (< 6): tracks and brakes; car 3 is 8 m behind car 2: tracks only.
    assert a[1].item() == pytest.approx(4.0 * (30 - 29) - 20.0 * 4.0)
    assert a[2].item() == pytest.approx(0.0)
    # car 5 is 12 m behind car 3: not < 12, so only tracking.
    assert a[4].item() == pytest.approx(4.0 * (30 - 31))
    assert sys.g(x)[0, 7, 0] == 1.0 and sys.g(x).abs().sum() == 1.0


def test_pvtol_drift_and_operator():
    sys = PVTOL(operator_gain=0.5)
    x = torch.tensor([[1.0, 2.0, 0.3, -0.2, 0.1, 1.2, 0.4]])
    f = sys.f(x)[0]
    expected = [0.3, -0.2, -math.sin(0.1) * 1.2, math.cos(0.1) * 1.2 - 1.0, 0.0, 0.0, 0.5 * 0.6]
    np.testing.assert_allclose(f.numpy(), expected, rtol=1e-6)
    assert PVTOL(with_operator=False).n_x == 6


def test_load_system_by_dotted_path_and_errors():
    assert isinstance(load_system('rcbf_ros.core.dynamics.Unicycle'), Unicycle)
    with pytest.raises(ValueError, match='system:'):
        load_system('no_such_system')
    with pytest.raises(ValueError, match='system:'):
        load_system('rcbf_ros.core.dynamics.NoSuchClass')
    with pytest.raises(ValueError, match='system_params'):
        load_system('unicycle', {'bogus': 1})


@pytest.mark.parametrize('name', ['unicycle', 'car_following', 'pvtol'])
def test_shipped_configs_build(name):
    config = filter_config_from_params(load_params(find_config(name), 'safety_filter'))
    assert config.problem.n_barriers >= 2
    assert config.fail_safe_action is not None


@pytest.mark.parametrize('params,key', [
    ({}, 'system'),
    ({'system': 'unicycle'}, 'barriers'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0, 1.0], 'radius': [1.0]}},
     'obstacles.y'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [float('nan')]}},
     'obstacles.radius'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0]},
      'alpha': 'fast'}, 'alpha'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0]},
      'disturbance': {'std': [0.1, 0.1]}}, 'disturbance.std'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                          'heading_index': 7}}, 'obstacles.heading_index'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                          'heading_index': 2, 'lookahead': 0.03, 'margin': 0.03,
                                          'speed_input': 2}}, 'obstacles.speed_input'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                          'heading_index': 2, 'speed_input': 0}},
     'obstacles.speed_input'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                          'heading_index': 2, 'lookahead': 0.03, 'margin': 0.03,
                                          'speed_input': 0, 'gammas': [1.0]}},
     'obstacles.speed_input'),
    ({'system': 'pvtol', 'bands': {'operator': {'index': 0, 'half_width': -1.0}}},
     'bands.operator.'),
    ({'system': 'car_following', 'gaps': {'a': [4, 12], 'b': [6, 6], 'delta': 3.5}},
     'gaps.a'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                          'position_indices': [0, 5]}},
     'obstacles.position_indices'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0]},
      'input_limits': {'min': [1.0, 1.0], 'max': [0.0, 2.0]}}, 'input_limits.min'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0]},
      'input_weight': [1.0]}, 'input_weight'),
    ({'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0]},
      'input_weight': [1.0, 0.0]}, 'input_weight'),
])
def test_config_errors_name_the_key(params, key):
    with pytest.raises(ValueError, match=key.replace('.', r'\.')):
        filter_config_from_params(params)


ONE_OBSTACLE = {'x': [0.0], 'y': [0.0], 'radius': [1.0]}


@pytest.mark.parametrize('override, key', [
    ({'fail_safe_action': [99.0, 0.0]}, r'^fail_safe_action: .* outside the input limits'),
    ({'fail_safe_action': [0.0, -2.6]}, r'^fail_safe_action: .* outside the input limits'),
    ({'obstacles': dict(ONE_OBSTACLE, margin=-5.0)}, r'^obstacles\.margin: must be >= 0'),
    ({'obstacles': dict(ONE_OBSTACLE, radius=[-0.5])}, r'^obstacles\.radius: every radius'),
    ({'obstacles': dict(ONE_OBSTACLE, radius=[0.0])}, r'^obstacles\.radius: radius \+'),
    ({'obstacles': dict(ONE_OBSTACLE, lookahead=-0.1, heading_index=2)},
     r'^obstacles\.lookahead: must be >= 0'),
    ({'obstacles': dict(ONE_OBSTACLE, gammas=[1.0, -1.0])}, r'^obstacles\.gammas: every'),
    ({'alpha': 0.0}, r'^alpha: must be > 0'),
    ({'alpha': -2.0}, r'^alpha: must be > 0'),
    ({'k_c': -0.1}, r'^k_c: must be >= 0'),
    ({'slack_weight': 0.0}, r'^slack_weight: must be >= 1e-12'),
    ({'walls': {'nx': [0.0], 'ny': [0.0], 'offset': [1.0]}}, r'^walls\.nx/walls\.ny: '),
    # each would make the filter guard nothing or refuse everything
    ({'obstacles': dict(ONE_OBSTACLE, lookahead=10.0, heading_index=2, margin=0.1)},
     r'^obstacles\.lookahead: 10 exceeds obstacles\.margin 0\.1'),
    ({'input_weight': [5e-324, 5e-324]}, r'^input_weight: must be >= 1e-12'),
    ({'disturbance': {'std': [0.1, -0.1, 0.0]}}, r'^disturbance\.std: must be >= 0'),
])
def test_unsafe_values_are_refused_naming_the_key(override, key):
    # Silently clipping a fail-safe of [99, 0] gave full speed; a negative margin shrank every
    # obstacle; a negative radius was reported under a key nobody writes (obstacles.radii).
    params = {'system': 'unicycle', 'obstacles': ONE_OBSTACLE, **override}
    with pytest.raises(ValueError, match=key):
        filter_config_from_params(params)


def test_a_gap_or_band_against_itself_and_a_dotted_band_name_are_refused():
    with pytest.raises(ValueError, match=r'^gaps\.b: state 4 is also its gaps\.a'):
        filter_config_from_params({'system': 'car_following',
                                   'gaps': {'a': [4], 'b': [4], 'delta': 0.5}})
    with pytest.raises(ValueError, match=r'^bands\.lane\.center_index: state 1 is the band'):
        filter_config_from_params({'system': 'unicycle', 'bands.lane.index': 1,
                                   'bands.lane.half_width': 3.0, 'bands.lane.center_index': 1})
    with pytest.raises(ValueError, match=r'^bands\.a\.b\.\w+: expected bands\.<name>\.<key>'):
        filter_config_from_params({'system': 'unicycle', 'bands.a.b.index': 0,
                                   'bands.a.b.half_width': 1.0, 'obstacles': ONE_OBSTACLE})


def test_gaps_delta_and_band_gains_are_checked():
    with pytest.raises(ValueError, match=r'^gaps\.delta: must be >= 0'):
        filter_config_from_params({'system': 'car_following',
                                   'gaps': {'a': [4], 'b': [6], 'delta': -1.0}})
    with pytest.raises(ValueError, match=r'^bands\.tilt\.gammas: every cascade gain'):
        filter_config_from_params({'system': 'pvtol', 'bands': {'tilt': {
            'index': 4, 'half_width': 1.0, 'gammas': [0.0]}}})


@pytest.mark.parametrize('bad', [1.5, True, float('inf'), float('nan'), 'one'])
def test_an_index_that_is_not_an_integer_is_refused_not_truncated(bad):
    base = {'system': 'unicycle', 'obstacles': {'x': [0.0], 'y': [0.0], 'radius': [1.0],
                                                'heading_index': 2, 'lookahead': 0.03,
                                                'margin': 0.09}}
    assert filter_config_from_params(
        {**base, 'obstacles': {**base['obstacles'], 'speed_input': 0.0}}) is not None
    with pytest.raises(ValueError, match=r'obstacles\.speed_input: expected an integer'):
        filter_config_from_params({**base, 'obstacles': {**base['obstacles'], 'speed_input': bad}})


def test_flatten_matches_ros_dotted_names():
    assert flatten({'a': {'b': 1, 'c': {'d': [1, 2]}}, 'e': 'x'}) == {
        'a.b': 1, 'a.c.d': [1, 2], 'e': 'x'}


def test_params_file_node_section_overrides_wildcard(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    alpha: 1.0\n    k_c: 3.0\n'
                    '/safety_filter:\n  ros__parameters:\n    alpha: 2.0\n'
                    '/other:\n  ros__parameters:\n    alpha: 9.0\n')
    assert load_params(path, 'safety_filter') == {'alpha': 2.0, 'k_c': 3.0}
    with pytest.raises(FileNotFoundError):
        load_params(tmp_path / 'missing.yaml', 'x')


def test_problem_counts_rows():
    problem = RCBFProblem(PVTOL(), (CircleObstacles(centers=((0.0, 0.0),) * 3,
                                                    radii=(1.0,) * 3),))
    assert problem.n_barriers == 3 and problem.n_constraints == 3 + 4
    no_limits = RCBFProblem(CarFollowing(), (CircleObstacles(centers=((0.0, 0.0),),
                                                             radii=(1.0,)),))
    assert no_limits.n_constraints == 1


def test_envelope_params_keep_only_the_bands_of_every_layout():
    from rcbf_ros.core.config import envelope_params, envelope_problem
    params = {'system': 'pvtol', 'obstacles.x': [1.0], 'obstacles.y': [0.0],
              'obstacles.radius': [0.4], 'obstacles.gammas': [1.0, 1.0],
              'bands.operator.layout': True, 'bands.operator.index': 0,
              'bands.operator.center_index': 6, 'bands.operator.half_width': 0.5,
              'bands.operator.gammas': [1.0, 1.0], 'bands.tilt.index': 4,
              'bands.tilt.half_width': 1.0, 'bands.tilt.layout': False, 'alpha': 2.0}
    envelope = envelope_params(params)
    assert not any(k.startswith(('obstacles.', 'bands.operator.')) for k in envelope)
    assert envelope['bands.tilt.half_width'] == 1.0 and envelope['alpha'] == 2.0
    problem = envelope_problem(params)
    assert problem is not None and problem.barrier_names == ['tilt'] and problem.alpha == 2.0
    assert problem.system.n_x == 7  # the same system: the learner's GP serves both
    assert envelope_problem({k: v for k, v in params.items()
                             if not k.startswith('bands.tilt.')}) is None
    # A string is not a flag ('false' would otherwise count as true).
    with pytest.raises(ValueError, match=r'bands\.operator\.layout'):
        envelope_params({**params, 'bands.operator.layout': 'false'})


@pytest.mark.parametrize('system, obstacles, key', [
    ('unicycle', {'heading_index': 0}, r'^obstacles\.heading_index: state 0 '
     r'of Unicycle is not a heading; its heading is state 2'),
    ('unicycle', {'heading_index': 1}, r'^obstacles\.heading_index: state 1'),
    ('unicycle', {'position_indices': [0, 2]}, r'^obstacles\.position_indices: state 2 of '
     r'Unicycle is a heading'),
    ('pvtol', {'heading_index': 2}, r'^obstacles\.heading_index: state 2 of '
     r'PVTOL is not a heading; its heading is state 4'),
    ('car_following', {'heading_index': 1}, r'^obstacles\.heading_index: .* it has no heading'),
])
def test_obstacle_indices_are_checked_against_the_state_layout(system, obstacles, key):
    # heading_index 0 on the Unicycle would make the guarded point follow x as if it were the
    # heading, and the answers break the true rows
    params = {'system': system, 'obstacles': {**ONE_OBSTACLE, **obstacles}}
    with pytest.raises(ValueError, match=key):
        filter_config_from_params(params)


@pytest.mark.parametrize('system, extra, words', [
    ('car_following', {'obstacles.x': [1.0], 'obstacles.y': [0.0], 'obstacles.radius': [0.5]},
     r'^obstacles\.x: system car_following declares no planar position \(its state \[p1, '
     r'v1, '),
    ('car_following', {'observation_sources': ['front'], 'front.type': 'scan',
                       'front.topic': 'scan', 'footprint.radius': 0.2},
     r'^observation_sources: system car_following declares no planar position'),
    ('pvtol', {'obstacles.position_indices': [2, 3]},
     r'^obstacles\.position_indices: \[2, 3\] is not the planar position of pvtol, \[0, 1\] '
     r'\(x1, x2\)'),
    ('unicycle', {'obstacles.position_indices': [1, 0]},
     r'^obstacles\.position_indices: \[1, 0\] is not the planar position of unicycle'),
])
def test_points_in_a_plane_need_the_planar_position_the_system_declares(system, extra, words):
    # the cars' default position_indices [0, 1] is (p1, v1): a position and a speed, which
    # a circle or a sensor point would take as a point in a plane
    from rcbf_ros.parameters.rules import find_config, load_params
    params = load_params(find_config(system), 'safety_filter')
    params.update(extra)
    with pytest.raises(ValueError, match=words):
        filter_config_from_params(params)
    for shipped in ('unicycle', 'pvtol', 'car_following'):
        filter_config_from_params(load_params(find_config(shipped), 'safety_filter'))


@pytest.mark.parametrize('system, heading', [('unicycle', 2), ('pvtol', 4)])
def test_the_heading_index_of_each_system_is_accepted(system, heading):
    params = {'system': system, 'obstacles': {**ONE_OBSTACLE, 'heading_index': heading,
                                              'lookahead': 0.05, 'margin': 0.05}}
    assert filter_config_from_params(params).problem.n_barriers == 1


@pytest.mark.parametrize('lookahead, margin, refused', [(0.03, 0.09, False), (0.03, 0.089, True),
                                                        (0.02, 0.05, True), (0.01, 0.03, False)])
def test_a_point_that_may_switch_behind_needs_three_lookaheads_of_margin(lookahead, margin,
                                                                         refused):
    """With speed_input the guarded point may switch to the one behind the robot; the centre
    then stays delta - 3 |l_p| from an obstacle's centre (rcbf_ros.core.rcbf.barrier_terms), so
    a margin below 3 |l_p| could let the robot into an obstacle: refused, naming both keys.
    Without speed_input the point stays ahead and margin >= |l_p| is enough."""
    obstacles = {'x': [0.0], 'y': [0.0], 'radius': [1.0], 'heading_index': 2,
                 'lookahead': lookahead, 'margin': margin, 'speed_input': 0}
    params = {'system': 'unicycle', 'obstacles': obstacles}
    if refused:
        with pytest.raises(ValueError, match=r'obstacles\.margin: .* 3 x obstacles\.lookahead'):
            filter_config_from_params(params)
        obstacles.pop('speed_input')
        if abs(lookahead) <= margin:
            assert filter_config_from_params(params) is not None
    else:
        assert filter_config_from_params(params) is not None

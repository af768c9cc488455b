"""The batched closed-form barrier terms (rcbf_ros.core.lie_closed_form_batch) against autograd.

References, none of them the code under test: RCBFProblem.terms (autograd through every barrier
and cascade) on the shipped configs and random variations of them, torch.autograd.functional
for the systems' Jacobians, and the differentiable layer's answer and gradient on the autograd
path.
"""
from __future__ import annotations

import numpy as np
import pytest
from test_lie_closed_form import (
    LOOKAHEAD,
    OwnFamily,
    OwnUnicycle,
    problems,
    random_state,
    shipped,
    SYSTEMS,
    TOLERANCE,
)
import torch

from rcbf_ros.core.config import envelope_problem, filter_config_from_params
from rcbf_ros.core.dynamics import CarFollowing, PVTOL, Unicycle
from rcbf_ros.core.lie_closed_form_batch import BatchClosedForm
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.learning.safety_layer import DifferentiableSafetyLayer


def assert_close(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    scale = max(1.0, float(want.abs().max()))
    torch.testing.assert_close(got, want, rtol=TOLERANCE, atol=TOLERANCE * scale, msg=what)


def states(system: str, n_x: int, count: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(np.stack([random_state(system, rng, n_x) for _ in range(count)]))


@pytest.mark.parametrize('system', [Unicycle(), CarFollowing(), PVTOL(),
                                    PVTOL(with_operator=False),
                                    CarFollowing(k_v=2.5, k_b=7.0, brake_gap=9.0)],
                         ids=['unicycle', 'cars', 'pvtol', 'pvtol-6', 'cars-gains'])
def test_drift_jacobian_matches_autograd(system):
    name = {Unicycle: 'unicycle', CarFollowing: 'car_following', PVTOL: 'pvtol'}[type(system)]
    x = states(name, system.n_x, 40, seed=1)
    got = system.drift_jacobian(x)
    for b in range(x.shape[0]):
        want = torch.autograd.functional.jacobian(lambda s: system.f(s[None])[0], x[b])
        torch.testing.assert_close(got[b], want, rtol=0, atol=1e-12)
    if name == 'car_following':  # both braking branches were taken
        braking = got[:, 3, 0] != 0
        assert 0 < int(braking.sum()) < x.shape[0]


@pytest.mark.parametrize('system', SYSTEMS)
def test_terms_match_autograd_on_shipped_and_varied_configs(system):
    for index, problem in enumerate(problems(system, 12, seed=10 + SYSTEMS.index(system))):
        closed = BatchClosedForm.from_problem(problem)
        assert closed is not None
        n_x, n_u = problem.system.n_x, problem.system.n_u
        x = states(system, n_x, 64, seed=index)
        u = torch.from_numpy(np.random.default_rng(index).uniform(-3.0, 3.0, (64, n_u)))
        for proposal in (u, None):
            got = closed.terms(x, proposal)
            want = problem.terms(x, proposal)
            for name, a, b in zip(got._fields, got, want):
                assert_close(a, b, f'{system} problem {index} {name}')


def test_the_lookahead_point_follows_the_direction_of_travel_as_autograd_does():
    """States on the obstacles' rims, where the point ahead and the point behind disagree."""
    rng = np.random.default_rng(4)
    params = shipped('unicycle')
    problem = filter_config_from_params(params).problem
    centers = np.stack([params['obstacles.x'], params['obstacles.y']], axis=1)
    delta = np.array(params['obstacles.radius']) + params['obstacles.margin']
    which = rng.integers(len(centers), size=400)
    angle = rng.uniform(-np.pi, np.pi, 400)
    rim = centers[which] + (delta[which] + rng.uniform(-0.04, 0.04, 400))[:, None] * np.stack(
        [np.cos(angle), np.sin(angle)], axis=1)
    x = torch.from_numpy(np.column_stack([rim, rng.uniform(-np.pi, np.pi, 400)]))
    u = torch.from_numpy(rng.uniform(-2.5, 2.5, (400, 2)))
    got = BatchClosedForm.from_problem(problem).terms(x, u)
    want = problem.terms(x, u)
    for name, a, b in zip(got._fields, got, want):
        assert_close(a, b, name)
    ahead = problem.terms(x).h
    switched = (got.h != ahead).any(dim=1)
    assert 20 <= int(switched.sum()) <= 380  # both choices occur


def test_the_pvtol_envelope_takes_the_closed_form_too():
    params = shipped('pvtol')
    envelope = envelope_problem(params)
    closed = BatchClosedForm.from_problem(envelope)
    assert closed is not None
    x = states('pvtol', envelope.system.n_x, 50, seed=3)
    for name, a, b in zip(closed.terms(x)._fields, closed.terms(x), envelope.terms(x)):
        assert_close(a, b, name)


@pytest.mark.parametrize('problem', [RCBFProblem(OwnUnicycle(), (LOOKAHEAD,)),
                                     RCBFProblem(Unicycle(), (LOOKAHEAD, OwnFamily()))],
                         ids=['own system', 'own family'])
def test_other_problems_have_no_batched_closed_form(problem):
    assert BatchClosedForm.from_problem(problem) is None
    assert DifferentiableSafetyLayer(problem)._closed_form is None


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_layer_gives_the_autograd_paths_safe_action_and_gradient(system):
    problem = filter_config_from_params(shipped(system)).problem
    layer = DifferentiableSafetyLayer(problem)
    assert layer._closed_form is not None
    autograd_layer = DifferentiableSafetyLayer(problem)
    autograd_layer._closed_form = None
    n_x, n_u = problem.system.n_x, problem.system.n_u
    x = states(system, n_x, 64, seed=7)
    rng = np.random.default_rng(7)
    u = torch.from_numpy(rng.uniform(-2.5, 2.5, (64, n_u)))
    mean = torch.from_numpy(rng.normal(0.0, 0.05, (64, n_x)))
    std = torch.from_numpy(rng.uniform(0.0, 0.05, (64, n_x)))
    weights = torch.from_numpy(rng.normal(size=(64, n_u)))
    answers = []
    for each in (layer, autograd_layer):
        u_rl = u.clone().requires_grad_(True)
        safe = each(x, u_rl, (mean, std))
        (gradient,) = torch.autograd.grad((weights * safe).sum(), u_rl)
        answers.append((safe.detach(), gradient))
    assert float((answers[0][0] - u).abs().max()) > 1e-3  # the filter corrected something
    torch.testing.assert_close(answers[0][0], answers[1][0], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(answers[0][1], answers[1][1], rtol=1e-7, atol=1e-7)

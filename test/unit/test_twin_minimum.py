"""twin_minimum against autograd through both critics and torch.minimum: the value bit for bit,
the action gradient to float64 round-off, at ties too, for any depth of critic; no gradient
reaches the critics' weights."""
from __future__ import annotations

import copy

import pytest
import torch

from rcbf_ros.learning.networks import QNetwork, twin_minimum

OBS, N_U, B = 4, 3, 64


def _critics(hidden: tuple[int, ...], seed: int) -> tuple[QNetwork, QNetwork]:
    torch.manual_seed(seed)
    return (QNetwork(OBS, N_U, hidden).to(torch.float64),
            QNetwork(OBS, N_U, hidden).to(torch.float64))


def _autograd(first: QNetwork, second: QNetwork, obs: torch.Tensor, action: torch.Tensor,
              weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    action = action.detach().clone().requires_grad_(True)
    value = torch.minimum(first(obs, action), second(obs, action))
    (grad,) = torch.autograd.grad((value * weights).sum(), action)
    return value.detach(), grad


def _ours(first: QNetwork, second: QNetwork, obs: torch.Tensor, action: torch.Tensor,
          weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    action = action.detach().clone().requires_grad_(True)
    value = twin_minimum(first, second, obs, action)
    (grad,) = torch.autograd.grad((value * weights).sum(), action)
    return value.detach(), grad


@pytest.mark.parametrize('hidden', [(7,), (16, 9), (8, 8, 5)])
@pytest.mark.parametrize('seed', range(3))
def test_value_and_action_gradient_are_autograds_through_both_critics(hidden, seed):
    first, second = _critics(hidden, seed)
    g = torch.Generator().manual_seed(seed + 10)
    obs = torch.randn(B, OBS, generator=g, dtype=torch.float64)
    action = torch.randn(B, N_U, generator=g, dtype=torch.float64)
    weights = torch.randn(B, generator=g, dtype=torch.float64)
    with torch.no_grad():   # shift the second critic so that each is the minimum of about half
        second.net[-1].bias += (first(obs, action) - second(obs, action)).median()
    value, grad = _ours(first, second, obs, action, weights)
    expected_value, expected_grad = _autograd(first, second, obs, action, weights)
    assert torch.equal(value, expected_value)
    firsts = int((first(obs, action) < second(obs, action)).sum())
    assert 0 < firsts < B   # each critic is the minimum of some samples
    torch.testing.assert_close(grad, expected_grad, rtol=1e-12, atol=1e-14)


def test_at_a_tie_each_critic_takes_half_of_the_gradient_as_autograd_gives_it():
    first, _ = _critics((12, 6), 4)
    twin = copy.deepcopy(first)
    with torch.no_grad():   # the twin differs in the first layer's action columns only
        twin.net[0].weight[:, OBS:] *= 1.5
    g = torch.Generator().manual_seed(5)
    obs = torch.randn(B, OBS, generator=g, dtype=torch.float64)
    action = torch.randn(B, N_U, generator=g, dtype=torch.float64)
    action[::2] = 0.0   # there both critics give the same value: a tie
    weights = torch.rand(B, generator=g, dtype=torch.float64) + 0.5
    value, grad = _ours(first, twin, obs, action, weights)
    expected_value, expected_grad = _autograd(first, twin, obs, action, weights)
    assert torch.equal(first(obs, action)[::2], twin(obs, action)[::2])
    assert torch.equal(value, expected_value)
    torch.testing.assert_close(grad, expected_grad, rtol=1e-12, atol=1e-14)
    alone, _ = _ours(first, first, obs, action, weights)
    assert torch.equal(alone, first(obs, action).detach())


def test_one_critic_the_minimum_everywhere_and_the_critics_weights_get_no_gradient():
    first, second = _critics((10,), 6)
    with torch.no_grad():
        second.net[-1].bias += 100.0   # second is never the minimum
    g = torch.Generator().manual_seed(7)
    obs = torch.randn(B, OBS, generator=g, dtype=torch.float64)
    action = torch.randn(B, N_U, generator=g, dtype=torch.float64)
    weights = torch.ones(B, dtype=torch.float64)
    value, grad = _ours(first, second, obs, action, weights)
    expected_value, expected_grad = _autograd(first, second, obs, action, weights)
    assert torch.equal(value, expected_value)
    torch.testing.assert_close(grad, expected_grad, rtol=1e-12, atol=1e-14)
    action = action.requires_grad_(True)
    twin_minimum(first, second, obs, action).sum().backward()
    assert all(p.grad is None for p in (*first.parameters(), *second.parameters()))


def test_an_observation_that_requires_a_gradient_is_refused():
    first, second = _critics((5,), 8)
    obs = torch.zeros(2, OBS, dtype=torch.float64, requires_grad=True)
    with pytest.raises(ValueError, match='twin_minimum: obs'):
        twin_minimum(first, second, obs, torch.zeros(2, N_U, dtype=torch.float64))

"""SAC's one-observation acting path returns exactly what the straightforward formulation
returns: the noise drawn as ``torch.randn((1, n_u))`` from the agent's generator, in the same
order relative to the updates' draws, and the squashed-Gaussian action computed with
out-of-place numpy operations and ``np.clip``."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rcbf_ros.learning.networks import LOG_STD_MAX, LOG_STD_MIN
from rcbf_ros.learning.sac import SAC, SACConfig


def reference_act(agent: SAC, generator: torch.Generator, obs: np.ndarray,
                  deterministic: bool) -> tuple[np.ndarray, np.ndarray]:
    """(u_proposed, u_rl) of one observation, from the torch weights and ``generator``."""
    noise = None if deterministic else torch.randn(
        (1, agent.n_u), generator=generator, dtype=agent.dtype)[0].numpy()
    actor = agent.actor
    dtype = actor.action_center.numpy().dtype
    x = np.asarray(obs, dtype=dtype)
    layers = [m for m in actor.trunk[0] if isinstance(m, torch.nn.Linear)]
    for index, layer in enumerate(layers):
        x = layer.weight.detach().numpy() @ x + layer.bias.detach().numpy()
        if index + 1 < len(layers):
            x = np.maximum(x, 0.0)
    features = np.maximum(x, 0.0)
    center = actor.action_center.numpy()
    half_range = actor.action_half_range.numpy()
    mean = (actor.mean_head.weight.detach().numpy() @ features
            + actor.mean_head.bias.detach().numpy())
    mean_action = center + half_range * np.tanh(mean)
    if noise is None:
        u_rl = mean_action
    else:
        log_std = np.clip(actor.log_std_head.weight.detach().numpy() @ features
                          + actor.log_std_head.bias.detach().numpy(), LOG_STD_MIN, LOG_STD_MAX)
        u_rl = center + half_range * np.tanh(mean + np.exp(log_std) * noise)
    u_proposed = u_rl
    if agent.compensator is not None:
        compensator = [m for m in agent.compensator.net if isinstance(m, torch.nn.Linear)]
        c = np.asarray(obs, dtype=dtype)
        for index, layer in enumerate(compensator):
            c = layer.weight.detach().numpy() @ c + layer.bias.detach().numpy()
            if index + 1 < len(compensator):
                c = np.maximum(c, 0.0)
        u_proposed = np.clip(u_rl + c, center - half_range, center + half_range)
    return u_proposed, u_rl


@pytest.mark.parametrize('n_u', [1, 2, 3, 17])
@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
@pytest.mark.parametrize('mode', ['baseline', 'baseline_compensator'])
def test_one_observation_acting_equals_the_reference_bit_for_bit(n_u, dtype, mode):
    obs_dim = 5
    low, high = -np.linspace(1.0, 2.0, n_u), np.linspace(0.5, 3.0, n_u)
    agent = SAC(obs_dim, n_u, low, high, SACConfig(mode=mode, hidden_sizes=(32, 24)), seed=3,
                dtype=dtype)
    generator = torch.Generator().manual_seed(4)  # the agent's noise generator: seed + 1
    rng = np.random.default_rng(0)
    for step in range(60):
        obs = rng.normal(scale=3.0, size=obs_dim)
        deterministic = step % 7 == 3
        proposal = agent.act_detailed(obs, deterministic)
        u_proposed, u_rl = reference_act(agent, generator, obs, deterministic)
        np.testing.assert_array_equal(proposal.u_rl, u_rl)
        np.testing.assert_array_equal(proposal.u_proposed, u_proposed)
        assert proposal.u_rl.dtype == u_rl.dtype and proposal.u_rl.shape == (n_u,)
        if step % 5 == 0:  # an update's batch draw from the same generator in between
            a = torch.randn((256, n_u), generator=agent.generator, dtype=dtype)
            b = torch.randn((256, n_u), generator=generator, dtype=dtype)
            assert torch.equal(a, b)
    assert torch.equal(agent.generator.get_state(), generator.get_state())


def test_the_returned_arrays_are_the_callers_own():
    agent = SAC(4, 2, -np.ones(2), np.ones(2), SACConfig(hidden_sizes=(8, 8)), seed=0)
    obs = np.arange(4.0)
    first = agent.act_detailed(obs)
    kept = first.u_rl.copy(), first.u_proposed.copy()
    first.u_proposed[:] = 99.0
    assert np.array_equal(first.u_rl, kept[0])
    second = agent.act_detailed(obs)
    assert np.array_equal(first.u_rl, kept[0]) and not np.shares_memory(first.u_rl,
                                                                         second.u_rl)
    # A list and a float32 array take the same path to the same numbers.
    generator_state = agent.generator.get_state()
    from_array = agent.act_detailed(obs.astype(np.float32))
    agent.generator.set_state(generator_state)
    from_list = agent.act_detailed(list(obs))
    np.testing.assert_array_equal(from_array.u_rl, from_list.u_rl)

"""The twin critics as one batched network, the lean Adam step and the actor's log density,
each against an independent computation (two separate networks, torch.optim.Adam,
torch.distributions), and checkpoints in the per-network layout."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rcbf_ros.learning.buffers import TransitionBatch
from rcbf_ros.learning.networks import QNetwork, SquashedGaussianActor, TwinQNetwork
from rcbf_ros.learning.sac import AdamStep, SAC, SACConfig

OBS, N_U, B = 4, 2, 16
HIDDEN = (8, 6)


def _pair(dtype: torch.dtype = torch.float64) -> tuple[QNetwork, QNetwork]:
    torch.manual_seed(0)
    return QNetwork(OBS, N_U, HIDDEN).to(dtype), QNetwork(OBS, N_U, HIDDEN).to(dtype)


def _linears(network: QNetwork) -> list[torch.nn.Linear]:
    return [m for m in network.net if isinstance(m, torch.nn.Linear)]


def _batch(seed: int, dtype: torch.dtype = torch.float64) -> TransitionBatch:
    g = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=dtype) * 2 - 1

    u = rand(B, N_U)
    return TransitionBatch(obs=rand(B, OBS), state=rand(B, 2), u_rl=u, u_safe=u,
                           u_s=torch.zeros_like(u), reward=rand(B), next_obs=rand(B, OBS),
                           next_state=rand(B, 2), done=(rand(B) > 0.6).to(dtype))


def test_twin_forward_and_backward_equal_two_separate_networks():
    first, second = _pair()
    twin = TwinQNetwork([first, second])
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(B, OBS, generator=g, dtype=torch.float64)
    action = torch.randn(B, N_U, generator=g, dtype=torch.float64)
    weights = torch.randn(2, B, generator=g, dtype=torch.float64)

    obs_t, action_t = obs.clone().requires_grad_(True), action.clone().requires_grad_(True)
    q = twin(obs_t, action_t)
    (weights * q).sum().backward()
    obs_s, action_s = obs.clone().requires_grad_(True), action.clone().requires_grad_(True)
    separate = torch.stack([first(obs_s, action_s), second(obs_s, action_s)])
    (weights * separate).sum().backward()

    assert q.shape == (2, B)
    torch.testing.assert_close(q, separate, rtol=0, atol=1e-13)
    torch.testing.assert_close(obs_t.grad, obs_s.grad, rtol=0, atol=1e-13)
    torch.testing.assert_close(action_t.grad, action_s.grad, rtol=0, atol=1e-13)
    for layer, linears in zip(twin.layers, zip(_linears(first), _linears(second))):
        for index, linear in enumerate(linears):
            torch.testing.assert_close(layer.weight.grad[index].t(), linear.weight.grad,
                                       rtol=0, atol=1e-13)
            torch.testing.assert_close(layer.bias.grad[index, 0], linear.bias.grad,
                                       rtol=0, atol=1e-13)


def test_members_are_live_views_of_the_twin_and_loading_one_writes_its_slice():
    first, second = _pair()
    twin = TwinQNetwork([first, second])
    state = torch.random.get_rng_state()
    members = twin.member(0), twin.member(1)
    assert torch.equal(state, torch.random.get_rng_state())    # no draw from the global RNG
    x, u = torch.randn(B, OBS, dtype=torch.float64), torch.randn(B, N_U, dtype=torch.float64)
    for member, original in zip(members, (first, second)):
        assert not any(p.requires_grad for p in member.parameters())
        torch.testing.assert_close(member(x, u), original(x, u), rtol=0, atol=1e-14)
    with torch.no_grad():
        twin.layers[1].weight[1].mul_(2.0)
    assert torch.equal(members[1].net[2].weight, 2.0 * second.net[2].weight.detach())
    assert torch.equal(members[0].net[2].weight, first.net[2].weight.detach())
    other = QNetwork(OBS, N_U, HIDDEN).to(torch.float64)
    members[0].load_state_dict(other.state_dict())
    torch.testing.assert_close(twin(x, u)[0], other(x, u), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match='same layer sizes'):
        TwinQNetwork([first, QNetwork(OBS, N_U, (8, 5))])


def test_critic_loss_and_its_gradient_equal_those_of_two_separate_critics():
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), SACConfig(hidden_sizes=HIDDEN),
                dtype=torch.float64)
    batch = _batch(2)
    noise = torch.randn(B, N_U, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    first = QNetwork(OBS, N_U, HIDDEN).to(torch.float64)
    second = QNetwork(OBS, N_U, HIDDEN).to(torch.float64)
    first.load_state_dict(agent.q1.state_dict())
    second.load_state_dict(agent.q2.state_dict())

    loss, metrics = agent.critic_loss(batch, noise)
    loss.backward()
    target = agent.critic_target(batch, noise)
    q1, q2 = first(batch.obs, batch.u_rl), second(batch.obs, batch.u_rl)
    expected = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
    expected.backward()

    torch.testing.assert_close(loss, expected, rtol=0, atol=1e-14)
    assert metrics['q1_mean'] == pytest.approx(float(q1.detach().mean()), abs=1e-14)
    assert metrics['q2_mean'] == pytest.approx(float(q2.detach().mean()), abs=1e-14)
    for layer, linears in zip(agent.critics.layers, zip(_linears(first), _linears(second))):
        for index, linear in enumerate(linears):
            torch.testing.assert_close(layer.weight.grad[index].t(), linear.weight.grad,
                                       rtol=0, atol=1e-14)
            torch.testing.assert_close(layer.bias.grad[index, 0], linear.bias.grad,
                                       rtol=0, atol=1e-14)


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_adam_step_is_the_fused_optimizer_step_bit_for_bit(dtype):
    g = torch.Generator().manual_seed(4)
    shapes = [(5, 3), (5,), (2, 5, 1)]
    start = [torch.randn(*shape, generator=g, dtype=dtype) for shape in shapes]
    ours = [torch.nn.Parameter(t.clone()) for t in start]
    reference = [torch.nn.Parameter(t.clone()) for t in start]
    optimizer = torch.optim.Adam(ours, lr=1e-2, fused=True)
    reference_optimizer = torch.optim.Adam(reference, lr=1e-2, fused=True)
    step = AdamStep(optimizer)
    for _ in range(4):
        grads = [torch.randn(*shape, generator=g, dtype=dtype) for shape in shapes]
        step.zero_grad()
        for p, grad in zip(ours, grads):
            p.grad = grad.clone()
        for p, grad in zip(reference, grads):
            p.grad = grad.clone()
        step()
        reference_optimizer.step()
        for a, b in zip(ours, reference):
            assert torch.equal(a, b)
    ours_state, reference_state = optimizer.state_dict(), reference_optimizer.state_dict()
    for index, entry in reference_state['state'].items():
        for key, value in entry.items():
            assert torch.equal(ours_state['state'][index][key], value)
    # A parameter without a gradient: the optimizer's own step, which skips it.
    ours[0].grad = None
    step()
    reference[0].grad = None
    reference_optimizer.step()
    assert all(torch.equal(a, b) for a, b in zip(ours, reference))


def test_actor_log_density_equals_the_change_of_variables_by_torch_distributions():
    torch.manual_seed(5)
    low, high = torch.tensor([-1.0, -3.0], dtype=torch.float64), torch.tensor([2.0, 1.0],
                                                                               dtype=torch.float64)
    actor = SquashedGaussianActor(OBS, low, high, HIDDEN).to(torch.float64)
    obs = torch.randn(B, OBS, dtype=torch.float64)
    noise = torch.randn(B, N_U, dtype=torch.float64)
    sample = actor(obs, noise=noise)
    features = actor.trunk(obs)
    mean = actor.mean_head(features)
    std = actor.log_std_head(features).clamp(-5.0, 2.0).exp()
    z = mean + std * noise
    half = (high - low) / 2
    expected = (torch.distributions.Normal(mean, std).log_prob(z)
                - torch.log(half * (1 - torch.tanh(z) ** 2) + 1e-6)).sum(-1)
    torch.testing.assert_close(sample.log_prob, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(sample.action, (high + low) / 2 + half * torch.tanh(z),
                               rtol=0, atol=1e-14)
    torch.testing.assert_close(sample.mean_action, (high + low) / 2 + half * torch.tanh(mean),
                               rtol=0, atol=1e-14)


def _per_network_checkpoint(agent: SAC) -> dict:
    """A checkpoint in the per-network layout built without the twin: two QNetworks (q1's
    and q2's weights perturbed apart) and their targets, and torch.optim.Adam over
    ``[*q1.parameters(), *q2.parameters()]`` stepped twice on a loss of both."""
    torch.manual_seed(6)
    q1, q2 = QNetwork(OBS, N_U, HIDDEN), QNetwork(OBS, N_U, HIDDEN)
    q1_target, q2_target = QNetwork(OBS, N_U, HIDDEN), QNetwork(OBS, N_U, HIDDEN)
    optimizer = torch.optim.Adam([*q1.parameters(), *q2.parameters()], lr=3e-4, fused=True)
    batch = _batch(7, torch.float32)
    for _ in range(2):
        optimizer.zero_grad()
        loss = (q1(batch.obs, batch.u_rl) ** 2).mean() + (3 * q2(batch.obs, batch.u_rl)).mean()
        loss.backward()
        optimizer.step()
    state = agent.state_dict()
    state.update({'q1': q1.state_dict(), 'q2': q2.state_dict(),
                  'q1_target': q1_target.state_dict(), 'q2_target': q2_target.state_dict(),
                  'critic_optimizer': optimizer.state_dict()})
    return state


def test_per_network_checkpoints_load_into_the_twin_and_are_written_alike():
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), SACConfig(hidden_sizes=HIDDEN))
    old = _per_network_checkpoint(agent)
    agent.load_state_dict(old)
    for name in ('q1', 'q2', 'q1_target', 'q2_target'):
        for key, value in getattr(agent, name).state_dict().items():
            assert torch.equal(value, old[name][key])
    # The moments land on the twin's slices: twin parameter j, member k <- old entry 6 k + j.
    twin_params = list(agent.critics.parameters())
    names = [name for name, _ in agent.critics.named_parameters()]
    for j, (name, param) in enumerate(zip(names, twin_params)):
        moments = agent.critic_optimizer.state[param]
        for k in (0, 1):
            entry = old['critic_optimizer']['state'][k * len(twin_params) + j]
            for key in ('exp_avg', 'exp_avg_sq'):
                assert torch.equal(TwinQNetwork.member_tensor(name, moments[key], k), entry[key])
            assert float(moments['step']) == float(entry['step']) == 2.0
    # Written back in the same layout, value for value.
    saved = agent.state_dict()['critic_optimizer']
    assert saved['param_groups'] == old['critic_optimizer']['param_groups']
    assert saved['state'].keys() == old['critic_optimizer']['state'].keys()
    for index, entry in old['critic_optimizer']['state'].items():
        for key, value in entry.items():
            assert saved['state'][index][key].shape == value.shape
            assert saved['state'][index][key].is_contiguous()
            assert torch.equal(saved['state'][index][key], value)
    bad = {**old, 'critic_optimizer': {**old['critic_optimizer'], 'param_groups': [
        {**old['critic_optimizer']['param_groups'][0], 'params': list(range(6))}]}}
    with pytest.raises(ValueError, match='12 parameters'):
        agent.load_state_dict(bad)


def test_checkpoints_hold_each_network_alone_and_training_resumes_bit_for_bit():
    config = SACConfig(hidden_sizes=HIDDEN)
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, seed=1)
    for seed in range(3):
        agent.update(_batch(seed, torch.float32))
    state = agent.state_dict()
    for name in ('q1', 'q2', 'q1_target', 'q2_target'):
        for value in state[name].values():
            # Its own storage, not a view of both twins' weights.
            assert value.is_contiguous() and value.untyped_storage().nbytes() == value.nbytes
    resumed = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, seed=9)
    resumed.load_state_dict(state)
    for seed in range(3, 6):
        assert agent.update(_batch(seed, torch.float32)) == resumed.update(
            _batch(seed, torch.float32))
    for a, b in zip(agent.state_dict()['critic_optimizer']['state'].values(),
                    resumed.state_dict()['critic_optimizer']['state'].values()):
        assert all(torch.equal(a[key], b[key]) for key in a)
    for a, b in zip(agent.critics_target.parameters(), resumed.critics_target.parameters()):
        assert torch.equal(a, b)

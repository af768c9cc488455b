"""The parts of SAC's eager update, each against an independent computation: the critic loss
and its gradient (two critics evaluated apart), the lean Adam step (torch.optim.Adam), the
actor's log density (torch.distributions), a whole update (autograd losses, Optimizer.step,
alpha's loss differentiated by autograd, the Polyak rule written out) and checkpoints in
torch.optim.Adam's layout."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rcbf_ros.learning.buffers import BatchDisturbance, TransitionBatch
from rcbf_ros.learning.networks import QNetwork, SquashedGaussianActor
from rcbf_ros.learning.sac import AdamStep, SAC, SACConfig

OBS, N_U, B = 4, 2, 16
HIDDEN = (8, 6)
CRITICS = ('q1', 'q2', 'q1_target', 'q2_target')


def _batch(seed: int, dtype: torch.dtype = torch.float64) -> TransitionBatch:
    g = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=dtype) * 2 - 1

    u = rand(B, N_U)
    return TransitionBatch(obs=rand(B, OBS), state=rand(B, 2), u_rl=u, u_safe=u,
                           u_s=torch.zeros_like(u), reward=rand(B), next_obs=rand(B, OBS),
                           next_state=rand(B, 2), done=(rand(B) > 0.6).to(dtype))


def _copy(network: torch.nn.Module, like: torch.nn.Module) -> torch.nn.Module:
    """``network`` (a freshly built module) holding ``like``'s weights."""
    network.load_state_dict(like.state_dict())
    return network.to(torch.float64)


def test_critic_loss_is_half_the_two_critics_mean_squared_errors_and_reaches_each_critic():
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), SACConfig(hidden_sizes=HIDDEN),
                dtype=torch.float64)
    batch = _batch(2)
    noise = torch.randn(B, N_U, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    first = _copy(QNetwork(OBS, N_U, HIDDEN), agent.q1)
    second = _copy(QNetwork(OBS, N_U, HIDDEN), agent.q2)

    loss, metrics = agent.critic_loss(batch, noise)
    loss.backward()
    target = agent.critic_target(batch, noise)
    q1, q2 = first(batch.obs, batch.u_rl), second(batch.obs, batch.u_rl)
    expected = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
    expected.backward()

    assert torch.equal(loss, expected)
    assert metrics == {'q1_mean': float(q1.detach().mean()), 'q2_mean': float(q2.detach().mean()),
                       'target_mean': float(target.mean())}
    for critic, separate in ((agent.q1, first), (agent.q2, second)):
        for ours, theirs in zip(critic.parameters(), separate.parameters()):
            assert torch.equal(ours.grad, theirs.grad)


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


class _ReferenceSAC:
    """SAC's update written out with autograd and torch.optim.Adam.step() on copies of an
    agent's networks: alpha's loss differentiated by autograd, the Polyak rule as
    tau theta + (1 - tau) theta_bar, each critic and target on its own."""

    def __init__(self, agent: SAC, layer=None) -> None:
        self.layer = layer
        cfg, low, high = agent.config, agent.u_low, agent.u_high
        self.config, self.target_entropy = cfg, agent.target_entropy
        self.actor = _copy(SquashedGaussianActor(OBS, low, high, HIDDEN), agent.actor)
        for name in CRITICS:
            setattr(self, name, _copy(QNetwork(OBS, N_U, HIDDEN), getattr(agent, name)))
        self.log_alpha = agent.log_alpha.detach().clone().requires_grad_(True)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr,
                                                fused=True)
        self.critic_optimizer = torch.optim.Adam(
            [*self.q1.parameters(), *self.q2.parameters()], lr=cfg.critic_lr, fused=True)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr, fused=True)
        self.generator = torch.Generator().manual_seed(0)
        self.generator.set_state(agent.generator.get_state())

    def _safe(self, state, action, estimate):
        """The layer's action (``layer`` given: diff mode), else the action itself."""
        if self.layer is None:
            return action
        return self.layer(state, action, (estimate[:, 0], estimate[:, 1]))

    def update(self, batch: TransitionBatch, disturbance=None) -> dict[str, float]:
        """One update; with a layer, the diff mode's, the layer called apart at x_{t+1} (the
        target) and at x_t (the actor loss, after the critics' step)."""
        cfg = self.config
        alpha = self.log_alpha.detach().exp()
        next_noise = torch.randn(B, N_U, generator=self.generator, dtype=torch.float64)
        noise = torch.randn(B, N_U, generator=self.generator, dtype=torch.float64)
        with torch.no_grad():
            following = self.actor(batch.next_obs, noise=next_noise)
            next_action = self._safe(batch.next_state, following.action,
                                     None if disturbance is None else disturbance.next_state)
            next_q = torch.minimum(self.q1_target(batch.next_obs, next_action),
                                   self.q2_target(batch.next_obs, next_action))
            target = batch.reward + cfg.gamma * (1 - batch.done) * (
                next_q - alpha * following.log_prob)
        trained = batch.u_rl if self.layer is None else batch.u_safe
        q1, q2 = self.q1(batch.obs, trained), self.q2(batch.obs, trained)
        critic_loss = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
        self.critic_optimizer.zero_grad()
        critic_loss.backward()
        self.critic_optimizer.step()

        sample = self.actor(batch.obs, noise=noise)
        action = self._safe(batch.state, sample.action,
                            None if disturbance is None else disturbance.state)
        q = torch.minimum(self.q1(batch.obs, action), self.q2(batch.obs, action))
        actor_loss = (alpha * sample.log_prob - q).mean()
        self.actor_optimizer.zero_grad()
        actor_loss.backward()
        self.actor_optimizer.step()

        alpha_loss = -(self.log_alpha * (sample.log_prob.detach() + self.target_entropy)).mean()
        self.alpha_optimizer.zero_grad()
        alpha_loss.backward()
        self.alpha_optimizer.step()

        with torch.no_grad():
            for critic, target_critic in ((self.q1, self.q1_target), (self.q2, self.q2_target)):
                for param, target_param in zip(critic.parameters(), target_critic.parameters()):
                    target_param.copy_(cfg.tau * param + (1 - cfg.tau) * target_param)
            return {'q1_mean': float(q1.mean()), 'q2_mean': float(q2.mean()),
                    'target_mean': float(target.mean()), 'critic_loss': float(critic_loss),
                    'actor_loss': float(actor_loss), 'alpha': float(self.log_alpha.exp()),
                    'alpha_loss': float(alpha_loss), 'entropy': float(-sample.log_prob.mean())}


def _assert_same_metrics(metrics: dict[str, float], expected: dict[str, float], *,
                         rel: float) -> None:
    assert metrics.keys() == expected.keys()
    for key, value in expected.items():
        assert metrics[key] == pytest.approx(value, rel=rel, abs=1e-12), key


def _assert_same_weights(agent: SAC, reference: _ReferenceSAC, *, rtol: float,
                         atol: float) -> None:
    """The actor, the critics, their targets and log alpha of both agree."""
    for name in ('actor', *CRITICS):
        for ours, theirs in zip(getattr(agent, name).parameters(),
                                getattr(reference, name).parameters()):
            torch.testing.assert_close(ours, theirs, rtol=rtol, atol=atol)
    torch.testing.assert_close(agent.log_alpha, reference.log_alpha.detach(), rtol=rtol,
                               atol=atol)


def test_update_equals_the_update_written_out_with_autograd_and_optimizer_step():
    # tau large enough that a target moved toward the wrong critic is far off.
    config = SACConfig(hidden_sizes=HIDDEN, tau=0.3, actor_lr=1e-2, critic_lr=1e-2,
                       alpha_lr=1e-2)
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, seed=2, dtype=torch.float64)
    reference = _ReferenceSAC(agent)
    for seed in range(4):
        _assert_same_metrics(agent.update(_batch(seed)), reference.update(_batch(seed)),
                             rel=1e-9)
    _assert_same_weights(agent, reference, rtol=1e-9, atol=1e-12)
    for name in ('actor_optimizer', 'critic_optimizer', 'alpha_optimizer'):
        ours, theirs = getattr(agent, name).state_dict(), getattr(reference, name).state_dict()
        assert ours['state'].keys() == theirs['state'].keys()
        for index, entry in theirs['state'].items():
            for key, value in entry.items():
                torch.testing.assert_close(ours['state'][index][key], value, rtol=1e-9,
                                           atol=1e-12)


def _kinked_layer(state, u_rl, estimate):
    """A per-sample safety layer with a kink, differentiable almost everywhere: u_rl held
    below a bound that depends on the state and on the estimate's mean and std, so that a
    state or estimate paired with the wrong sample moves the answer."""
    mean, std = estimate
    bound = 0.1 + 0.5 * torch.tanh(state[:, :N_U] + mean[:, :N_U]) - std[:, :N_U]
    return u_rl - torch.relu(u_rl - bound)


def test_update_through_the_layer_equals_the_layer_called_apart_for_target_and_actor():
    """SAC.update runs the layer once on both halves of the minibatch; the update written out
    calls it apart, at x_{t+1} for the target and at x_t for the actor loss after the critics'
    step (the eager order of the paper's equations)."""
    config = SACConfig(mode='diff', hidden_sizes=HIDDEN, tau=0.3, actor_lr=1e-2,
                       critic_lr=1e-2, alpha_lr=1e-2)
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, safety_layer=_kinked_layer,
                seed=2, dtype=torch.float64)
    reference = _ReferenceSAC(agent, _kinked_layer)
    g = torch.Generator().manual_seed(11)
    clipped = 0
    for seed in range(4):
        batch = _batch(seed)
        batch = batch._replace(u_safe=batch.u_rl * 0.5)
        disturbance = BatchDisturbance(
            torch.rand(B, 2, 2, generator=g, dtype=torch.float64) * 0.4,
            torch.rand(B, 2, 2, generator=g, dtype=torch.float64) * 0.4)
        with torch.no_grad():
            probe = agent.actor(batch.obs, generator=torch.Generator().manual_seed(seed)).action
            clipped += int((_kinked_layer(batch.state, probe, (disturbance.state[:, 0],
                                                              disturbance.state[:, 1]))
                            != probe).sum())
        _assert_same_metrics(agent.update(batch, disturbance),
                             reference.update(batch, disturbance), rel=1e-12)
    assert clipped > 0   # the layer changes some of the policy's actions
    _assert_same_weights(agent, reference, rtol=1e-12, atol=1e-13)


def _adam_checkpoint(agent: SAC) -> dict:
    """A checkpoint built without the agent's update: two QNetworks and their targets (all
    apart), and torch.optim.Adam over ``[*q1.parameters(), *q2.parameters()]`` stepped twice
    on a loss of both."""
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


def test_adam_checkpoints_load_onto_each_critic_and_are_written_alike():
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), SACConfig(hidden_sizes=HIDDEN))
    old = _adam_checkpoint(agent)
    agent.load_state_dict(old)
    for name in CRITICS:
        for key, value in getattr(agent, name).state_dict().items():
            assert torch.equal(value, old[name][key])
    # Entry j of the optimizer's state is the moments of [*q1.parameters(), *q2.parameters()][j].
    params = [*agent.q1.parameters(), *agent.q2.parameters()]
    for j, param in enumerate(params):
        entry = old['critic_optimizer']['state'][j]
        for key in ('exp_avg', 'exp_avg_sq'):
            assert torch.equal(agent.critic_optimizer.state[param][key], entry[key])
        assert float(agent.critic_optimizer.state[param]['step']) == 2.0
    saved = agent.state_dict()['critic_optimizer']
    assert saved['param_groups'] == old['critic_optimizer']['param_groups']
    assert saved['state'].keys() == old['critic_optimizer']['state'].keys()
    for index, entry in old['critic_optimizer']['state'].items():
        for key, value in entry.items():
            assert torch.equal(saved['state'][index][key], value)


def _tensors(value) -> list[torch.Tensor]:
    if isinstance(value, torch.Tensor):
        return [value]
    if isinstance(value, dict):
        return [t for item in value.values() for t in _tensors(item)]
    if isinstance(value, (list, tuple)):
        return [t for item in value for t in _tensors(item)]
    return []


def test_checkpoints_hold_each_tensor_alone_and_training_resumes_bit_for_bit():
    config = SACConfig(hidden_sizes=HIDDEN)
    agent = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, seed=1)
    for seed in range(3):
        agent.update(_batch(seed, torch.float32))
    state = agent.state_dict()
    # Every tensor its own storage (the optimizers' step counts too, which AdamStep keeps
    # as views of one tensor), as torch.optim.Adam and nn.Module write them.
    for value in _tensors(state):
        assert value.is_contiguous() and value.untyped_storage().nbytes() == value.nbytes
    for name in ('actor_optimizer', 'critic_optimizer', 'alpha_optimizer'):
        assert all(float(entry['step']) == 3.0 for entry in state[name]['state'].values())
    resumed = SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), config, seed=9)
    resumed.load_state_dict(state)
    for seed in range(3, 6):
        assert agent.update(_batch(seed, torch.float32)) == resumed.update(
            _batch(seed, torch.float32))
    ours, theirs = agent.state_dict(), resumed.state_dict()
    for name in ('actor', *CRITICS, 'actor_optimizer', 'critic_optimizer', 'alpha_optimizer'):
        for a, b in zip(_tensors(ours[name]), _tensors(theirs[name]), strict=True):
            assert torch.equal(a, b)
    assert torch.equal(ours['log_alpha'], theirs['log_alpha'])

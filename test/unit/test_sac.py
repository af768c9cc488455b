"""SAC and its SAC-RCBF training modes: gradients through the layer, targets, learning."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rcbf_ros.learning.buffers import ReplayBuffer, TransitionBatch
from rcbf_ros.learning.model_based import ModelRollout, RolloutConfig
from rcbf_ros.learning.sac import polyak_update, SAC, SACConfig

OBS_DIM, STATE_DIM, N_U = 3, 2, 2
U_LOW, U_HIGH = -np.ones(N_U), np.ones(N_U)
HALF_PLANE_NORMAL = torch.tensor([1.0, 0.5])


def halfplane_projection_fixture(state: torch.Tensor, u_rl: torch.Tensor) -> torch.Tensor:
    """TEST FIXTURE standing in for the RCBF-QP layer: Euclidean projection of u onto the
    half-plane {u : n^T u <= b(x)}, b(x) = x_0 (state dependent, differentiable a.e.).

    Shapes: state (B, n_x), u_rl (B, n_u) -> u_safe (B, n_u).
    """
    normal = HALF_PLANE_NORMAL.to(u_rl.dtype)
    violation = torch.relu(u_rl @ normal - state[:, 0].to(u_rl.dtype))
    return u_rl - violation[:, None] * normal / (normal @ normal)


def detached_projection_fixture(state: torch.Tensor, u_rl: torch.Tensor) -> torch.Tensor:
    """TEST FIXTURE: the same projection with its output cut from the graph."""
    return halfplane_projection_fixture(state, u_rl).detach()


def identity_layer_fixture(state: torch.Tensor, u_rl: torch.Tensor) -> torch.Tensor:
    """TEST FIXTURE: a safety layer that never intervenes."""
    return u_rl


def random_batch(size: int, seed: int, dtype: torch.dtype = torch.float32) -> TransitionBatch:
    """A batch with the projection fixture's u_safe; b(x) = x_0 in [-0.5, 0.5] makes the
    constraint active for a good share of rows."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=dtype) * 2 - 1

    state, next_state = 0.5 * rand(size, STATE_DIM), 0.5 * rand(size, STATE_DIM)
    u_rl = rand(size, N_U)
    u_safe = halfplane_projection_fixture(state, u_rl)
    return TransitionBatch(obs=rand(size, OBS_DIM), state=state, u_rl=u_rl, u_safe=u_safe,
                           u_s=u_safe - u_rl, reward=rand(size), next_obs=rand(size, OBS_DIM),
                           next_state=next_state,
                           done=(torch.rand(size, generator=g) < 0.2).to(dtype))


def make_agent(mode: str, layer=halfplane_projection_fixture, seed: int = 0,
               dtype: torch.dtype = torch.float32, hidden=(32, 32), **config) -> SAC:
    return SAC(OBS_DIM, N_U, U_LOW, U_HIGH, SACConfig(mode=mode, hidden_sizes=hidden, **config),
               safety_layer=layer, seed=seed, dtype=dtype)


def actor_grad(agent: SAC, batch: TransitionBatch, noise: torch.Tensor) -> torch.Tensor:
    agent.actor.zero_grad()
    loss, _ = agent.actor_loss(batch, noise=noise)
    loss.backward()
    return torch.cat([p.grad.reshape(-1) for p in agent.actor.parameters()])


def test_diff_actor_gradient_flows_through_safety_layer_and_matches_finite_differences():
    dtype = torch.float64
    batch = random_batch(16, seed=0, dtype=dtype)
    noise = torch.randn(16, N_U, generator=torch.Generator().manual_seed(1), dtype=dtype)
    diff = make_agent('diff', dtype=dtype, hidden=(4,))
    detached = make_agent('diff', layer=detached_projection_fixture, dtype=dtype, hidden=(4,))
    sample = diff.actor(batch.obs, noise=noise).action
    active = (sample @ HALF_PLANE_NORMAL.double() > batch.state[:, 0])
    assert 0 < int(active.sum()) < 16  # the layer changes some actions but not all

    grad = actor_grad(diff, batch, noise)
    grad_detached = actor_grad(detached, batch, noise)
    assert (grad - grad_detached).abs().max() > 1e-3

    # Central finite differences of the loss in every actor parameter.
    eps = 1e-6
    fd = []
    with torch.no_grad():
        for param in diff.actor.parameters():
            flat = param.view(-1)
            for i in range(flat.numel()):
                original = float(flat[i])
                flat[i] = original + eps
                plus = float(diff.actor_loss(batch, noise=noise)[0])
                flat[i] = original - eps
                minus = float(diff.actor_loss(batch, noise=noise)[0])
                flat[i] = original
                fd.append((plus - minus) / (2 * eps))
    torch.testing.assert_close(grad, torch.tensor(fd, dtype=dtype), atol=1e-6, rtol=1e-5)


def test_modular_target_differs_from_diff_target_only_in_the_next_state_term():
    batch = random_batch(64, seed=2)
    noise = torch.randn(64, N_U, generator=torch.Generator().manual_seed(3))
    # Identity layer: the two targets coincide.
    diff_id = make_agent('diff', layer=identity_layer_fixture)
    modular_id = make_agent('modular', layer=identity_layer_fixture)
    assert torch.equal(diff_id.critic_target(batch, noise),
                       modular_id.critic_target(batch, noise))

    # Projection layer, modular without a layer (the paper's: u^S dropped): they differ by
    # gamma (1 - done) (min Q_bar(x', safe(a')) - min Q_bar(x', a')).
    diff = make_agent('diff')
    modular = make_agent('modular', layer=None)
    with torch.no_grad():
        next_action = diff.actor(batch.next_obs, noise=noise).action
        safe_next = halfplane_projection_fixture(batch.next_state, next_action)

        def min_target_q(action):
            return torch.minimum(diff.q1_target(batch.next_obs, action),
                                 diff.q2_target(batch.next_obs, action))

        expected = diff.config.gamma * (1 - batch.done) * (min_target_q(safe_next)
                                                           - min_target_q(next_action))
    difference = diff.critic_target(batch, noise) - modular.critic_target(batch, noise)
    torch.testing.assert_close(difference, expected, atol=1e-6, rtol=1e-5)
    assert (expected.abs() > 1e-5).sum() >= 5


def test_modular_with_an_envelope_layer_sees_its_correction_in_target_and_actor_loss():
    # The envelope's layer (the barriers of every layout) in modular mode: target and actor
    # loss as in diff with that layer, gradients through it; the critic stays at u*_t.
    batch = random_batch(32, seed=6)
    noise = torch.randn(32, N_U, generator=torch.Generator().manual_seed(7))
    diff, envelope, plain = make_agent('diff'), make_agent('modular'), make_agent('modular',
                                                                                  layer=None)
    torch.testing.assert_close(envelope.critic_target(batch, noise),
                               diff.critic_target(batch, noise))
    assert (envelope.critic_target(batch, noise)
            - plain.critic_target(batch, noise)).abs().max() > 1e-5
    torch.testing.assert_close(actor_grad(envelope, batch, noise), actor_grad(diff, batch, noise))
    difference = actor_grad(envelope, batch, noise) - actor_grad(plain, batch, noise)
    assert difference.abs().max() > 1e-6


@pytest.mark.parametrize(('mode', 'trained_on'), [
    ('unconstrained', 'u_rl'), ('baseline', 'u_rl'), ('baseline_compensator', 'u_rl'),
    ('diff', 'u_safe'), ('modular', 'u_safe')])
def test_critic_is_trained_at_the_mode_s_action(mode, trained_on):
    batch = random_batch(32, seed=4)
    noise = torch.randn(32, N_U, generator=torch.Generator().manual_seed(5))
    agent = make_agent(mode)
    other = 'u_safe' if trained_on == 'u_rl' else 'u_rl'
    loss = agent.critic_loss(batch, noise)[0]
    changed_other = batch._replace(**{other: getattr(batch, other) + 0.3})
    changed_own = batch._replace(**{trained_on: getattr(batch, trained_on) + 0.3})
    assert torch.equal(agent.critic_loss(changed_other, noise)[0], loss)
    assert not torch.equal(agent.critic_loss(changed_own, noise)[0], loss)


def bandit_return(agent: SAC, obs: np.ndarray) -> float:
    """Deterministic return of the 1-D task r = -(u + s)^2 (optimum u = -s)."""
    u = agent.act(obs, deterministic=True)[:, 0]
    return float(np.mean(-(u + obs[:, 0]) ** 2))


def test_plain_sac_learns_a_trivial_one_dimensional_task():
    rng = np.random.default_rng(0)
    agent = SAC(1, 1, [-1.0], [1.0], SACConfig(mode='unconstrained', hidden_sizes=(64, 64),
                                               actor_lr=1e-3, critic_lr=1e-3), seed=0)
    buffer = ReplayBuffer(5000, 1, 1, 1, seed=0)
    eval_obs = np.linspace(-0.9, 0.9, 19)[:, None]
    before = bandit_return(agent, eval_obs)
    for _ in range(400):
        obs = rng.uniform(-0.9, 0.9, size=(8, 1))
        u = agent.act(obs)
        reward = -(u[:, 0] + obs[:, 0]) ** 2
        # One-step episodes: done = 1, no bootstrapping.
        buffer.add(obs=obs, state=obs, u_rl=u, u_safe=u, u_s=np.zeros_like(u), reward=reward,
                   next_obs=obs, next_state=obs, done=np.ones(8))
        agent.update(buffer.sample(64))
    after = bandit_return(agent, eval_obs)
    assert after > before + 0.05
    assert after > -0.02


def test_same_seed_gives_bit_identical_parameters():
    def train(seed: int) -> list[torch.Tensor]:
        agent = make_agent('diff', seed=seed)
        buffer = ReplayBuffer(200, OBS_DIM, STATE_DIM, N_U, seed=seed)
        batch = random_batch(200, seed=7)
        buffer.add(**batch._asdict())
        for _ in range(15):
            agent.update(buffer.sample(32))
        return [p.detach().clone() for p in (*agent.actor.parameters(), *agent.q1.parameters(),
                                             *agent.q2_target.parameters(), agent.log_alpha)]

    first, second, other = train(3), train(3), train(4)
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    assert not all(torch.equal(a, b) for a, b in zip(first, other))


def test_compensator_learns_a_fixed_correction_and_is_added_when_acting():
    def correction(obs: torch.Tensor) -> torch.Tensor:
        return torch.stack([0.5 * obs[:, 0], torch.full_like(obs[:, 0], -0.3)], dim=1)

    agent = make_agent('baseline_compensator', hidden=(64, 64), compensator_lr=3e-3)
    buffer = ReplayBuffer(1000, OBS_DIM, STATE_DIM, N_U, seed=0)
    batch = random_batch(1000, seed=8)
    buffer.add(**batch._replace(u_s=correction(batch.obs))._asdict())
    test_obs = random_batch(200, seed=9).obs
    with torch.no_grad():
        initial_error = (agent.compensator(test_obs) - correction(test_obs)).pow(2).mean()
    for _ in range(300):
        metrics = agent.update(buffer.sample(64))
    with torch.no_grad():
        final_error = (agent.compensator(test_obs) - correction(test_obs)).pow(2).mean()
    assert 'compensator_loss' in metrics
    assert final_error < 0.1 * initial_error and final_error < 2e-3

    proposal = agent.act_detailed(test_obs.numpy(), deterministic=True)
    with torch.no_grad():
        expected = torch.clamp(torch.as_tensor(proposal.u_rl) + agent.compensator(test_obs),
                               -1.0, 1.0)
    np.testing.assert_allclose(proposal.u_proposed, expected.numpy(), atol=1e-6)
    assert not np.allclose(proposal.u_proposed, proposal.u_rl)


def test_act_returns_numpy_in_the_box_and_plain_modes_propose_u_rl():
    agent = make_agent('diff')
    obs = np.zeros(OBS_DIM)
    u = agent.act(obs)
    assert isinstance(u, np.ndarray) and u.shape == (N_U,)
    assert np.all(u >= -1.0) and np.all(u <= 1.0)
    proposal = agent.act_detailed(np.zeros((4, OBS_DIM)), deterministic=True)
    assert np.array_equal(proposal.u_proposed, proposal.u_rl)
    with pytest.raises(ValueError, match='obs'):
        agent.act(np.zeros(OBS_DIM + 1))


@pytest.mark.parametrize('mode, dtype', [('diff', torch.float32),
                                         ('baseline_compensator', torch.float64)])
def test_numpy_acting_path_matches_the_torch_actor_after_updates_and_a_reload(mode, dtype):
    """One observation is acted on in numpy, on views of the live weights: it must agree with
    the batched torch path (same generator draws) after optimizer steps and a load_state_dict,
    both of which change the weights in place."""
    agent = make_agent(mode, dtype=dtype)
    other = make_agent(mode, seed=5, dtype=dtype)
    for index in range(3):
        other.update(random_batch(64, seed=20 + index, dtype=dtype))
    observations = np.random.default_rng(0).uniform(-1, 1, (5, OBS_DIM))
    tol = 1e-5 if dtype == torch.float32 else 1e-12

    def compare() -> None:
        for deterministic in (True, False):
            state = agent.generator.get_state()
            one = [agent.act_detailed(obs, deterministic) for obs in observations]
            agent.generator.set_state(state)
            batched = [agent.act_detailed(obs[None], deterministic) for obs in observations]
            for a, b in zip(one, batched):
                np.testing.assert_allclose(a.u_rl, b.u_rl[0], rtol=0, atol=tol)
                np.testing.assert_allclose(a.u_proposed, b.u_proposed[0], rtol=0, atol=tol)

    compare()
    before = agent.act_detailed(observations[0], deterministic=True).u_rl
    agent.update(random_batch(64, seed=1, dtype=dtype))
    compare()
    agent.load_state_dict(other.state_dict())
    compare()
    after = agent.act_detailed(observations[0], deterministic=True).u_rl
    assert not np.allclose(before, after)       # the views did follow the new weights


def test_checkpoint_round_trip_gives_identical_next_update():
    batch = random_batch(64, seed=10)
    agent = make_agent('modular')
    agent.update(batch)
    restored = make_agent('modular', seed=123)
    restored.load_state_dict(agent.state_dict())
    assert agent.update(batch) == restored.update(batch)
    for a, b in zip(agent.actor.parameters(), restored.actor.parameters()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match='mode'):
        make_agent('diff').load_state_dict(agent.state_dict())


def test_polyak_update():
    source, target = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    expected = [0.1 * s + 0.9 * t for s, t in zip(source.parameters(), target.parameters())]
    polyak_update(source.parameters(), target.parameters(), 0.1)
    for e, t in zip(expected, target.parameters()):
        torch.testing.assert_close(t, e)
    with pytest.raises(ValueError, match='2 parameters, 1 targets'):
        polyak_update(source.parameters(), [target.weight], 0.1)


def test_bad_configuration_is_rejected_naming_the_field():
    with pytest.raises(ValueError, match='mode'):
        SACConfig(mode='safe')
    with pytest.raises(ValueError, match='gamma'):
        SACConfig(gamma=1.5)
    with pytest.raises(ValueError, match='safety_layer'):
        SAC(OBS_DIM, N_U, U_LOW, U_HIGH, SACConfig(mode='diff'))
    with pytest.raises(ValueError, match='u_low'):
        SAC(OBS_DIM, N_U, [-1.0], U_HIGH)


# ----------------------------------------------------------------- model-based rollouts
DT = 0.1
GOAL_BONUS = 1.0


def single_integrator_next_state(state: torch.Tensor, u_safe: torch.Tensor) -> torch.Tensor:
    """Stand-in for dynamics prior + GP mean: x' = x + dt u."""
    return state + DT * u_safe


def progress_reward(state, u_safe, next_state):
    """Progress toward the origin plus a goal bonus once inside radius 0.3."""
    reached = next_state.norm(dim=1) < 0.3
    reward = state.norm(dim=1) - next_state.norm(dim=1) + GOAL_BONUS * reached
    return reward, reached


def test_model_rollout_transitions_follow_the_model_and_count_the_goal_bonus_once():
    env_buffer = ReplayBuffer(100, OBS_DIM, STATE_DIM, N_U, seed=0)
    start = random_batch(100, seed=11)
    env_buffer.add(**start._replace(state=start.state * 0.8)._asdict())
    model_buffer = ReplayBuffer(10_000, OBS_DIM, STATE_DIM, N_U, seed=0)
    agent = make_agent('diff')

    def obs_fn(state):
        return torch.cat([state, state.norm(dim=1, keepdim=True)], dim=1)

    rollout = ModelRollout(predict_next_state=single_integrator_next_state,
                           reward_fn=progress_reward, obs_fn=obs_fn,
                           policy=agent.policy_action, safety_layer=halfplane_projection_fixture,
                           config=RolloutConfig(num_rollouts=50, horizon=4))
    added = rollout.run(env_buffer, model_buffer)
    assert added == len(model_buffer)
    data = model_buffer.gather(torch.arange(added))
    torch.testing.assert_close(data.next_state,
                               single_integrator_next_state(data.state, data.u_safe))
    torch.testing.assert_close(data.u_safe,
                               halfplane_projection_fixture(data.state, data.u_rl))
    torch.testing.assert_close(data.u_s, data.u_safe - data.u_rl)
    torch.testing.assert_close(data.obs, obs_fn(data.state))
    torch.testing.assert_close(data.next_obs, obs_fn(data.next_state))
    reward, reached = progress_reward(data.state, data.u_safe, data.next_state)
    torch.testing.assert_close(data.reward, reward)  # bonus counted once
    assert torch.equal(data.done, reached.float())
    assert bool(reached.any())  # the bonus case occurs
    # Rollouts end at the goal: 50 rows at step 1, then only unfinished ones continue.
    finished_first = int(reached[:50].sum())
    second_step = data.state[50:50 + 50 - finished_first]
    torch.testing.assert_close(second_step, data.next_state[:50][~reached[:50]])

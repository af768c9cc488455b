"""In-process training: every mode on every system runs safely, seeds reproduce, resume works."""
from __future__ import annotations

from dataclasses import replace
import json

import numpy as np
import pytest
import torch

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.envs import make_env
from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.build import RunConfig
from rcbf_ros.training.loop import train
from rcbf_ros.training.run_files import append_row, load_payload

SMALL = dict(start_steps=40, update_after=40, batch_size=32, gp_refit_interval=60,
             sac=SACConfig(hidden_sizes=(32, 32)))


def small_run(tmp_path, system: str, mode: str, *, episodes: int = 1, steps: int = 100,
              seed: int = 0, **extra) -> RunConfig:
    return RunConfig(system=system, episodes=episodes, max_steps=steps,
                     out_dir=str(tmp_path / f'{system}_{mode}_{seed}'), record_bag=False,
                     learner=LearnerConfig(mode=mode, seed=seed, **{**SMALL, **extra}))


@pytest.mark.parametrize('system', ['unicycle', 'car_following', 'pvtol'])
@pytest.mark.parametrize('mode', ['baseline', 'baseline_compensator', 'diff', 'modular'])
def test_every_mode_trains_without_safety_violations(tmp_path, system, mode):
    history = train(small_run(tmp_path, system, mode), log=lambda _: None)
    assert len(history) == 1 and history[0]['steps'] > 40
    assert history[0]['violations'] == 0
    assert history[0]['fail_safe'] == 0
    # SAC actually updated (metrics are only present after updates).
    assert any(k.startswith(('critic', 'actor', 'q')) for k in history[0]), history[0].keys()


def test_model_based_diff_adds_synthetic_transitions(tmp_path):
    from rcbf_ros.training.build import build_run
    run = small_run(tmp_path, 'unicycle', 'diff', model_based=True, rollout_interval=50,
                    rollouts=16, rollout_horizon=2)
    env, filt, learner, _ = build_run(run)
    from rcbf_ros.training.episodes import run_episode
    stats = run_episode(env, filt, learner, episode=0, seed=0)
    assert stats.violations == 0
    assert learner.model_buffer is not None and len(learner.model_buffer) > 0


def _filled_learner(tmp_path, system: str, mode: str, **extra):
    """A learner whose buffer and GP hold 120 random transitions of ``system``, GP fitted."""
    from rcbf_ros.training.build import build_run
    env, _, learner, _ = build_run(small_run(tmp_path, system, mode, **extra))
    rng = np.random.default_rng(5)
    obs, info = env.reset(seed=0)
    for _ in range(120):
        u = rng.uniform(learner.u_low, learner.u_high)
        next_obs, reward, terminated, truncated, next_info = env.step(u)
        learner.observe(obs=obs, state=info['state'], u_rl=u, u_safe=u, reward=reward,
                        next_obs=next_obs, next_state=next_info['state'], terminated=terminated)
        obs, info = next_obs, next_info
        if terminated or truncated:
            obs, info = env.reset()
    learner.gp.fit()
    return learner


@pytest.mark.parametrize('system, mode, extra', [
    ('car_following', 'diff', {}), ('pvtol', 'modular', {'modular_envelope': True}),
    ('unicycle', 'diff', {'model_based': True, 'rollouts': 16, 'rollout_horizon': 2})])
def test_the_losses_see_the_gp_estimate_memoised_per_transition_as_if_predicted_afresh(
        tmp_path, system, mode, extra):
    """The learner hands the losses the GP's estimate at each batch's states from the replay
    buffer's memo; an update with it equals one whose safety layer predicts the estimate
    itself, and after a refit the memo holds the new GP's estimate."""
    memo = _filled_learner(tmp_path / 'memo', system, mode, **extra)
    fresh = _filled_learner(tmp_path / 'fresh', system, mode, **extra)
    if memo.rollout is not None:
        for learner in (memo, fresh):
            learner.rollout.run(learner.buffer, learner.model_buffer)
    for _ in range(3):
        batch, estimate = memo.sample_batch()
        assert estimate is not None
        for states, at in ((batch.state, estimate.state), (batch.next_state, estimate.next_state)):
            mean, std = memo.disturbance(states.to(torch.float64))
            torch.testing.assert_close(at[:, 0], mean, rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(at[:, 1], std, rtol=1e-12, atol=1e-14)
        ours = memo.sac.update(batch, estimate)
        theirs = fresh.sac.update(*(fresh.sample_batch()[0], None))
        assert ours.keys() == theirs.keys()
        for key in ours:
            assert ours[key] == pytest.approx(theirs[key], rel=1e-6, abs=1e-9), key
    # A refit on more data: the memo's entries are stale and predicted again.
    memo.gp.add(torch.zeros(1, memo.system.n_x, dtype=torch.float64),
                torch.full((1, memo.system.n_x), 0.3, dtype=torch.float64))
    memo.gp.fit()
    batch, estimate = memo.sample_batch()
    mean, std = memo.disturbance(batch.state.to(torch.float64))
    torch.testing.assert_close(estimate.state[:, 0], mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(estimate.state[:, 1], std, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize('system, mode, extra', [
    ('unicycle', 'diff', {}), ('pvtol', 'modular', {'modular_envelope': True})])
def test_the_acting_path_fills_the_memo_with_its_own_estimate(tmp_path, system, mode, extra):
    """The GP estimate each action is proposed with goes into the losses' memo, for the state
    of the transition stored next and the next state of the one stored before: a transition
    whose next state was acted in is never predicted again, and the memo holds the GP's
    estimate at the true (float64) states, which the buffer stores in float32."""
    from rcbf_ros.training.build import build_run
    env, filt, learner, _ = build_run(small_run(tmp_path, system, mode, **extra))
    obs, info = env.reset(seed=0)
    rng = np.random.default_rng(5)
    for _ in range(60):  # data for a fit
        u = rng.uniform(learner.u_low, learner.u_high)
        next_obs, reward, terminated, truncated, next_info = env.step(u)
        learner.observe(obs=obs, state=info['state'], u_rl=u, u_safe=u, reward=reward,
                        next_obs=next_obs, next_state=next_info['state'], terminated=terminated)
        obs, info = next_obs, next_info
    learner.gp.fit()
    asked: list[torch.Tensor] = []
    predict = learner.disturbance
    learner.disturbance = lambda x: (asked.append(x), predict(x))[1]
    acted, episode_ends = [], []
    for step in range(25):
        proposal = learner.propose(obs, info['state'])
        u = filt.filter(info['state'], proposal.u_proposed, proposal.disturbance_mean,
                        proposal.disturbance_std).u_safe
        next_obs, reward, terminated, truncated, next_info = env.step(u)
        learner.observe(obs=obs, state=info['state'], u_rl=proposal.u_rl, u_safe=u,
                        reward=reward, next_obs=next_obs, next_state=next_info['state'],
                        terminated=terminated)
        acted.append((learner.buffer.newest, info['state'].copy(), next_info['state'].copy()))
        obs, info = next_obs, next_info
        if step in (11, 24) or terminated or truncated:  # the last's next state unacted
            episode_ends.append(learner.buffer.newest)
            obs, info = env.reset()
    slots = torch.tensor([slot for slot, _, _ in acted])
    estimate = learner.buffer.predictions(slots, version=learner.gp.version,
                                          predict=learner.disturbance)
    # Only the next states of the episodes' last transitions were never acted in.
    assert len(asked) == 1
    torch.testing.assert_close(asked[0], learner.buffer.gather(
        torch.tensor(episode_ends)).next_state.to(torch.float64), rtol=0, atol=0)
    for row, (slot, state, next_state) in enumerate(acted):
        halves = ((estimate.state, state),) + (
            () if slot in episode_ends else ((estimate.next_state, next_state),))
        for at, true_state in halves:
            mean, std = learner.gp.predict_state(true_state)
            np.testing.assert_allclose(at[row, 0].numpy(), mean, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(at[row, 1].numpy(), std, rtol=1e-12, atol=1e-14)
    # A refit between an action and its transition's store: its estimate is stale.
    proposal = learner.propose(obs, info['state'])
    learner.gp.fit()
    next_obs, reward, terminated, _, next_info = env.step(proposal.u_proposed)
    learner.observe(obs=obs, state=info['state'], u_rl=proposal.u_rl,
                    u_safe=proposal.u_proposed, reward=reward, next_obs=next_obs,
                    next_state=next_info['state'], terminated=terminated)
    newest = torch.tensor([learner.buffer.newest])
    refitted = learner.buffer.predictions(newest, version=learner.gp.version,
                                          predict=learner.disturbance)
    assert len(asked) == 2 and asked[1].shape[0] == 2  # both of its states, predicted anew
    mean, std = predict(learner.buffer.gather(newest).state.to(torch.float64))
    torch.testing.assert_close(refitted.state[:, 0], mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(refitted.state[:, 1], std, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize('system, mode, extra', [
    ('unicycle', 'diff', {}), ('pvtol', 'modular', {'modular_envelope': True}),
    ('car_following', 'baseline', {})])
def test_a_refit_in_the_schedule_fills_the_memo_of_every_stored_transition(tmp_path, system,
                                                                           mode, extra):
    """The refit ``after_step`` runs is followed by one pass over the buffer
    (``ReplayBuffer.fill_predictions``) when the losses pass a layer: the minibatches until
    the next refit predict nothing and read the refitted GP's estimate. Without a layer in
    the losses nothing is predicted."""
    from rcbf_ros.training.build import build_run
    env, _, learner, _ = build_run(small_run(tmp_path, system, mode, **extra))
    rng = np.random.default_rng(5)
    obs, info = env.reset(seed=0)
    for _ in range(SMALL['gp_refit_interval']):
        u = rng.uniform(learner.u_low, learner.u_high)
        next_obs, reward, terminated, truncated, next_info = env.step(u)
        learner.observe(obs=obs, state=info['state'], u_rl=u, u_safe=u, reward=reward,
                        next_obs=next_obs, next_state=next_info['state'], terminated=terminated)
        obs, info = next_obs, next_info
        if terminated or truncated:
            obs, info = env.reset()
    asked: list[torch.Tensor] = []
    predict = learner.disturbance
    learner.disturbance = lambda x: (asked.append(x), predict(x))[1]
    version = learner.gp.version
    learner.after_step()  # the refit, the pass, then an update
    assert learner.gp.version != version
    if not learner.sac.through_layer:
        assert not asked
        return
    assert 0 < sum(len(x) for x in asked) <= 2 * len(learner.buffer)
    asked.clear()
    for _ in range(3):
        batch, estimate = learner.sample_batch()
        assert not asked
        for at, states in ((estimate.state, batch.state),
                           (estimate.next_state, batch.next_state)):
            mean, std = predict(states.to(torch.float64))
            torch.testing.assert_close(at[:, 0], mean, rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(at[:, 1], std, rtol=1e-10, atol=1e-12)


def test_without_a_layer_in_the_losses_no_estimate_is_drawn(tmp_path):
    learner = _filled_learner(tmp_path, 'unicycle', 'baseline')
    assert learner.sample_batch()[1] is None


def test_modular_learner_keeps_the_envelope_layer_of_every_layout(tmp_path):
    """Modular SAC-RCBF drops the layout's correction from its losses but keeps the envelope's
    (PVTOL: tilt, thrust, arena; not the operator, ``layout: true`` in config/pvtol.yaml), as
    the authors' code does (``modular_envelope``, which config/pvtol.yaml turns on; False gives
    the paper's plain modular). The Unicycle has no envelope: plain modular either way."""
    from rcbf_ros.training.build import build_run
    from rcbf_ros.training.episodes import run_episode
    env, filt, learner, _ = build_run(small_run(tmp_path, 'pvtol', 'modular',
                                                modular_envelope=True))
    assert env.with_operator and 'operator_upper' in filt.problem.barrier_names
    assert learner.envelope_layer is not None
    assert learner.sac.safety_layer is learner.envelope_layer
    assert sorted(learner.envelope_layer.problem.barrier_names) == [
        'arena_x_lower', 'arena_x_upper', 'arena_y_lower', 'arena_y_upper', 'thrust', 'tilt']
    assert run_episode(env, filt, learner, episode=0, seed=0).violations == 0
    _, _, plain, _ = build_run(small_run(tmp_path, 'pvtol', 'modular', modular_envelope=False))
    assert plain.envelope_layer is None and plain.sac.safety_layer is None
    _, _, unicycle, _ = build_run(small_run(tmp_path, 'unicycle', 'modular',
                                            modular_envelope=True))
    assert unicycle.envelope_layer is None and unicycle.sac.safety_layer is None


def test_upper_bound_run_drops_the_layout_but_keeps_the_envelope(tmp_path):
    """``no_obstacles`` (the transfer upper bound): no obstacles, no PVTOL operator, and only the
    barriers that are not part of the layout stay filtered: PVTOL's tilt/thrust/arena envelope,
    nothing on the Unicycle. The unconstrained PVTOL learner used to fly away (returns of
    -3000 in its first 10 episodes) with no filter at all."""
    from rcbf_ros.training.build import build_run
    from rcbf_ros.training.episodes import run_episode
    env, filt, learner, _ = build_run(replace(small_run(tmp_path, 'pvtol', 'unconstrained'),
                                              no_obstacles=True))
    assert len(env.obstacles) == 0
    assert not env.with_operator and learner.system.n_x == 6
    assert filt is not None
    assert sorted(filt.problem.barrier_names) == [
        'arena_x_lower', 'arena_x_upper', 'arena_y_lower', 'arena_y_upper', 'thrust', 'tilt']
    stats = run_episode(env, filt, learner, episode=0, seed=0)
    assert stats.violations == 0 and stats.filter_active > 0  # random actions hit the envelope
    # Its transfer evaluation meets layouts with the operator: the drone's entries from its GP,
    # the operator's the prior.
    from rcbf_ros.experiments.evaluate import disturbance_estimate
    state = np.array([-4.5, 2.0, 0.1, 0.0, 0.05, 1.1, -4.4])
    mean, std = disturbance_estimate(learner, state, 'learned')
    gp_mean, gp_std = learner.disturbance(torch.as_tensor(state[:6]).unsqueeze(0))
    np.testing.assert_allclose(mean, [*gp_mean[0].numpy(), 0.0])
    np.testing.assert_allclose(std, [*gp_std[0].numpy(), learner.config.gp_prior_std])
    _, filt, _, _ = build_run(replace(small_run(tmp_path, 'unicycle', 'unconstrained'),
                                      no_obstacles=True))
    assert filt is None


def test_same_seed_same_result_and_resume_equals_uninterrupted(tmp_path):
    a = train(small_run(tmp_path / 'a', 'unicycle', 'modular', episodes=2, steps=80),
              log=lambda _: None)
    b = train(small_run(tmp_path / 'b', 'unicycle', 'modular', episodes=2, steps=80),
              log=lambda _: None)
    def strip(rows):
        return [{k: v for k, v in r.items() if 'wall' not in k and 'per_s' not in k}
                              for r in rows]  # noqa: E731
    assert strip(a) == strip(b)
    policy_a = load_payload(tmp_path / 'a' / 'unicycle_modular_0' / 'policy.pt')['actor']
    policy_b = load_payload(tmp_path / 'b' / 'unicycle_modular_0' / 'policy.pt')['actor']
    assert all(torch.equal(policy_a[k], policy_b[k]) for k in policy_a)
    # A different seed gives a different run (the test above could not fail otherwise).
    c = train(small_run(tmp_path / 'c', 'unicycle', 'modular', episodes=2, steps=80, seed=1),
              log=lambda _: None)
    assert strip(c) != strip(a)
    # Kill after one episode (simulated by a 1-episode run), resume to two: same as straight.
    first = small_run(tmp_path / 'r', 'unicycle', 'modular', episodes=1, steps=80)
    train(first, log=lambda _: None)
    metrics = tmp_path / 'r' / 'unicycle_modular_0' / 'metrics.jsonl'
    assert metrics.exists()
    with metrics.open('a') as stream:  # an episode finished after the last checkpoint
        stream.write(json.dumps({'episode': 1, 'ret': 0.0}) + '\n')
    resumed = train(RunConfig(**{**first.__dict__, 'episodes': 2, 'resume': True}),
                    log=lambda _: None)
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert [r['episode'] for r in rows] == [0, 1] and rows[1]['ret'] != 0.0
    # Equal up to float round-off (the GP's cached factorisation is recomputed on load).
    assert len(resumed) == 2
    for got, want in zip(strip(resumed), strip(a)):
        assert got.keys() == want.keys()
        for key, value in want.items():
            assert got[key] == pytest.approx(value, rel=1e-6, abs=1e-9), key


def test_a_run_builds_its_env_through_the_one_registry(tmp_path):
    """build_run takes the system by name or by the dotted path of its env class (with a
    config file) and builds the same run; an unknown one is refused naming ``system``."""
    from rcbf_ros.envs.unicycle import UnicycleEnv
    from rcbf_ros.training.build import build_run
    by_name = build_run(small_run(tmp_path, 'unicycle', 'modular'))
    by_path = build_run(replace(small_run(tmp_path, 'unicycle', 'modular'),
                                system='rcbf_ros.envs.unicycle.UnicycleEnv',
                                config_file='unicycle'))
    assert type(by_path[0]) is type(by_name[0]) is UnicycleEnv
    np.testing.assert_array_equal(by_path[0].state, by_name[0].state)
    assert by_path[1].problem.barrier_names == by_name[1].problem.barrier_names
    with pytest.raises(ValueError, match="^system: no simulator for 'segway'"):
        build_run(replace(small_run(tmp_path, 'unicycle', 'modular'), system='segway',
                          config_file='unicycle'))


class DenseSystem:
    """n_x = 7, n_u = 2 with every entry of f and g state-dependent (a test system)."""

    n_x, n_u, u_min, u_max = 7, 2, None, None

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(x) * 3.1

    def g(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([torch.cos(x), torch.exp(0.1 * x)], dim=-1)


def test_learner_models_are_the_core_euler_step_bit_for_bit(tmp_path):
    """The learner's model step (model-based rollouts) is core.dynamics.step_euler with the GP
    mean, and its GP residual subtracts core.dynamics.nominal_derivative: both the same
    floating-point operations, in the same order, as x + dt ((f + g u) + d)."""
    from rcbf_ros.core.dynamics import step_euler
    from rcbf_ros.training.build import build_run
    _, _, learner, _ = build_run(small_run(tmp_path, 'pvtol', 'diff'))
    system, dt = learner.system, learner.dt
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.normal(size=(32, system.n_x)))
    u = torch.as_tensor(rng.normal(size=(32, system.n_u)))
    learner.gp.add(x, torch.as_tensor(rng.normal(scale=0.1, size=(32, system.n_x))))
    learner.gp.fit()
    mean, _ = learner.disturbance(x)
    assert mean.abs().max() > 0
    rate = system.f(x) + (system.g(x) @ u.unsqueeze(-1)).squeeze(-1)
    by_hand = x + dt * (rate + mean)
    assert torch.equal(learner.predict_next_state(x, u), by_hand)
    # A drift and an input matrix that overlap in every entry make the order visible.
    dense = DenseSystem()
    dense_rate = dense.f(x) + (dense.g(x) @ u.unsqueeze(-1)).squeeze(-1)
    assert torch.equal(step_euler(dense, x, u, dt, mean), x + dt * (dense_rate + mean))
    obs = np.zeros(learner.sac.obs_dim)
    learner.observe(obs=obs, state=x[0].numpy(), u_rl=u[0].numpy(),
                    u_safe=u[0].numpy(), reward=0.0, next_obs=obs,
                    next_state=by_hand[0].numpy(), terminated=False)
    residual = learner.gp.state_dict()['y'][-1]
    assert torch.equal(residual, ((by_hand[0] - x[0]) / dt - rate[0]).to(residual.dtype))


@pytest.mark.parametrize('system', ['unicycle', 'pvtol'])
def test_reward_and_observation_models_match_the_env(system):
    env = make_env(system, load_params(find_config(system), 'simulator'))
    env.reset(seed=0)
    reward_fn, obs_fn = env.torch_models()
    rng = np.random.default_rng(0)
    for _ in range(20):
        state = env.state + rng.normal(0, 0.5, env.state.shape)
        state[:2] = rng.uniform(-2.5, 2.5, 2)
        u = rng.uniform(-1, 1, env.nominal_system.n_u)
        env._state = state.copy()
        np.testing.assert_allclose(obs_fn(torch.as_tensor(state)[None])[0].numpy(),
                                   env._observation(), rtol=1e-12, atol=1e-12)
        env._last_distance = float(np.linalg.norm(state[:2] - env.goal))
        next_state = state.copy()
        next_state[:2] += rng.normal(0, 0.05, 2)
        env._state = next_state.copy()
        r_env, reached_env = env._reward_and_goal(state, u)
        r_model, reached = reward_fn(torch.as_tensor(state)[None], torch.as_tensor(u)[None],
                                     torch.as_tensor(next_state)[None])
        assert r_model.item() == pytest.approx(r_env, abs=1e-12)
        assert bool(reached.item()) == reached_env


def test_cli_train_writes_metrics_plot_and_bag(tmp_path, capsys):
    out = tmp_path / 'cli'
    code = cli_main(['train', '--system', 'unicycle', '--mode', 'baseline', '--episodes', '1',
                     '--max-steps', '60', '--start-steps', '30', '--update-after', '30',
                     '--batch-size', '16', '--out', str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    summary = json.loads(printed[printed.index('\n{') + 1:])
    assert summary['safety_violations'] == 0 and summary['episodes'] == 1
    rows = [json.loads(line) for line in (out / 'metrics.jsonl').read_text().splitlines()]
    assert len(rows) == 1
    assert (out / 'reward_curve.png').stat().st_size > 1000
    from rosbags.highlevel import AnyReader
    bag = next(out.glob('bag_*'))
    with AnyReader([bag]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts['/cmd_safe'] == rows[0]['steps'] == counts['/state']


def test_cli_rejects_bad_learner_settings(capsys, tmp_path):
    assert cli_main(['train', '--mode', 'modular', '--model-based', '--episodes', '1']) == 2
    assert 'model_based' in capsys.readouterr().err
    assert cli_main(['train', '--config', str(tmp_path / 'missing.yaml'), '--episodes', '1',
                     '--out', str(tmp_path / 'a')]) == 2
    assert 'no such file' in capsys.readouterr().err
    assert cli_main(['train', '--episodes', '0', '--out', str(tmp_path / 'b')]) == 2
    assert 'episodes' in capsys.readouterr().err
    assert cli_main(['train', '--threads', '0', '--episodes', '1',
                     '--out', str(tmp_path / 'd')]) == 2
    assert 'threads: must be >= 1' in capsys.readouterr().err
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters:\n    system: unicycle\n    obstacles:\n'
                   '      x: [0.0, 1.0]\n      y: [0.0]\n      radius: [0.5, 0.5]\n')
    assert cli_main(['train', '--config', str(bad), '--episodes', '1',
                     '--out', str(tmp_path / 'c')]) == 2
    assert 'obstacles.y' in capsys.readouterr().err
    assert not (tmp_path / 'c').exists()  # nothing half-written
    assert cli_main(['train', '--initial-alpha', '0', '--episodes', '1',
                     '--out', str(tmp_path / 'e')]) == 2
    assert '--initial-alpha' in capsys.readouterr().err
    bad_alpha = tmp_path / 'bad_alpha.yaml'
    bad_alpha.write_text(find_config('unicycle').read_text().replace(
        'initial_alpha: 0.01', 'initial_alpha: -1.0'))
    assert cli_main(['train', '--config', str(bad_alpha), '--episodes', '1',
                     '--out', str(tmp_path / 'f')]) == 2
    assert 'learner.initial_alpha' in capsys.readouterr().err


def test_initial_alpha_and_random_start_come_from_the_config_unless_the_run_sets_them(tmp_path):
    from rcbf_ros.training.build import build_run, resolve_run
    assert load_params(find_config('unicycle'), 'learner')['initial_alpha'] == 0.01
    small = dict(episodes=1, max_steps=20, record_bag=False)
    for alpha, expected in ((None, 0.01), (0.3, 0.3)):
        run = RunConfig(out_dir=str(tmp_path / f'a{alpha}'), **small,
                        learner=LearnerConfig(sac=SACConfig(initial_alpha=alpha)))
        assert resolve_run(run).learner.sac.initial_alpha == expected
        _, _, learner, _ = build_run(run)
        assert float(learner.sac.alpha) == pytest.approx(expected)
        train(run, log=lambda line: None)
        written = json.loads((tmp_path / f'a{alpha}' / 'run_config.json').read_text())
        assert written['learner']['sac']['initial_alpha'] == expected  # the value used
    # No learner section at all: SAC's own default.
    bare = tmp_path / 'bare.yaml'
    bare.write_text(find_config('unicycle').read_text().replace('/learner:', '/other:'))
    run = RunConfig(config_file=str(bare), out_dir=str(tmp_path / 'bare'), **small)
    assert resolve_run(run).learner.sac.initial_alpha == 0.2
    # YAML 1.1 reads 1.0e-2 as a string: still the number; a bool is not one.
    for text, expected in (('1.0e-2', 0.01), ('true', None)):
        path = tmp_path / f'alpha_{text}.yaml'
        path.write_text(find_config('unicycle').read_text().replace(
            'initial_alpha: 0.01', f'initial_alpha: {text}'))
        run = RunConfig(config_file=str(path), out_dir=str(tmp_path / 'x'), **small)
        if expected is None:
            with pytest.raises(ValueError, match='learner.initial_alpha: expected a number'):
                resolve_run(run)
        else:
            assert resolve_run(run).learner.sac.initial_alpha == expected
    starts = set()
    for seed in range(4):
        run = RunConfig(out_dir=str(tmp_path / 'rs'), random_start=True, **small,
                        learner=LearnerConfig(seed=seed))
        env, _, _, _ = build_run(run)
        starts.add(tuple(np.round(env.reset(seed=seed)[0][:2], 6)))
    assert len(starts) > 1  # the packaged file says random_start: false
    env, _, _, _ = build_run(RunConfig(out_dir=str(tmp_path / 'fs'), **small))
    assert tuple(env.reset(seed=1)[0][:2]) == (-2.5, -2.5)


def test_sigterm_mid_run_keeps_checkpoint_metrics_and_bag(tmp_path):
    """A killed `rcbf_ros train` (SIGTERM) still leaves a resumable run behind."""
    import os
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / 'killed'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros', 'train', '--system', 'unicycle', '--mode',
         'baseline', '--episodes', '50', '--max-steps', '40', '--start-steps', '20',
         '--update-after', '20', '--batch-size', '16', '--out', str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, OMP_NUM_THREADS='1'))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        metrics = out / 'metrics.jsonl'
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, output
    done = len((out / 'metrics.jsonl').read_text().splitlines())
    assert 2 <= done < 50
    checkpoint = load_payload(out / 'checkpoint.pt')
    assert checkpoint['episode'] == done
    assert (out / 'policy.pt').exists() and (out / 'reward_curve.png').exists()
    from rosbags.highlevel import AnyReader
    with AnyReader([next(out.glob('bag_*'))]) as reader:
        assert sum(c.msgcount for c in reader.connections if c.topic == '/cmd_safe') >= 80


def test_an_interrupt_between_an_episodes_row_and_its_line_loses_neither(tmp_path, monkeypatch):
    """Ctrl-C after an episode's row joined the history but before the metrics file got it:
    the file, the checkpoint's counter and its history still agree."""
    import rcbf_ros.training.run as run_module
    calls = []

    def interrupted_append(path, row):
        calls.append(row)
        if len(calls) == 2:
            raise KeyboardInterrupt
        append_row(path, row)

    monkeypatch.setattr(run_module, 'append_row', interrupted_append)
    run = small_run(tmp_path, 'unicycle', 'baseline', episodes=4, steps=30)
    with pytest.raises(KeyboardInterrupt):
        train(run, log=lambda _: None)
    out = tmp_path / 'unicycle_baseline_0'
    lines = (out / 'metrics.jsonl').read_text().splitlines()
    checkpoint = load_payload(out / 'checkpoint.pt')
    assert len(lines) == checkpoint['episode'] == len(checkpoint['history']) == 2
    assert [json.loads(line)['episode'] for line in lines] == [
        row['episode'] for row in checkpoint['history']]


def test_an_interrupt_during_the_finish_still_closes_the_bag(tmp_path, monkeypatch):
    """A signal that lands while the run finishes (its pictures take a while under load) still
    leaves a closed bag: every step's command is counted in its summary."""
    import rcbf_ros.training.loop as loop_module

    def interrupted_pictures(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(loop_module, 'draw_reward_curve', interrupted_pictures)
    run = replace(small_run(tmp_path, 'unicycle', 'baseline', episodes=2, steps=30),
                  record_bag=True)
    with pytest.raises(KeyboardInterrupt):
        train(run, log=lambda _: None)
    from rosbags.highlevel import AnyReader
    with AnyReader([tmp_path / 'unicycle_baseline_0' / 'bag_0000']) as reader:
        assert sum(c.msgcount for c in reader.connections if c.topic == '/cmd_safe') == 60


def test_train_cli_modular_envelope_flag_reaches_the_learner_config():
    import argparse

    from rcbf_ros.cli.train import add_train_arguments, settings_from_arguments
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)

    def envelope(*argv: str) -> bool | None:
        return settings_from_arguments(parser.parse_args(argv)).run_config().learner \
            .modular_envelope

    assert envelope('--modular-envelope') is True
    assert envelope('--no-modular-envelope') is False
    assert envelope() is None  # left to the config file's /learner section
    assert not LearnerConfig().modular_envelope  # the paper's modular by default


def test_the_train_cli_builds_its_options_and_defaults_from_the_run_settings():
    """``rcbf_ros train`` without options is TrainingSettings(), and every option sets the
    field of its name: the defaults are written once."""
    import argparse
    from dataclasses import fields

    from rcbf_ros.cli.train import add_train_arguments, OPTIONS, settings_from_arguments
    from rcbf_ros.learning.sac import MODES
    from rcbf_ros.training.settings import MODES as SETTING_MODES
    from rcbf_ros.training.settings import TrainingSettings
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert settings_from_arguments(parser.parse_args([])) == TrainingSettings()
    assert {name for name, _, _ in OPTIONS} <= {f.name for f in fields(TrainingSettings)}
    given = settings_from_arguments(parser.parse_args([
        '--system', 'pvtol', '--mode', 'diff', '--model-based', '--seed', '3',
        '--episodes', '7', '--max-steps', '9', '--config', 'c.yaml', '--out', 'o',
        '--no-obstacles', '--no-bag', '--resume', '--checkpoint-every', '2',
        '--compile-filter', '--compile-update', '--threads', '2', '--random-start',
        '--initial-alpha', '0.5', '--start-steps', '11', '--update-after', '12',
        '--batch-size', '13', '--gp-refit-interval', '14', '--no-modular-envelope']))
    assert given == TrainingSettings(
        system='pvtol', mode='diff', model_based=True, seed=3, episodes=7, max_steps=9,
        config_file='c.yaml', out_dir='o', no_obstacles=True, record_bag=False, resume=True,
        checkpoint_every=2, compile_filter=True, compile_update=True, threads=2,
        random_start=True, initial_alpha=0.5, start_steps=11, update_after=12, batch_size=13,
        gp_refit_interval=14, modular_envelope=False)
    run = given.run_config()
    assert (run.learner.sac.initial_alpha, run.learner.sac.compile_update) == (0.5, True)
    assert (run.learner.batch_size, run.learner.gp_refit_interval) == (13, 14)
    assert TrainingSettings().run_config().out_dir == 'runs/unicycle_modular_s0'
    assert SETTING_MODES == MODES


def test_episode_metrics_hold_the_critics_first_value_and_the_discounted_return(tmp_path):
    """q_start is min(Q1, Q2) at the first step's trained-at action (u* in modular), and
    disc_return the discounted sum of the rewards the bag recorded (read back by rosbags)."""
    from rosbags.highlevel import AnyReader

    from rcbf_ros.experiments.evaluate import load_trained_learner
    # No update before the episode ends: the checkpoint's critics are the ones of step 0.
    run = replace(small_run(tmp_path, 'pvtol', 'modular', steps=60, update_after=1000),
                  record_bag=True)
    row = train(run, log=lambda _: None)[0]
    with AnyReader([next((tmp_path / 'pvtol_modular_0').glob('bag_*'))]) as reader:
        rewards = [reader.deserialize(raw, c.msgtype).data for c, _, raw in
                   reader.messages([c for c in reader.connections if c.topic == '/reward'])]
    assert len(rewards) == row['steps'] == 60
    assert row['disc_return'] == pytest.approx(sum(0.99 ** t * r for t, r in enumerate(rewards)),
                                               rel=1e-12, abs=1e-15)
    _, learner = load_trained_learner(tmp_path / 'pvtol_modular_0')
    first = learner.buffer.state_dict()['data']
    obs, u_rl, u_safe = (torch.as_tensor(first[k][:1]).double() for k in ('obs', 'u_rl', 'u_safe'))
    assert not torch.allclose(u_rl, u_safe)  # the filter corrected the first proposal
    sac = learner.sac
    at_safe = torch.minimum(sac.q1(obs.to(sac.dtype), u_safe.to(sac.dtype)),
                            sac.q2(obs.to(sac.dtype), u_safe.to(sac.dtype)))
    assert row['q_start'] == pytest.approx(float(at_safe), rel=1e-6)


def test_unicycle_policy_proposes_forward_speeds_only(tmp_path):
    """config/unicycle.yaml's policy box: every proposal (warm-up draws, stochastic and
    deterministic policy) has v >= 0; the filter may still reverse. The box is written to
    run_config.json and used again when the policy is evaluated."""
    from rcbf_ros.experiments.evaluate import load_trained_learner, run_config_from_json
    from rcbf_ros.training.build import build_run, resolve_run
    section = load_params(find_config('unicycle'), 'learner')
    assert section['policy_limits.min'] == [0.0, -2.5]
    run = small_run(tmp_path, 'unicycle', 'modular', steps=120)
    assert resolve_run(run).learner.policy_min == (0.0, -2.5)
    train(run, log=lambda line: None)
    written = json.loads((tmp_path / 'unicycle_modular_0' / 'run_config.json').read_text())
    assert written['learner']['policy_min'] == [0.0, -2.5]
    assert written['learner']['policy_max'] == [2.5, 2.5]
    _, learner = load_trained_learner(tmp_path / 'unicycle_modular_0')
    np.testing.assert_array_equal(learner.u_low, [0.0, -2.5])
    assert learner.config.policy_min == (0.0, -2.5)
    rng = np.random.default_rng(0)
    state = np.array([0.5, -1.0, 0.3])
    env, _, _, _ = build_run(run)
    obs, _ = env.reset(seed=0)
    for deterministic in (False, True):
        speeds = [learner.sac.act(obs + rng.normal(0, 0.5, obs.shape),
                                  deterministic=deterministic)[0] for _ in range(200)]
        assert min(speeds) >= 0.0 and max(speeds) <= 2.5
    warm = build_run(run)[2]  # a fresh learner: env_steps 0, uniform warm-up draws
    draws = np.array([warm.propose(obs, state).u_rl for _ in range(300)])
    assert draws[:, 0].min() >= 0.0 and draws[:, 0].max() > 2.0
    assert draws[:, 1].min() < -2.0  # the turn rate keeps both signs
    one_input = replace(run, learner=replace(run.learner, policy_min=(0.0,), policy_max=(1.0,)))
    with pytest.raises(ValueError, match='policy_limits.min: expected 2 values'):
        build_run(one_input)
    # Without the section: the input limits, as before; a run written before the box
    # existed (no policy_min in its json) is rebuilt with them too.
    bare = tmp_path / 'bare.yaml'
    bare.write_text(find_config('unicycle').read_text().replace('/learner:', '/other:'))
    assert resolve_run(replace(run, config_file=str(bare))).learner.policy_min == ()
    legacy = dict(written)
    legacy['learner'] = {k: v for k, v in written['learner'].items()
                         if k not in ('policy_min', 'policy_max')}
    assert run_config_from_json(legacy).learner.policy_min == ()


@pytest.mark.parametrize('low, high, match', [
    ((0.0,), (2.5, 2.5), 'policy_limits'), ((0.0, -2.5), None, 'policy_limits'),
    ((2.5, -2.5), (2.5, 2.5), 'must be < max')])
def test_bad_policy_limits_name_the_key(low, high, match):
    with pytest.raises(ValueError, match=match):
        LearnerConfig(policy_min=low, policy_max=high)


def test_modular_envelope_comes_from_the_config_unless_the_run_sets_it(tmp_path):
    """config/pvtol.yaml's /learner modular_envelope makes `rcbf_ros train --mode modular` on
    PVTOL train the advised variant, as the learner node (which reads that section) does."""
    from rcbf_ros.training.build import build_run, resolve_run
    assert load_params(find_config('pvtol'), 'learner')['modular_envelope'] is True
    small = dict(episodes=1, max_steps=20, record_bag=False, out_dir=str(tmp_path / 'r'))
    cases = (('pvtol', None, True), ('pvtol', False, False), ('unicycle', None, False),
             ('unicycle', True, True))
    for system, given, expected in cases:
        run = RunConfig(system=system, **small,
                        learner=LearnerConfig(mode='modular', modular_envelope=given))
        assert resolve_run(run).learner.modular_envelope is expected, (system, given)
    _, _, learner, _ = build_run(RunConfig(system='pvtol', **small,
                                           learner=LearnerConfig(mode='modular')))
    assert learner.envelope_layer is not None
    assert learner.sac.safety_layer is learner.envelope_layer
    bad = tmp_path / 'bad.yaml'
    bad.write_text(find_config('pvtol').read_text().replace('modular_envelope: true',
                                                            'modular_envelope: 1'))
    with pytest.raises(ValueError, match='learner.modular_envelope: expected true or false'):
        resolve_run(RunConfig(system='pvtol', config_file=str(bad), **small,
                              learner=LearnerConfig(mode='modular')))

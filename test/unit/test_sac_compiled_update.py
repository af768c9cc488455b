"""SACConfig.compile_update: the functional update is SAC.update up to float32 round-off,
without a safety layer in the losses and through the real RCBF layer of a shipped config.

The fast tests run the functional update with torch.compile replaced by the identity (the same
functions the compiler gets); the slow tests compile them for real.
"""
from __future__ import annotations

from dataclasses import replace
import json

import numpy as np
import pytest
from sac_batches import N_U, OBS, random_batches
import torch
from torch._dynamo.utils import counters

from rcbf_ros.learning.buffers import BatchDisturbance, TransitionBatch
from rcbf_ros.learning.compiled_update import _Graph
from rcbf_ros.learning.sac import SAC, SACConfig


def _agent(compiled: bool, mode: str = 'baseline', seed: int = 3, **config) -> SAC:
    return SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U),
               SACConfig(mode=mode, hidden_sizes=(16, 16), compile_update=compiled, **config),
               seed=seed)


def _difference(a: SAC, b: SAC) -> float:
    worst = float((a.log_alpha.detach() - b.log_alpha.detach()).abs())
    for name in ('actor', 'q1', 'q2', 'q1_target', 'q2_target', 'compensator'):
        if getattr(a, name) is None:
            continue
        for p, q in zip(getattr(a, name).parameters(), getattr(b, name).parameters()):
            worst = max(worst, float((p.detach() - q.detach()).abs().max()))
    return worst


@pytest.fixture
def no_compiler(monkeypatch: pytest.MonkeyPatch) -> None:
    """torch.compile as the identity: the functional update runs as written."""
    monkeypatch.setattr(torch, 'compile', lambda function, **_: function)


@pytest.mark.parametrize('mode, config', [
    ('baseline', {}),
    ('baseline', {'target_update_interval': 2}),
    ('unconstrained', {'autotune_alpha': False}),
    ('modular', {}),  # no envelope layer: the critics are trained at u_safe
    ('baseline_compensator', {}),
])
def test_functional_update_is_sac_update_to_round_off(no_compiler, mode, config):
    eager, functional = _agent(False, mode, **config), _agent(True, mode, **config)
    for batch in random_batches(5):
        expected, got = eager.update(batch), functional.update(batch)
        assert sorted(got) == sorted(expected)
        assert all(abs(got[key] - expected[key]) < 1e-5 for key in expected)
        assert _difference(eager, functional) < 1e-6
    assert functional.num_updates == eager.num_updates == 5
    # The Adam state is kept where torch.optim.Adam keeps it, step count included.
    param = next(functional.actor.parameters())
    assert float(functional.actor_optimizer.state[param]['step']) == 5.0


def test_equal_seeds_give_bit_identical_functional_updates(no_compiler):
    def train(seed: int) -> list[torch.Tensor]:
        agent = _agent(True, seed=seed)
        for batch in random_batches(4):
            agent.update(batch)
        return [p.detach().clone() for p in (*agent.actor.parameters(),
                                             *agent.q2_target.parameters(), agent.log_alpha)]

    first, second, other = train(3), train(3), train(4)
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    assert not all(torch.equal(a, b) for a, b in zip(first, other))


def test_checkpoints_pass_between_the_compiled_and_the_eager_update(no_compiler):
    batches = random_batches(4)
    compiled, eager = _agent(True), _agent(False, seed=9)
    compiled.update(batches[0])
    eager.load_state_dict(compiled.state_dict())
    eager.update(batches[1])
    # Loading replaces the optimizers' state tensors: the functional update must bind the new
    # ones, else it would step the old moments and drift from the eager agent.
    compiled.load_state_dict(eager.state_dict())
    reference = _agent(False, seed=9)
    reference.load_state_dict(eager.state_dict())
    for batch in batches[2:]:
        compiled.update(batch)
        reference.update(batch)
    assert _difference(compiled, reference) < 1e-6


@pytest.mark.slow
def test_compiled_update_agrees_with_the_eager_update_and_repeats_itself_exactly():
    eager, compiled, again = _agent(False), _agent(True), _agent(True)
    for batch in random_batches(3):
        expected, got = eager.update(batch), compiled.update(batch)
        assert all(abs(got[key] - expected[key]) < 1e-5 for key in expected)
        assert again.update(batch) == got
    assert _difference(eager, compiled) < 1e-6
    assert _difference(compiled, again) == 0.0


# ------------------------------------------------------------------ through the safety layer
Draw = tuple[TransitionBatch, BatchDisturbance]


def _filled_learner(tmp_path, system: str, mode: str, **extra):
    """A learner of ``system`` whose buffer and GP hold 150 random transitions (GP fitted),
    with 32x32 networks: its safety layer is the one training passes the losses through."""
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import build_run, RunConfig
    learner_cfg = LearnerConfig(mode=mode, seed=0, start_steps=40, update_after=40,
                                batch_size=32, gp_refit_interval=60,
                                sac=SACConfig(hidden_sizes=(32, 32)), **extra)
    env, _, learner, _ = build_run(RunConfig(system=system, episodes=1, max_steps=100,
                                             out_dir=str(tmp_path / 'run'), record_bag=False,
                                             learner=learner_cfg))
    rng = np.random.default_rng(5)
    obs, info = env.reset(seed=0)
    for _ in range(150):
        u = rng.uniform(learner.u_low, learner.u_high)
        next_obs, reward, terminated, truncated, next_info = env.step(u)
        learner.observe(obs=obs, state=info['state'], u_rl=u, u_safe=u, reward=reward,
                        next_obs=next_obs, next_state=next_info['state'], terminated=terminated)
        obs, info = next_obs, next_info
        if terminated or truncated:
            obs, info = env.reset()
    learner.gp.fit()
    assert learner.sac.through_layer
    return learner


LAYERS = {'unicycle/diff': ('unicycle', 'diff', {}),
          'pvtol/modular': ('pvtol', 'modular', {'modular_envelope': True}),
          'car_following/diff': ('car_following', 'diff', {})}


@pytest.fixture(scope='module')
def learners(tmp_path_factory) -> dict:
    """One filled learner per entry of LAYERS, and 6 minibatches of each with the buffer's
    memoised disturbance estimate."""
    out = {}
    for name, (system, mode, extra) in LAYERS.items():
        learner = _filled_learner(tmp_path_factory.mktemp(name.replace('/', '_')), system,
                                  mode, **extra)
        out[name] = (learner, [learner.sample_batch() for _ in range(6)])
    return out


def _layer_agent(learner, compiled: bool, *, seed: int = 3, dtype=torch.float32,
                 **config) -> SAC:
    sac = learner.sac
    return SAC(sac.obs_dim, sac.n_u, sac.u_low, sac.u_high,
               replace(sac.config, compile_update=compiled, **config),
               safety_layer=sac.safety_layer, seed=seed, dtype=dtype)


def _assert_the_layer_acts(agent: SAC, draws: list[Draw]) -> None:
    """The policy's samples meet active QP rows in every minibatch: the layer changes the
    action (and its Jacobian is not the identity) for some of them."""
    for batch, estimate in draws:
        with torch.no_grad():
            sample = agent.actor(batch.obs.to(agent.dtype), generator=torch.Generator())
            safe = agent._safe_action(batch.state.to(agent.dtype), sample.action,
                                      estimate.state)
        assert int(((safe - sample.action).abs().amax(-1) > 1e-4).sum()) >= 2


def _metrics_close(got: dict, expected: dict, rel: float) -> bool:
    return sorted(got) == sorted(expected) and all(
        abs(got[key] - expected[key]) <= rel * (1.0 + abs(expected[key])) for key in expected)


@pytest.mark.parametrize('name', list(LAYERS))
@pytest.mark.parametrize('dtype, rel, tolerance', [(torch.float64, 1e-13, 1e-13),
                                                   (torch.float32, 1e-5, 1e-6)])
def test_through_the_layer_the_functional_update_is_sac_update(no_compiler, learners, name,
                                                               dtype, rel, tolerance):
    """In float64 the functional update through the real RCBF layer is SAC.update to float64
    round-off (the same math, only the order of operations differs); in float32 (training's
    dtype) to float32 round-off. Both see the buffer's memoised disturbance estimate."""
    learner, draws = learners[name]
    eager, functional = (_layer_agent(learner, compiled, dtype=dtype)
                         for compiled in (False, True))
    _assert_the_layer_acts(eager, draws)
    for batch, estimate in draws[:4]:
        expected, got = eager.update(batch, estimate), functional.update(batch, estimate)
        assert _metrics_close(got, expected, rel), (got, expected)
        assert _difference(eager, functional) < tolerance
    assert functional.num_updates == eager.num_updates == 4
    param = next(functional.actor.parameters())
    assert float(functional.actor_optimizer.state[param]['step']) == 4.0


@pytest.mark.parametrize('config', [{'target_update_interval': 2}, {'autotune_alpha': False}])
def test_through_the_layer_without_an_estimate_and_other_settings(no_compiler, learners,
                                                                  config):
    """The layer predicting the estimate itself (no memo), the Polyak step every second
    update, a fixed alpha: still SAC.update (float64)."""
    learner, draws = learners['unicycle/diff']
    eager, functional = (_layer_agent(learner, compiled, dtype=torch.float64, **config)
                         for compiled in (False, True))
    for batch, _ in draws[:4]:
        expected, got = eager.update(batch), functional.update(batch)
        assert _metrics_close(got, expected, 1e-13), (got, expected)
        assert _difference(eager, functional) < 1e-13


def test_through_the_layer_checkpoints_pass_between_the_compiled_and_the_eager_update(
        no_compiler, learners):
    learner, draws = learners['pvtol/modular']
    compiled, eager = _layer_agent(learner, True), _layer_agent(learner, False, seed=9)
    compiled.update(*draws[0])
    eager.load_state_dict(compiled.state_dict())
    eager.update(*draws[1])
    compiled.load_state_dict(eager.state_dict())
    reference = _layer_agent(learner, False, seed=9)
    reference.load_state_dict(eager.state_dict())
    for draw in draws[2:]:
        compiled.update(*draw)
        reference.update(*draw)
    assert _difference(compiled, reference) < 1e-6


def test_a_graph_that_would_compile_again_stops_with_one_line():
    graph = _Graph(lambda x: torch.sin(x) * 2.0, 'the test graph', compile_=True, mode=None)
    first = torch.linspace(0.0, 1.0, 5)
    torch.testing.assert_close(graph(None, first), torch.sin(first) * 2.0)
    graph(None, first + 1.0)  # the same shape: no compile
    with pytest.raises(RuntimeError, match='^compile_update: the test graph compiled again '
                                           r'at a later update \(an input changed'):
        graph(None, torch.zeros(7))
    # A variant of its own compiles once, too.
    graph('other', torch.zeros(7))


def test_a_graph_that_does_not_compile_stops_with_one_line():
    def breaks(x: torch.Tensor) -> torch.Tensor:
        torch._dynamo.graph_break()
        return x + 1.0

    graph = _Graph(breaks, 'the test graph', compile_=True, mode=None)
    with pytest.raises(RuntimeError) as caught:
        graph(None, torch.zeros(3))
    message = str(caught.value)
    assert message.startswith('compile_update: the test graph does not compile (')
    assert message.endswith('; set it false') and '\n' not in message


@pytest.mark.slow
@pytest.mark.parametrize('name', ['unicycle/diff', 'pvtol/modular'])
def test_compiled_update_through_the_layer_agrees_compiles_once_and_repeats_itself(learners,
                                                                                  name):
    learner, draws = learners[name]
    eager, compiled, again = (_layer_agent(learner, c) for c in (False, True, True))
    graphs = []
    for batch, estimate in draws[:4]:
        expected, got = eager.update(batch, estimate), compiled.update(batch, estimate)
        assert _metrics_close(got, expected, 1e-5), (got, expected)
        graphs.append(counters['stats']['unique_graphs'])
        assert again.update(batch, estimate) == got
    # The first update compiled the three graphs; none compiled since (the second agent's
    # equal constants reuse them).
    assert graphs[0] >= 3 and graphs[1:] == [graphs[0]] * 3
    assert _difference(eager, compiled) < 1e-6
    assert _difference(compiled, again) == 0.0
    # A checkpoint replaces the optimizers' state: the update binds it without compiling.
    compiled.load_state_dict(eager.state_dict())
    expected, got = eager.update(*draws[4]), compiled.update(*draws[4])
    assert _metrics_close(got, expected, 1e-5)
    assert counters['stats']['unique_graphs'] == graphs[0]
    # A minibatch of another size would compile again: refused in one line.
    batch, estimate = draws[5]
    with pytest.raises(RuntimeError, match='^compile_update: the policy samples compiled '
                                           'again'):
        compiled.update(TransitionBatch(*(t[:16] for t in batch)),
                        BatchDisturbance(*(t[:16] for t in estimate)))


@pytest.mark.slow
def test_cli_trains_diff_with_the_compiled_update(tmp_path, capsys):
    from rcbf_ros.cli.main import main as cli_main
    out = tmp_path / 'run'
    assert cli_main(['train', '--system', 'unicycle', '--mode', 'diff', '--compile-update',
                     '--episodes', '1', '--max-steps', '60', '--start-steps', '30',
                     '--update-after', '30', '--batch-size', '32', '--no-bag',
                     '--out', str(out)]) == 0
    assert '"safety_violations": 0' in capsys.readouterr().out
    row = json.loads((out / 'metrics.jsonl').read_text().splitlines()[-1])
    assert row['steps'] == 60 and np.isfinite(row['actor_loss'])  # the compiled update ran

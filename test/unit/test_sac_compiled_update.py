"""SACConfig.compile_update: the functional update is SAC.update up to float32 round-off.

The fast tests run the functional update with torch.compile replaced by the identity (the same
function the compiler gets); one slow test compiles it for real.
"""
from __future__ import annotations

import numpy as np
import pytest
from sac_batches import N_U, OBS, random_batches
import torch

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


def test_compile_update_is_refused_where_the_losses_pass_a_safety_layer():
    with pytest.raises(ValueError, match="compile_update: mode 'diff'"):
        SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U), SACConfig(mode='diff', compile_update=True),
            safety_layer=lambda state, u: u)
    with pytest.raises(ValueError, match="compile_update: mode 'modular'"):
        SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U),
            SACConfig(mode='modular', compile_update=True), safety_layer=lambda state, u: u)


@pytest.mark.slow
def test_compiled_update_agrees_with_the_eager_update_and_repeats_itself_exactly():
    eager, compiled, again = _agent(False), _agent(True), _agent(True)
    for batch in random_batches(3):
        expected, got = eager.update(batch), compiled.update(batch)
        assert all(abs(got[key] - expected[key]) < 1e-5 for key in expected)
        assert again.update(batch) == got
    assert _difference(eager, compiled) < 1e-6
    assert _difference(compiled, again) == 0.0

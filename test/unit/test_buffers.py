"""ReplayBuffer: circular storage, seeded sampling, checkpoints, clear errors."""
from __future__ import annotations

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.learning.buffers import ReplayBuffer, TransitionBatch
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig


def add_numbered(buffer: ReplayBuffer, start: int, count: int) -> None:
    """Transitions whose every field encodes their index i (reward = i)."""
    index = torch.arange(start, start + count, dtype=torch.float32)
    buffer.add(obs=index[:, None].repeat(1, 3), state=-index[:, None].repeat(1, 2),
               u_rl=index[:, None], u_safe=index[:, None] + 0.5, u_s=torch.full((count, 1), 0.5),
               reward=index, next_obs=index[:, None].repeat(1, 3) + 1,
               next_state=-index[:, None].repeat(1, 2) - 1, done=(index % 2 == 0))


def test_single_and_batched_add_and_field_alignment():
    buffer = ReplayBuffer(10, 3, 2, 1)
    buffer.add(obs=np.zeros(3), state=np.zeros(2), u_rl=[0.1], u_safe=[0.3], u_s=[0.2],
               reward=1.5, next_obs=np.ones(3), next_state=np.ones(2), done=True)
    add_numbered(buffer, 1, 4)
    assert len(buffer) == 5
    batch = buffer.gather(torch.arange(5))
    assert isinstance(batch, TransitionBatch)
    assert batch.obs.shape == (5, 3) and batch.state.shape == (5, 2)
    assert batch.reward.shape == (5,) and batch.done.shape == (5,)
    assert batch.reward.tolist() == [1.5, 1.0, 2.0, 3.0, 4.0]
    assert batch.done.tolist() == [1.0, 0.0, 1.0, 0.0, 1.0]
    torch.testing.assert_close(batch.u_s[0], torch.tensor([0.2]))
    # Every field of a sampled row belongs to the same transition.
    sample = buffer.sample(64)
    rows = sample.reward != 1.5  # the numbered ones
    torch.testing.assert_close(sample.obs[rows, 0], sample.reward[rows])
    torch.testing.assert_close(sample.next_state[rows, 1], -sample.reward[rows] - 1)


def test_circular_overwrite_keeps_the_newest():
    buffer = ReplayBuffer(4, 3, 2, 1)
    add_numbered(buffer, 0, 3)
    add_numbered(buffer, 3, 3)
    assert len(buffer) == 4
    assert sorted(buffer.gather(torch.arange(4)).reward.tolist()) == [2.0, 3.0, 4.0, 5.0]
    add_numbered(buffer, 10, 9)  # more than the capacity at once: the last 4 survive
    assert sorted(buffer.gather(torch.arange(4)).reward.tolist()) == [15.0, 16.0, 17.0, 18.0]


def test_sampling_is_seeded():
    def draws(seed: int) -> torch.Tensor:
        buffer = ReplayBuffer(100, 3, 2, 1, seed=seed)
        add_numbered(buffer, 0, 50)
        return torch.cat([buffer.sample(16).reward for _ in range(3)])

    assert torch.equal(draws(3), draws(3))
    assert not torch.equal(draws(3), draws(4))


def test_state_dict_round_trip_continues_the_same_stream():
    buffer = ReplayBuffer(20, 3, 2, 1, seed=1)
    add_numbered(buffer, 0, 25)
    buffer.sample(5)
    restored = ReplayBuffer(20, 3, 2, 1, seed=99)
    restored.load_state_dict(buffer.state_dict())
    assert len(restored) == 20
    for a, b in zip(buffer.sample(8), restored.sample(8)):
        assert torch.equal(a, b)
    add_numbered(buffer, 100, 1)
    add_numbered(restored, 100, 1)
    for a, b in zip(buffer.gather(torch.arange(20)), restored.gather(torch.arange(20))):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match='capacity'):
        ReplayBuffer(10, 3, 2, 1).load_state_dict(buffer.state_dict())
    with pytest.raises(ValueError, match='obs width'):
        ReplayBuffer(20, 4, 2, 1).load_state_dict(buffer.state_dict())


def test_bad_input_names_the_field():
    buffer = ReplayBuffer(10, 3, 2, 1)
    good = dict(obs=np.zeros(3), state=np.zeros(2), u_rl=[0.1], u_safe=[0.3], u_s=[0.2],
                reward=1.0, next_obs=np.ones(3), next_state=np.ones(2), done=False)
    with pytest.raises(ValueError, match='next_state'):
        buffer.add(**{**good, 'next_state': np.zeros(3)})
    with pytest.raises(ValueError, match='reward'):
        buffer.add(**{**good, 'reward': float('nan')})
    # Beyond float32's range: infinite once stored, refused the same way.
    with pytest.raises(ValueError, match='^u_safe contains non-finite values$'):
        buffer.add(**{**good, 'u_safe': [1e300]})
    with pytest.raises(ValueError, match='^obs contains'):
        buffer.add(**{**good, 'obs': torch.tensor([0.0, float('inf'), 0.0])})
    with pytest.raises(ValueError, match='done must hold 2 row'):
        buffer.add(**{name: np.stack([value, value]) if np.ndim(value) else [value, value]
                      for name, value in good.items()} | {'done': [True, False, True]})
    assert len(buffer) == 0  # nothing refused was stored
    with pytest.raises(ValueError, match='empty'):
        buffer.sample(1)
    with pytest.raises(ValueError, match='capacity'):
        ReplayBuffer(0, 3, 2, 1)


class CountingModel:
    """mean = 2 x + offset, std = |x| + 1 (float64), counting the rows it was asked for."""

    def __init__(self) -> None:
        self.offset = 0.0
        self.rows: list[int] = []

    def __call__(self, states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        assert states.dtype == torch.float64
        self.rows.append(states.shape[0])
        return 2.0 * states + self.offset, states.abs() + 1.0


def expected(model: CountingModel, states: torch.Tensor) -> torch.Tensor:
    x = states.to(torch.float64)
    return torch.stack([2.0 * x + model.offset, x.abs() + 1.0], dim=1)


def test_predictions_are_the_models_at_both_states_and_each_slot_is_predicted_once():
    buffer = ReplayBuffer(10, 3, 2, 1)
    add_numbered(buffer, 0, 6)
    model = CountingModel()
    index = torch.tensor([4, 1, 4, 0, 1])
    at = buffer.predictions(index, version=0, predict=model)
    batch = buffer.gather(index)
    torch.testing.assert_close(at.state, expected(model, batch.state), rtol=0, atol=0)
    torch.testing.assert_close(at.next_state, expected(model, batch.next_state), rtol=0, atol=0)
    assert model.rows == [6]  # one call: 3 distinct slots, state and next state each
    again = buffer.predictions(torch.tensor([0, 1, 4, 4]), version=0, predict=model)
    assert model.rows == [6]  # nothing stale
    torch.testing.assert_close(again.state, expected(model, buffer.gather(
        torch.tensor([0, 1, 4, 4])).state), rtol=0, atol=0)
    buffer.predictions(torch.tensor([0, 5]), version=0, predict=model)
    assert model.rows == [6, 2]  # only slot 5 is new


def test_a_new_model_version_or_an_overwritten_slot_is_predicted_again():
    buffer = ReplayBuffer(4, 3, 2, 1)
    add_numbered(buffer, 0, 4)
    model = CountingModel()
    everything = torch.arange(4)
    buffer.predictions(everything, version=0, predict=model)
    model.offset = 10.0  # a refit: new predictions, new version
    at = buffer.predictions(everything, version=1, predict=model)
    assert model.rows == [8, 8]
    torch.testing.assert_close(at.state, expected(model, buffer.gather(everything).state),
                               rtol=0, atol=0)
    add_numbered(buffer, 50, 1)  # overwrites the oldest slot, 0
    at = buffer.predictions(everything, version=1, predict=model)
    assert model.rows == [8, 8, 2]
    torch.testing.assert_close(at.next_state, expected(
        model, buffer.gather(everything).next_state), rtol=0, atol=0)


def test_a_restored_buffer_predicts_every_slot_again():
    buffer = ReplayBuffer(5, 3, 2, 1)
    add_numbered(buffer, 0, 5)
    model = CountingModel()
    buffer.predictions(torch.arange(5), version=3, predict=model)
    other = ReplayBuffer(5, 3, 2, 1)
    add_numbered(other, 100, 5)
    other.predictions(torch.arange(5), version=3, predict=model)
    other.load_state_dict(buffer.state_dict())  # same version number, other transitions
    at = other.predictions(torch.arange(5), version=3, predict=model)
    assert model.rows == [10, 10, 10]
    torch.testing.assert_close(at.state, expected(model, buffer.gather(torch.arange(5)).state),
                               rtol=0, atol=0)


def test_a_remembered_prediction_stands_in_for_its_state_only():
    """``remember`` puts a prediction made elsewhere (at the state before it was rounded to the
    buffer's dtype) into the memo of one half of one slot; ``predictions`` then predicts only
    the other halves. A state the slot does not hold, or another model version, is not
    taken, nor one for a half that holds this version's prediction already."""
    buffer = ReplayBuffer(10, 3, 2, 1)
    add_numbered(buffer, 0, 4)  # slot i: state (-i, -i), next state (-i - 1, -i - 1)
    model = CountingModel()
    mean, std = np.array([7.0, 8.0]), np.array([0.1, 0.2])
    unrounded = np.array([-2.0 + 1e-9, -2.0])  # rounds to slot 2's float32 state
    assert buffer.remember(2, 0, unrounded, mean, std, version=0)
    assert not buffer.remember(2, 1, unrounded, mean, std, version=0)  # slot 2's next: -3
    assert not buffer.remember(3, 0, np.array([-3.0, -3.001]), mean, std, version=0)
    index = torch.tensor([2, 3, 2])
    at = buffer.predictions(index, version=0, predict=model)
    assert model.rows == [3]  # slot 2's next state, slot 3's two states
    torch.testing.assert_close(at.state[0], torch.tensor([[7.0, 8.0], [0.1, 0.2]],
                                                         dtype=torch.float64))
    batch = buffer.gather(index)
    torch.testing.assert_close(at.state[1], expected(model, batch.state)[1], rtol=0, atol=0)
    torch.testing.assert_close(at.next_state, expected(model, batch.next_state),
                               rtol=0, atol=0)
    # One value per version: a half this version predicted already is left as it is.
    assert not buffer.remember(3, 0, np.array([-3.0, -3.0]), mean, std, version=0)
    torch.testing.assert_close(buffer.predictions(index, version=0, predict=model).state[1],
                               at.state[1], rtol=0, atol=0)
    buffer.predictions(torch.tensor([2]), version=1, predict=model)
    assert model.rows == [3, 2]  # a new version: the remembered half is stale too
    assert buffer.newest == 3
    add_numbered(buffer, 4, 7)  # wraps around
    assert buffer.newest == 0


def test_one_pass_after_a_refit_predicts_each_stored_state_once_in_chunks():
    """``fill_predictions`` predicts every stored state of a new version in calls of at most
    ``chunk`` rows; a next state the following slot holds as its state is copied from it
    (also across the wrap from the last slot to the first), one it does not (the oldest
    transition follows the newest) is predicted. Afterwards a minibatch predicts nothing and
    reads the model's values."""
    buffer = ReplayBuffer(10, 3, 2, 1)
    add_numbered(buffer, 0, 13)  # slots 0-2 hold transitions 10-12, slots 3-9 hold 3-9
    model = CountingModel()
    buffer.predictions(torch.tensor([4, 5]), version=0, predict=model)  # an older version
    model.rows.clear()
    model.offset = 3.0
    assert buffer.fill_predictions(version=1, predict=model, chunk=4) == 11
    assert model.rows == [4, 4, 2, 1]  # ten states, then slot 2's next state (-13)
    everything = torch.arange(10)
    at = buffer.predictions(everything, version=1, predict=model)
    assert model.rows == [4, 4, 2, 1]
    batch = buffer.gather(everything)
    torch.testing.assert_close(at.state, expected(model, batch.state), rtol=0, atol=0)
    torch.testing.assert_close(at.next_state, expected(model, batch.next_state),
                               rtol=0, atol=0)
    assert buffer.fill_predictions(version=1, predict=model) == 0  # nothing stale
    with pytest.raises(ValueError, match='chunk'):
        buffer.fill_predictions(version=2, predict=model, chunk=0)
    assert ReplayBuffer(4, 3, 2, 1).fill_predictions(version=0, predict=model) == 0


def _gp_on(states: np.ndarray, seed: int) -> DisturbanceGP:
    """A GP on 2 states conditioned on ``states`` (no hyperparameter fit: fast)."""
    gp = DisturbanceGP(2, 2, GPConfig(max_train_points=24, seed=seed))
    rng = np.random.default_rng(seed)
    gp.add(states, np.sin(states) + 0.05 * rng.standard_normal(states.shape))
    gp.set_hyperparameters(np.full((2, 2), 0.7), np.array([1.0, 0.5]), np.array([1e-2, 1e-3]))
    return gp


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(capacity=st.integers(2, 40), before=st.integers(1, 90), after=st.integers(0, 50),
       breaks=st.lists(st.integers(0, 140), max_size=8), chunk=st.integers(1, 64),
       stale_draw=st.integers(0, 30), seed=st.integers(0, 2 ** 16))
def test_after_a_refit_every_minibatch_reads_fresh_predictions(capacity, before, after, breaks,
                                                               chunk, stale_draw, seed):
    """The memo's contract with the one-pass fill: after a refit (new version) and
    ``fill_predictions``, the estimate of any minibatch, over transitions stored before the
    refit and written after it (overwriting some, wrapping around), equals the GP predicting
    afresh at the gathered states, to float round-off; transitions stored before the refit
    cost no prediction at all, and the pass asks for each distinct stored state at most once
    (a chained episode's next state is its successor's state)."""
    rng = np.random.default_rng(seed)
    total = before + after
    # An episode's states in a walk; a break (episode end) starts a new walk.
    walk = np.cumsum(rng.normal(scale=0.4, size=(total + 1, 2)), axis=0)
    restart = np.zeros(total + 1, dtype=bool)
    restart[[b for b in breaks if b < total]] = True
    next_states = walk[1:].copy()
    states = walk[:-1].copy()
    for i in np.flatnonzero(restart[:total]):
        states[i] = rng.normal(scale=2.0, size=2)  # after a reset: not the last next state
    buffer = ReplayBuffer(capacity, 3, 2, 1, seed=seed)

    def store(rows: slice) -> None:
        count = rows.stop - rows.start
        if count:
            buffer.add(obs=np.zeros((count, 3)), state=states[rows], u_rl=np.zeros((count, 1)),
                       u_safe=np.zeros((count, 1)), u_s=np.zeros((count, 1)),
                       reward=np.zeros(count), next_obs=np.zeros((count, 3)),
                       next_state=next_states[rows], done=np.zeros(count))

    store(slice(0, before))
    old = _gp_on(states[:before], seed)
    buffer.predictions(buffer.sample_index(stale_draw + 1), version=old.version,
                       predict=old.predict)  # a memo of the model before the refit
    gp = _gp_on(np.concatenate([states[:before], next_states[:before]]), seed + 1)
    version = gp.version + old.version + 1  # not the old model's
    asked: list[int] = []

    def predict(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        asked.append(x.shape[0])
        return gp.predict(x)

    filled = buffer.fill_predictions(version=version, predict=predict, chunk=chunk)
    distinct = torch.unique(torch.cat([buffer.gather(torch.arange(len(buffer))).state,
                                       buffer.gather(torch.arange(len(buffer))).next_state]),
                            dim=0).shape[0]
    assert sum(asked) == filled and max(asked, default=0) <= chunk
    assert len(buffer) <= filled <= 2 * len(buffer)
    assert filled <= distinct + int(restart[:before].sum()) + 1
    asked.clear()
    index = buffer.sample_index(48)
    estimate = buffer.predictions(index, version=version, predict=predict)
    assert not asked  # the pass left nothing to predict
    store(slice(before, total))
    for _ in range(3):
        index = buffer.sample_index(48)
        estimate = buffer.predictions(index, version=version, predict=predict)
        batch = buffer.gather(index)
        for at, states_at in ((estimate.state, batch.state),
                              (estimate.next_state, batch.next_state)):
            mean, std = gp.predict(states_at.to(torch.float64))
            torch.testing.assert_close(at[:, 0], mean, rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(at[:, 1], std, rtol=1e-10, atol=1e-12)

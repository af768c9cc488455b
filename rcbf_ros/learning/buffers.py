"""Replay buffer of SAC-RCBF transitions: preallocated tensors, seeded sampling, and a memo of
the disturbance model's prediction at each stored transition."""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np
import torch

ArrayLike = torch.Tensor | np.ndarray | float

PREDICT_CHUNK = 512
"""States per ``predict`` call of :meth:`ReplayBuffer.fill_predictions`: the GP's cost per
state, its kernel on the GEMM path from 16 states on (``gp_bounds.kernel_batch``), is lowest
from about 256 to 1,024 (CPU time of a pass over 200,000 stored states of a fitted GP:
benchmarks/RESULTS.md, "Training speed at a full buffer"); a call's kernel block, D x 512 x M
float64, stays below 21 MB at 10 outputs on 512 training points."""


class TransitionBatch(NamedTuple):
    """A batch of B transitions (x_t, u^RL_t, u*_t, u^S_t, r_t, x_{t+1}, done)."""

    obs: torch.Tensor
    """(B, obs_dim) observation at t, the networks' input."""
    state: torch.Tensor
    """(B, state_dim) system state at t, the safety QP's input (may differ from ``obs``)."""
    u_rl: torch.Tensor
    """(B, n_u) the policy's own sample u^RL_t."""
    u_safe: torch.Tensor
    """(B, n_u) the action applied in the environment, u*_t (eq. final_action)."""
    u_s: torch.Tensor
    """(B, n_u) the correction on top of the policy's sample, u*_t - u^RL_t (with a
    compensator this includes the compensator's part)."""
    reward: torch.Tensor
    """(B,) reward r_t."""
    next_obs: torch.Tensor
    """(B, obs_dim) observation at t + 1."""
    next_state: torch.Tensor
    """(B, state_dim) state at t + 1."""
    done: torch.Tensor
    """(B,) 1.0 if x_{t+1} is terminal (no bootstrapping), else 0.0; a time-limit
    truncation is not terminal."""


class BatchDisturbance(NamedTuple):
    """The disturbance model's estimate at a batch's states, for the safety layer."""

    state: torch.Tensor
    """(B, 2, state_dim) float64: mean ([:, 0]) and std ([:, 1]) at ``TransitionBatch.state``."""
    next_state: torch.Tensor
    """The same at ``TransitionBatch.next_state``."""


Predictor = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""states (B, state_dim) float64 -> (mean, std), each (B, state_dim)."""


class ReplayBuffer:
    """Circular buffer of ``TransitionBatch`` fields in preallocated tensors.

    Args:
        capacity: maximum number of transitions; the oldest are overwritten.
        obs_dim, state_dim, n_u: field sizes.
        seed: seed of ``sample``'s generator.
        dtype: storage type of every field.
    """

    def __init__(self, capacity: int, obs_dim: int, state_dim: int, n_u: int, *,
                 seed: int = 0, dtype: torch.dtype = torch.float32) -> None:
        for name, value in (('capacity', capacity), ('obs_dim', obs_dim),
                            ('state_dim', state_dim), ('n_u', n_u)):
            if value < 1:
                raise ValueError(f'{name} must be >= 1, got {value}')
        self.capacity = capacity
        self.dtype = dtype
        self._widths = {'obs': obs_dim, 'state': state_dim, 'u_rl': n_u, 'u_safe': n_u,
                        'u_s': n_u, 'reward': 0, 'next_obs': obs_dim,
                        'next_state': state_dim, 'done': 0}
        # One table, a row per transition, the fields side by side: an add is one write and a
        # sample one gather; ``_data`` holds each field's columns as a view of it.
        self._columns: dict[str, slice] = {}
        start = 0
        for name, width in self._widths.items():
            self._columns[name] = slice(start, start + (width or 1))
            start += width or 1
        self._table = torch.zeros((capacity, start), dtype=dtype)
        self._data = self._fields(self._table)
        self._position = 0
        self._size = 0
        self._generator = torch.Generator().manual_seed(seed)
        # The memo of predictions (allocated at its first use): per slot and half (state, next
        # state), the model version it was computed for, -1 when none or the slot was written
        # since.
        self._predicted: torch.Tensor | None = None
        self._predicted_version = torch.full((capacity, 2), -1, dtype=torch.int64)

    def __len__(self) -> int:
        return self._size

    @property
    def newest(self) -> int:
        """The slot of the transition added last (the buffer must not be empty)."""
        if self._size == 0:
            raise ValueError('the buffer is empty')
        return (self._position - 1) % self.capacity

    def add(self, *, obs: ArrayLike, state: ArrayLike, u_rl: ArrayLike, u_safe: ArrayLike,
            u_s: ArrayLike, reward: ArrayLike, next_obs: ArrayLike, next_state: ArrayLike,
            done: ArrayLike) -> None:
        """Store one transition (fields without batch dim) or K (leading dim K everywhere)."""
        fields = {'obs': obs, 'state': state, 'u_rl': u_rl, 'u_safe': u_safe, 'u_s': u_s,
                  'reward': reward, 'next_obs': next_obs, 'next_state': next_state,
                  'done': done}
        count = 1 if np.ndim(obs) == 1 else len(obs)
        blocks = []
        for name, value in fields.items():
            array = (value.detach().cpu().numpy() if isinstance(value, torch.Tensor)
                     else np.asarray(value, dtype=np.float64))
            width = self._widths[name]
            try:
                blocks.append(array.reshape(count, width or 1))
            except ValueError:
                raise ValueError(f'{name} must hold {count} row(s) of width {width or 1}, '
                                 f'got shape {tuple(array.shape)}') from None
        rows = torch.from_numpy(np.concatenate(blocks, axis=1, dtype=np.float64)).to(self.dtype)
        # Checked in the storage type: a value beyond its range is as unusable as a NaN.
        if not bool(torch.isfinite(rows).all()):
            bad = next(name for name, columns in self._columns.items()
                       if not bool(torch.isfinite(rows[:, columns]).all()))
            raise ValueError(f'{bad} contains non-finite values')
        if count == 1:
            self._table[self._position] = rows[0]
            self._predicted_version[self._position] = -1
        else:
            if count > self.capacity:
                rows = rows[-self.capacity:]
                count = self.capacity
            index = (self._position + torch.arange(count)) % self.capacity
            self._table[index] = rows
            self._predicted_version[index] = -1
        self._position = (self._position + count) % self.capacity
        self._size = min(self._size + count, self.capacity)

    def sample(self, batch_size: int) -> TransitionBatch:
        """Uniform sample with replacement, drawn from the buffer's seeded generator."""
        return self.gather(self.sample_index(batch_size))

    def sample_index(self, batch_size: int) -> torch.Tensor:
        """The (B,) positions ``sample`` would gather (the same draw from the generator)."""
        if self._size == 0:
            raise ValueError('cannot sample from an empty buffer')
        if batch_size < 1:
            raise ValueError(f'batch_size must be >= 1, got {batch_size}')
        return torch.randint(self._size, (batch_size,), generator=self._generator)

    def gather(self, index: torch.Tensor) -> TransitionBatch:
        """The transitions at ``index`` ((B,) int64 positions < len(self))."""
        return TransitionBatch(**self._fields(self._table[index]))

    def _fields(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each field's columns of ``rows`` (views; a scalar field as (R,))."""
        return {name: rows[:, columns] if self._widths[name] else rows[:, columns.start]
                for name, columns in self._columns.items()}

    def predictions(self, index: torch.Tensor, *, version: int,
                    predict: Predictor) -> BatchDisturbance:
        """A model's (mean, std) at the state and the next state of the transitions at
        ``index``.

        Memoised per slot and state: ``predict`` runs, in one call, only on the states never
        predicted, written since, or predicted for another ``version`` of the model. The caller
        changes ``version`` whenever the model's predictions change (a GP refit); the result
        then equals ``predict`` on the gathered states, up to the round-off of the batch it ran
        in, or, where :meth:`remember` filled the memo, the model's prediction at the state as
        it was before it was stored in the buffer's dtype.
        """
        memo = self._memo()
        if bool((self._predicted_version[index] != version).any()):
            unique = torch.unique(index)
            stale = self._predicted_version[unique] != version  # (U, 2)
            slot, half = stale.nonzero(as_tuple=True)
            slot = unique[slot]
            states = torch.where((half == 0)[:, None], self._data['state'][slot],
                                 self._data['next_state'][slot]).to(torch.float64)
            mean, std = predict(states)
            memo[slot, half] = torch.stack([mean, std], dim=1).to(torch.float64)
            self._predicted_version[slot, half] = version
        rows = memo[index]
        return BatchDisturbance(state=rows[:, 0], next_state=rows[:, 1])

    def fill_predictions(self, *, version: int, predict: Predictor,
                         chunk: int = PREDICT_CHUNK) -> int:
        """Put ``version``'s prediction at both states of every stored transition into the
        memo of :meth:`predictions`, in calls of at most ``chunk`` states; returns how many
        states ``predict`` was asked for.

        Meant right after a refit: with N stored and a refit every R steps, predicting on
        demand leaves up to 2 N / R states per minibatch to predict in small calls, where one
        pass predicts each stored state once, in calls of the size that runs fastest
        (``PREDICT_CHUNK``). Within an episode the
        next state of a transition is the state of the one stored after it: where the slot
        after a slot holds that state (its stored value equal) and its memo holds this
        version's prediction, it is copied instead of predicted again; equal stored states
        give ``predict`` the same input, so the memo holds what predicting would give, up to
        the round-off of the batch it ran in. Slots already holding this version's prediction
        are left as they are."""
        if chunk < 1:
            raise ValueError(f'chunk must be >= 1, got {chunk}')
        size = self._size
        if size == 0:
            return 0
        memo = self._memo()
        versions = self._predicted_version[:size]
        states, next_states = self._data['state'][:size], self._data['next_state'][:size]
        asked = self._predict_into(memo, (versions[:, 0] != version).nonzero().squeeze(1), 0,
                                   states, version, predict, chunk)
        stale = (versions[:, 1] != version).nonzero().squeeze(1)
        following = (stale + 1) % self.capacity
        shared = (following < size) & (versions[following.clamp_max(size - 1), 0] == version)
        candidates = stale[shared]
        after = following[shared]
        same = (next_states[candidates] == states[after]).all(dim=1)
        copied, source = candidates[same], after[same]
        memo[copied, 1] = memo[source, 0]
        self._predicted_version[copied, 1] = version
        rest = (self._predicted_version[:size, 1] != version).nonzero().squeeze(1)
        return asked + self._predict_into(memo, rest, 1, next_states, version, predict, chunk)

    def _predict_into(self, memo: torch.Tensor, slots: torch.Tensor, half: int,
                      states: torch.Tensor, version: int, predict: Predictor,
                      chunk: int) -> int:
        """``predict`` at ``states[slots]`` in calls of ``chunk`` rows, into ``half`` of the
        memo; returns the number of rows."""
        for start in range(0, slots.numel(), chunk):
            slot = slots[start:start + chunk]
            mean, std = predict(states[slot].to(torch.float64))
            memo[slot, half] = torch.stack([mean, std], dim=1).to(torch.float64)
            self._predicted_version[slot, half] = version
        return int(slots.numel())

    def remember(self, slot: int, half: int, state: np.ndarray, mean: np.ndarray,
                 std: np.ndarray, *, version: int) -> bool:
        """Put a prediction made elsewhere into the memo of :meth:`predictions`: the model's
        (mean, std) at ``state``, for the state (``half`` 0) or the next state (1) of the
        transition in ``slot``, computed by ``version`` of the model (the learner's acting path
        predicts every state it acts in, which is the state of the transition it stores next
        and the next state of the one before).

        Kept only if the slot holds that state (``state`` in the buffer's dtype equals the
        stored one) and its memo does not hold this version's prediction already (one value
        per version); returns whether it was kept."""
        versions = self._predicted_version.numpy()
        stored = self._data[('state', 'next_state')[half]][slot]
        if versions[slot, half] == version or not torch.equal(
                torch.from_numpy(np.asarray(state, dtype=np.float64)).to(self.dtype), stored):
            return False
        # The memo's writes in numpy, on views of its tensors: a few element writes.
        memo = self._memo().numpy()
        memo[slot, half, 0] = mean
        memo[slot, half, 1] = std
        versions[slot, half] = version
        return True

    def _memo(self) -> torch.Tensor:
        """(capacity, 2 halves, 2 [mean, std], state_dim) float64, allocated at first use."""
        if self._predicted is None:
            # torch.empty: pages are only touched for slots that get predicted.
            self._predicted = torch.empty((self.capacity, 2, 2, self._widths['state']),
                                          dtype=torch.float64)
        return self._predicted

    def state_dict(self) -> dict[str, Any]:
        """Stored transitions (only the filled rows), write position and sampler state."""
        return {'capacity': self.capacity, 'position': self._position, 'size': self._size,
                'data': {name: tensor[:self._size].clone() for name, tensor in
                         self._data.items()},
                'generator': self._generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict`` of a buffer with the same capacity and field sizes."""
        if state['capacity'] != self.capacity:
            raise ValueError(f"capacity mismatch: state_dict has {state['capacity']}, "
                             f'buffer has {self.capacity}')
        for name, tensor in state['data'].items():
            if tensor.shape[1:] != self._data[name].shape[1:]:
                raise ValueError(f'{name} width mismatch: state_dict has '
                                 f'{tuple(tensor.shape[1:])}, buffer has '
                                 f'{tuple(self._data[name].shape[1:])}')
        self._size = state['size']
        self._position = state['position']
        self._predicted_version.fill_(-1)
        for name, tensor in state['data'].items():
            self._data[name].zero_()
            self._data[name][:self._size] = tensor.to(self.dtype)
        self._generator.set_state(state['generator'])

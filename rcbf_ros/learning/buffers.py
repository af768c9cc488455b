"""Replay buffer of SAC-RCBF transitions: preallocated tensors, seeded sampling."""
from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

ArrayLike = torch.Tensor | np.ndarray | float


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
        self._data = {name: torch.zeros((capacity, width) if width else (capacity,),
                                        dtype=dtype)
                      for name, width in self._widths.items()}
        self._position = 0
        self._size = 0
        self._generator = torch.Generator().manual_seed(seed)

    def __len__(self) -> int:
        return self._size

    def add(self, *, obs: ArrayLike, state: ArrayLike, u_rl: ArrayLike, u_safe: ArrayLike,
            u_s: ArrayLike, reward: ArrayLike, next_obs: ArrayLike, next_state: ArrayLike,
            done: ArrayLike) -> None:
        """Store one transition (fields without batch dim) or K (leading dim K everywhere)."""
        fields = {'obs': obs, 'state': state, 'u_rl': u_rl, 'u_safe': u_safe, 'u_s': u_s,
                  'reward': reward, 'next_obs': next_obs, 'next_state': next_state,
                  'done': done}
        obs_t = torch.as_tensor(np.asarray(obs) if not isinstance(obs, torch.Tensor) else obs)
        count = 1 if obs_t.ndim == 1 else obs_t.shape[0]
        rows: dict[str, torch.Tensor] = {}
        for name, value in fields.items():
            tensor = value if isinstance(value, torch.Tensor) else torch.as_tensor(
                np.asarray(value, dtype=np.float64))
            tensor = tensor.detach().to(self.dtype)
            width = self._widths[name]
            shape = ((count, width) if width else (count,))
            try:
                tensor = tensor.reshape(shape)
            except RuntimeError:
                raise ValueError(f'{name} must hold {count} row(s) of width {width or 1}, '
                                 f'got shape {tuple(tensor.shape)}') from None
            if not torch.isfinite(tensor).all():
                raise ValueError(f'{name} contains non-finite values')
            rows[name] = tensor
        if count > self.capacity:
            rows = {name: tensor[-self.capacity:] for name, tensor in rows.items()}
            count = self.capacity
        index = (self._position + torch.arange(count)) % self.capacity
        for name, tensor in rows.items():
            self._data[name][index] = tensor
        self._position = (self._position + count) % self.capacity
        self._size = min(self._size + count, self.capacity)

    def sample(self, batch_size: int) -> TransitionBatch:
        """Uniform sample with replacement, drawn from the buffer's seeded generator."""
        if self._size == 0:
            raise ValueError('cannot sample from an empty buffer')
        if batch_size < 1:
            raise ValueError(f'batch_size must be >= 1, got {batch_size}')
        index = torch.randint(self._size, (batch_size,), generator=self._generator)
        return self.gather(index)

    def gather(self, index: torch.Tensor) -> TransitionBatch:
        """The transitions at ``index`` ((B,) int64 positions < len(self))."""
        return TransitionBatch(**{name: tensor[index] for name, tensor in self._data.items()})

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
        for name, tensor in state['data'].items():
            self._data[name].zero_()
            self._data[name][:self._size] = tensor.to(self.dtype)
        self._generator.set_state(state['generator'])

"""Test helper: small random SAC minibatches, the same ones for every caller."""
from __future__ import annotations

import torch

from rcbf_ros.learning.buffers import TransitionBatch

OBS, N_X, N_U, B = 5, 3, 2, 32
"""Observation, state and action sizes, and the minibatch size."""


def random_batches(count: int) -> list[TransitionBatch]:
    """``count`` minibatches of B random transitions (actions in [-1, 1], a few terminal),
    drawn from a generator seeded alike on every call."""
    draws = torch.Generator().manual_seed(11)

    def rand(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=draws)

    return [TransitionBatch(obs=rand(B, OBS), state=rand(B, N_X),
                            u_rl=rand(B, N_U).clamp(-1, 1), u_safe=rand(B, N_U).clamp(-1, 1),
                            u_s=rand(B, N_U), reward=rand(B), next_obs=rand(B, OBS),
                            next_state=rand(B, N_X), done=(rand(B) > 1.0).float())
            for _ in range(count)]

"""Short model rollouts into a model buffer (paper: "Model-Based RL", Algorithm 1).

From M states sampled uniformly from the environment buffer, roll the current policy and the
safety layer through the learned model for k steps:

    u^RL_t ~ pi(.|o(x_t)),  u*_t = safety_layer(x_t, u^RL_t),
    x_{t+1} = predict_next_state(x_t, u*_t)       (dynamics prior + GP mean, the caller's),
    (r_t, done_t) = reward_fn(x_t, u*_t, x_{t+1}),

and store every (o(x_t), x_t, u^RL_t, u*_t, u*_t - u^RL_t, r_t, o(x_{t+1}), x_{t+1}, done_t)
in the model buffer. A rollout stops at its first terminal transition. The reward is
``reward_fn``'s value unchanged: any goal bonus is counted once, inside ``reward_fn`` (the
reference code adds it a second time).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from rcbf_ros.learning.buffers import ReplayBuffer

NextStateFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
RewardFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor],
                    tuple[torch.Tensor, torch.Tensor]]
ObsFn = Callable[[torch.Tensor], torch.Tensor]
PolicyFn = Callable[[torch.Tensor], torch.Tensor]
SafetyLayer = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class RolloutConfig:
    """Size of the synthetic data of one call of ``ModelRollout.run``."""

    num_rollouts: int = 400
    """M: start states sampled from the environment buffer."""
    horizon: int = 5
    """k: model steps per rollout (short: model errors compound)."""

    def __post_init__(self) -> None:
        if self.num_rollouts < 1:
            raise ValueError(f'num_rollouts must be >= 1, got {self.num_rollouts}')
        if self.horizon < 1:
            raise ValueError(f'horizon must be >= 1, got {self.horizon}')


class ModelRollout:
    """k-step synthetic transitions from sampled buffer states (Algorithm 1, lines 8-15).

    Args:
        predict_next_state: (state (B, n_x), u_safe (B, n_u)) -> next state (B, n_x).
        reward_fn: (state, u_safe, next_state) -> (reward (B,), done (B,) bool or 0/1).
        obs_fn: state (B, n_x) -> observation (B, obs_dim).
        policy: observation (B, obs_dim) -> u^RL (B, n_u), e.g. ``SAC.policy_action``.
        safety_layer: (state (B, n_x), u^RL (B, n_u)) -> u* (B, n_u).
        config: see ``RolloutConfig``.
    """

    def __init__(self, *, predict_next_state: NextStateFn, reward_fn: RewardFn, obs_fn: ObsFn,
                 policy: PolicyFn, safety_layer: SafetyLayer,
                 config: RolloutConfig | None = None) -> None:
        self.predict_next_state = predict_next_state
        self.reward_fn = reward_fn
        self.obs_fn = obs_fn
        self.policy = policy
        self.safety_layer = safety_layer
        self.config = config if config is not None else RolloutConfig()

    def run(self, env_buffer: ReplayBuffer, model_buffer: ReplayBuffer) -> int:
        """Sample start states from ``env_buffer`` (its seeded generator), roll out, and add
        the transitions to ``model_buffer``.

        Returns:
            number of transitions added.
        """
        start = env_buffer.sample(self.config.num_rollouts)
        state = start.state
        added = 0
        with torch.no_grad():
            for _ in range(self.config.horizon):
                if state.shape[0] == 0:
                    break
                obs = self.obs_fn(state)
                u_rl = self.policy(obs)
                u_safe = self.safety_layer(state, u_rl).to(u_rl.dtype)
                next_state = self.predict_next_state(state, u_safe)
                reward, done = self.reward_fn(state, u_safe, next_state)
                done = done.to(torch.bool).reshape(-1)
                model_buffer.add(obs=obs, state=state, u_rl=u_rl, u_safe=u_safe,
                                 u_s=u_safe - u_rl, reward=reward,
                                 next_obs=self.obs_fn(next_state), next_state=next_state,
                                 done=done.to(reward.dtype))
                added += state.shape[0]
                state = next_state[~done]
        return added

"""Reward and observation models in torch, batched, for model-based rollouts (Algorithm 1).

Synthetic transitions need r(x, u*, x') and o(x') for states the plant never visited, so the
go-to-goal systems' reward and observation are restated here as batched torch functions of the
state. ``test/unit/test_training.py`` checks them against the envs on random states so the two
cannot drift. Car Following has no state-only observation model (its observation holds the
cars' measured accelerations), so model-based training is offered for Unicycle and PVTOL.
"""
from __future__ import annotations

from typing import Any, Callable

import torch
from torch import Tensor

RewardFn = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]
ObsFn = Callable[[Tensor], Tensor]


def _goal_terms(position: Tensor, heading: Tensor, goal: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """cos/sin of the heading, the unit goal direction in the body frame, the distance."""
    to_goal = goal - position
    distance = to_goal.norm(dim=-1)
    c, s = torch.cos(heading), torch.sin(heading)
    body = torch.stack([c * to_goal[:, 0] + s * to_goal[:, 1],
                        -s * to_goal[:, 0] + c * to_goal[:, 1]], dim=-1)
    body = body / (body.norm(dim=-1, keepdim=True) + 1e-3)
    return torch.stack([c, s], dim=-1), body, distance


def go_to_goal_reward(goal: Tensor, radius: float, bonus: float) -> RewardFn:
    """Progress toward the goal plus ``bonus`` (once) on arrival; arrival ends the episode."""

    def reward(state: Tensor, u: Tensor, next_state: Tensor) -> tuple[Tensor, Tensor]:
        g = goal.to(state.dtype)
        before = (state[:, :2] - g).norm(dim=-1)
        after = (next_state[:, :2] - g).norm(dim=-1)
        reached = after <= radius
        return before - after + bonus * reached.to(state.dtype), reached

    return reward


def unicycle_models(env: Any) -> tuple[RewardFn, ObsFn]:
    """[x, y, cos th, sin th, body-frame goal direction (2), exp(-distance)]."""
    goal = torch.as_tensor(env.goal, dtype=torch.float64)

    def obs(state: Tensor) -> Tensor:
        trig, body, distance = _goal_terms(state[:, :2], state[:, 2], goal.to(state.dtype))
        return torch.cat([state[:, :2], trig, body, torch.exp(-distance)[:, None]], dim=-1)

    return go_to_goal_reward(goal, env.goal_radius, env.goal_reward), obs


def pvtol_models(env: Any) -> tuple[RewardFn, ObsFn]:
    """[x1, x2, cos th, sin th, v1, v2, f, body-frame goal direction (2), exp(-distance)]."""
    goal = torch.as_tensor(env.goal, dtype=torch.float64)

    def obs(state: Tensor) -> Tensor:
        trig, body, distance = _goal_terms(state[:, :2], state[:, 4], goal.to(state.dtype))
        return torch.cat([state[:, :2], trig, state[:, 2:4], state[:, 5:6], body,
                          torch.exp(-distance)[:, None]], dim=-1)

    return go_to_goal_reward(goal, env.goal_radius, env.goal_reward), obs


MODELS: dict[str, Callable[[Any], tuple[RewardFn, ObsFn]]] = {
    'unicycle': unicycle_models,
    'pvtol': pvtol_models,
}

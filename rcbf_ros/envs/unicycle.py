"""Unicycle among obstacles (paper, "Unicycle Environment").

TRUE dynamics (unknown to the agent): x_dot = g(x) (u + u_d), u_d = -0.1 cos(theta) [1, 0]
(a slope), with the nominal g of :class:`rcbf_ros.core.dynamics.Unicycle`; Euler step
x' = x + dt g(x) (u + u_d(x)).

Parameters: :class:`UnicycleSettings` (flat keys, the reference's values as defaults; an
``arena_half_size`` key is informational: the arena is not a barrier). ``random_start`` picks
the start among :data:`~rcbf_ros.envs.layouts.UNICYCLE_STARTS` (corners and edge midpoints away
from the goal) with a heading U[-pi, pi); ``layout``: ``fixed`` (the
``obstacles.x/.y/.radius(/.shape)`` keys) or ``random`` (a new
:func:`~rcbf_ros.envs.layouts.unicycle_random_layout` per reset, its seed drawn from the env's
generator and reported as ``info['layout_seed']``); ``layout_seed`` >= 0 pins one random
layout.

Reward: previous distance - distance to the goal, + ``goal_reward`` when within
``goal_radius`` (the episode terminates there). Observation (7,):
[x, y, cos th, sin th, e_goal (2), exp(-distance)], e_goal the unit vector to the goal in the
robot's frame (as the reference computes its "compass").

``h_true``: one signed clearance per obstacle of the robot's CENTRE to the true shape (circle,
square or triangle; no filter margin, no look-ahead).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping, TYPE_CHECKING

import gymnasium as gym
import numpy as np

from rcbf_ros.core.dynamics import Unicycle
from rcbf_ros.core.torch_import import LazyTorch
from rcbf_ros.envs.base import (
    goal_terms,
    GoToGoalReward,
    GoToGoalSettings,
    input_limits,
    SafetyEnv,
)
from rcbf_ros.envs.layouts import (
    layout_to_params,
    signed_clearance,
    unicycle_random_layout,
    UNICYCLE_STARTS,
)
from rcbf_ros.envs.nominal import unicycle_go_to_goal
from rcbf_ros.parameters.reader import setting

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


def unicycle_slope_disturbance(state: np.ndarray) -> np.ndarray:
    """u_d(x) = -0.1 cos(theta) [1, 0] in input space. state: (3,) -> (2,)."""
    return np.array([-0.1 * math.cos(state[2]), 0.0])


@dataclass(frozen=True)
class UnicycleSettings(GoToGoalSettings):
    """The unicycle env's parameters (defaults: the reference's values)."""

    goal: tuple[float, ...] = setting((2.5, 2.5), length=2,
                                      description='goal position [x, y] (m)')
    """Goal position (m)."""
    start: tuple[float, ...] = setting((-2.5, -2.5, 0.0), length=3,
                                       description='start state [x, y, theta] (m, rad)')
    """Start state [x, y, theta]."""


class UnicycleEnv(GoToGoalReward, SafetyEnv):
    """Unicycle go-to-goal with obstacles (see module docstring)."""

    system_name = 'unicycle'
    gymnasium_id = 'rcbf_ros/Unicycle-v0'
    settings_type = UnicycleSettings
    settings: UnicycleSettings
    go_to_goal = staticmethod(unicycle_go_to_goal)

    def __init__(self, params: Mapping[str, Any] | None = None, **overrides: Any) -> None:
        super().__init__(params, overrides)
        self.nominal_system = Unicycle(**input_limits(self.params, 2))
        self._take_goal_settings(self.settings)
        self.current_layout_seed: int | None = None
        if self.settings.layout == 'random' and self.settings.layout_seed >= 0:
            self._use_random_layout(self.settings.layout_seed)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(7,), dtype=np.float64)
        lo = self.nominal_system.u_min or (-np.inf, -np.inf)
        hi = self.nominal_system.u_max or (np.inf, np.inf)
        self.action_space = gym.spaces.Box(np.asarray(lo), np.asarray(hi), dtype=np.float64)
        self._last_distance = 0.0

    @property
    def h_true_names(self) -> list[str]:  # type: ignore[override]
        return [f'obstacle_{i}' for i in range(len(self.obstacles))]

    def _use_random_layout(self, seed: int) -> None:
        self.current_layout_seed = seed
        self.obstacles = unicycle_random_layout(seed)

    def _reset_state(self, options: dict[str, Any]) -> np.ndarray:
        if self.settings.layout == 'random' and self.settings.layout_seed < 0:
            self._use_random_layout(int(self.np_random.integers(2 ** 31 - 1)))
        if self.random_start:
            xy = UNICYCLE_STARTS[int(self.np_random.integers(len(UNICYCLE_STARTS)))]
            state = np.array([xy[0], xy[1], self.np_random.uniform(-math.pi, math.pi)])
        else:
            state = np.array(self.settings.start)
        self._last_distance = float(np.linalg.norm(state[:2] - self.goal))
        return state

    def _true_derivative(self, state: np.ndarray, u: np.ndarray) -> np.ndarray:
        f, g = self.nominal_terms(state)
        return f + g @ (u + unicycle_slope_disturbance(state))

    def _observation(self) -> np.ndarray:
        x, y, theta = self._state
        to_goal = self.goal - self._state[:2]
        distance = float(np.linalg.norm(to_goal))
        c, s = math.cos(theta), math.sin(theta)
        body = np.array([c * to_goal[0] + s * to_goal[1], -s * to_goal[0] + c * to_goal[1]])
        body = body / (np.linalg.norm(body) + 1e-3)
        return np.array([x, y, c, s, body[0], body[1], math.exp(-distance)])

    def _torch_observation(self, state: Tensor, goal: Tensor) -> Tensor:
        """[x, y, cos th, sin th, body-frame goal direction (2), exp(-distance)]."""
        trig, body, distance = goal_terms(state[:, :2], state[:, 2], goal)
        return torch.cat([state[:, :2], trig, body, torch.exp(-distance)[:, None]], dim=-1)

    def _h_true(self, state: np.ndarray) -> np.ndarray:
        return np.array([signed_clearance(o, state[:2]) for o in self.obstacles])

    def _set_layout_filter_params(self, params: dict[str, Any]) -> None:
        layout = layout_to_params(self.obstacles)
        layout.pop('obstacles.shape')
        params.update(layout)

    def _info(self, *, goal_reached: bool) -> dict[str, Any]:
        info = super()._info(goal_reached=goal_reached)
        info['layout_seed'] = self.current_layout_seed
        return info

"""Modified planar VTOL among obstacles, optionally shadowed by a safety operator (paper, "PVTOL").

QP state [x1, x2, v1, v2, theta, f] (+ [x_h] with the operator), input [omega, u_f], nominal
model :class:`rcbf_ros.core.dynamics.PVTOL`. TRUE dynamics (unknown to the agent): the nominal
ones plus

- attitude-tracking error d_omega(x) = 0.1 (f - 1) - 0.1 sin(theta) on theta_dot (smooth,
  bounded for bounded thrust, zero in level hover: the inner attitude loop lags more at high
  thrust and leans back toward level), scaled by ``attitude_error_gain``;
- the operator: a noisy single integrator x_h' = x_h + dt k_h (x1 - x_h) + sqrt(dt) sigma_h n,
  n ~ N(0, 1) from the env's generator, k_h = ``system_params.operator_gain``,
  sigma_h = ``operator_noise``. The reference moves its operator by
  clip(0.07 (x1 - x_h), +-0.07) + 0.015 U(-1, 1) per 0.02 s step: k_h = 0.07 / dt = 3.5 per
  second (the clip, 3.5 m/s, is never reached inside the 0.6 m band) and a per-step noise std
  of 0.015 / sqrt(3) = sqrt(dt) 0.06 (Gaussian here).

Parameters: :class:`PVTOLSettings` (flat keys, the reference's values as defaults). The start
is a level hover (v = 0, theta = 0, f = 1; the operator starts under the drone, x_h = x1);
``random_start`` picks it among :data:`~rcbf_ros.envs.layouts.PVTOL_STARTS`; ``layout``
``random`` draws :func:`~rcbf_ros.envs.layouts.pvtol_random_layout` (operator present with
probability 0.5); ``operator_band`` is the TRUE band |x1 - x_h| (the filter's
``bands.operator.half_width`` is smaller by its margin).

Reward: progress toward the goal + ``goal_reward`` on reaching it (terminates). Observation
(10,): [x1, x2, cos th, sin th, v1, v2, f, e_goal (2), exp(-distance)], e_goal the unit vector
to the goal in the body frame. The arena [-6, 6] x [-3, 3] is not a barrier here.

``h_true``: signed clearance of (x1, x2) to every obstacle circle (no margin), then
``operator_band - |x1 - x_h|`` when the operator is present.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping, TYPE_CHECKING

import gymnasium as gym
import numpy as np

from rcbf_ros.core.dynamics import PVTOL
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
    pvtol_random_layout,
    PVTOL_STARTS,
    signed_clearance,
)
from rcbf_ros.envs.nominal import pvtol_go_to_goal
from rcbf_ros.parameters.reader import setting

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


def pvtol_attitude_error(state: np.ndarray, gain: float = 0.1) -> float:
    """d_omega(x) = gain ((f - 1) - sin(theta)). state: (n_x,) -> scalar."""
    return gain * ((state[5] - 1.0) - math.sin(state[4]))


@dataclass(frozen=True)
class PVTOLSettings(GoToGoalSettings):
    """The PVTOL env's parameters (defaults: the reference's values)."""

    with_operator: bool = setting(True, key='system_params.with_operator', text_bool=True)
    """Whether the state carries the safety operator (x_h, its band)."""
    operator_gain: float = setting(3.5, key='system_params.operator_gain', positive=True)
    """Gain of the operator following x1."""
    max_steps: int = setting(2000, minimum=1,
                             description='steps per episode before it is truncated')
    """Steps before truncation."""
    goal: tuple[float, ...] = setting((5.0, -1.5), length=2,
                                      description='goal position [x, y] (m)')
    """Goal position (m)."""
    goal_reward: float = setting(3.0, description='reward for reaching the goal')
    """Reward for reaching the goal."""
    start: tuple[float, ...] = setting((-4.5, 2.0), length=2,
                                       description='start position [x1, x2] (m), level hover')
    """Start position [x1, x2] (level hover)."""
    attitude_error_gain: float = setting(
        0.1, description='gain of the attitude-tracking error on theta_dot')
    """Gain of the attitude-tracking error on theta_dot."""
    operator_noise: float = setting(0.06, minimum=0,
                                    description="std of the operator's motion noise per sqrt(s)")
    """Std of the operator's motion noise per sqrt(s)."""
    operator_band: float = setting(
        0.6, positive=True,
        description='true band |x1 - x_h| the operator keeps to (the filter adds a margin)')
    """True band |x1 - x_h| the operator keeps to."""


class PVTOLEnv(GoToGoalReward, SafetyEnv):
    """PVTOL go-to-goal (see module docstring)."""

    system_name = 'pvtol'
    gymnasium_id = 'rcbf_ros/PVTOL-v0'
    settings_type = PVTOLSettings
    go_to_goal = staticmethod(pvtol_go_to_goal)
    settings: PVTOLSettings

    def __init__(self, params: Mapping[str, Any] | None = None, **overrides: Any) -> None:
        super().__init__(params, overrides)
        self._limits = input_limits(self.params, 2)
        self._take_goal_settings(self.settings)
        self.with_operator = self.settings.with_operator
        self.current_layout_seed: int | None = None
        if self.settings.layout == 'random' and self.settings.layout_seed >= 0:
            self._use_random_layout(self.settings.layout_seed)
        self._build_system()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(10,), dtype=np.float64)
        lo = self.nominal_system.u_min or (-np.inf, -np.inf)
        hi = self.nominal_system.u_max or (np.inf, np.inf)
        self.action_space = gym.spaces.Box(np.asarray(lo), np.asarray(hi), dtype=np.float64)
        self._last_distance = 0.0

    def _build_system(self) -> None:
        self.nominal_system = PVTOL(with_operator=self.with_operator,
                                    operator_gain=self.settings.operator_gain, **self._limits)

    def _use_random_layout(self, seed: int) -> None:
        self.current_layout_seed = seed
        self.obstacles, self.with_operator = pvtol_random_layout(seed)

    @property
    def h_true_names(self) -> list[str]:  # type: ignore[override]
        names = [f'obstacle_{i}' for i in range(len(self.obstacles))]
        return names + (['operator'] if self.with_operator else [])

    def _reset_state(self, options: dict[str, Any]) -> np.ndarray:
        if self.settings.layout == 'random' and self.settings.layout_seed < 0:
            self._use_random_layout(int(self.np_random.integers(2 ** 31 - 1)))
            self._build_system()
        if self.random_start:
            xy = PVTOL_STARTS[int(self.np_random.integers(len(PVTOL_STARTS)))]
        else:
            xy = self.settings.start
        state = [xy[0], xy[1], 0.0, 0.0, 0.0, 1.0] + ([xy[0]] if self.with_operator else [])
        self._last_distance = float(np.hypot(xy[0] - self.goal[0], xy[1] - self.goal[1]))
        return np.asarray(state, dtype=np.float64)

    def _true_derivative(self, state: np.ndarray, u: np.ndarray) -> np.ndarray:
        f, g = self.nominal_terms(state)
        derivative = f + g @ u
        derivative[4] += pvtol_attitude_error(state, self.settings.attitude_error_gain)
        return derivative

    def _post_step(self, state: np.ndarray) -> np.ndarray:
        if self.with_operator and self.settings.operator_noise > 0:
            state = state.copy()
            state[6] += math.sqrt(self.dt) * self.settings.operator_noise * self.np_random.normal()
        return state

    def _observation(self) -> np.ndarray:
        s = self._state
        to_goal = self.goal - s[:2]
        distance = float(np.linalg.norm(to_goal))
        c, sn = math.cos(s[4]), math.sin(s[4])
        body = np.array([c * to_goal[0] + sn * to_goal[1], -sn * to_goal[0] + c * to_goal[1]])
        body = body / (np.linalg.norm(body) + 1e-3)
        return np.array([s[0], s[1], c, sn, s[2], s[3], s[5], body[0], body[1],
                         math.exp(-distance)])

    def _torch_observation(self, state: Tensor, goal: Tensor) -> Tensor:
        """[x1, x2, cos th, sin th, v1, v2, f, body-frame goal direction (2),
        exp(-distance)]."""
        trig, body, distance = goal_terms(state[:, :2], state[:, 4], goal)
        return torch.cat([state[:, :2], trig, state[:, 2:4], state[:, 5:6], body,
                          torch.exp(-distance)[:, None]], dim=-1)

    def _h_true(self, state: np.ndarray) -> np.ndarray:
        values = [signed_clearance(o, state[:2]) for o in self.obstacles]
        if self.with_operator:
            values.append(self.settings.operator_band - abs(state[0] - state[6]))
        return np.asarray(values)

    def _set_layout_filter_params(self, params: dict[str, Any]) -> None:
        layout = layout_to_params(self.obstacles)
        layout.pop('obstacles.shape')
        params.update(layout)
        params['system_params.with_operator'] = self.with_operator
        params['system_params.operator_gain'] = self.settings.operator_gain
        if not self.with_operator:
            for key in [k for k in params if k.startswith('bands.operator.')]:
                del params[key]

    def _info(self, *, goal_reached: bool) -> dict[str, Any]:
        info = super()._info(goal_reached=goal_reached)
        info['layout_seed'] = self.current_layout_seed
        return info

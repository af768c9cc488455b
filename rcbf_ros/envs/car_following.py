"""Five-car chain; the agent drives car 4 (paper, "Car Following", after Cheng et al. 2019).

TRUE dynamics (unknown to the agent): p_i_dot = v_i, v_i_dot = (1 + d_i) u_i with d_i = 0.1 for
cars 1, 2, 3, 5 and d_4 = 0, where

- u_1 = k_v (v_des - v_1) + 10 sin(0.2 t): the leader tracks v_des with the paper's sinusoidal
  acceleration on top ("u_1 = 10 sin(0.2 t) around v_des", ENVIRONMENTS.md);
- u_2, u_3, u_5: the nominal controllers of :class:`rcbf_ros.core.dynamics.CarFollowing`
  (track v_des; brake on the car ahead within 6 m, car 5 on car 3 within 12 m);
- u_4: the applied action (no actuator limits, as in the paper).

The nominal prior lacks the 1 + d_i gains and car 1's input; the learned disturbance covers them.

Parameters: :class:`CarFollowingSettings` (flat keys, the reference's values as defaults). Car
4 starts faster than the others, closing on car 3 ("car 4 at 35" in ENVIRONMENTS.md is
``initial_velocity_car4``); ``velocity_noise`` is the std of ONE normal draw added to every
car's initial velocity, from the env's generator.

Reward: -reward_scale ||u||^2 (paper r(u) = -||u||^2, scaled so that an episode's return is
minus the mean squared acceleration). Observation (15,): positions / 100, velocities / 30 and
the accelerations of the last step / 10 (zero after reset), car by car
[p_1, v_1, a_1, ..., p_5, v_5, a_5]. The episode never reaches a goal; it truncates.

``h_true``: [p_3 - p_4 - delta, p_4 - p_5 - delta] (signed gaps in metres, delta =
``collision_gap``, the paper's 3.5 m). The filter's ``gaps.delta`` (config: 3.75) adds a
0.25 m margin: pushed against the barrier by a controller, the filter holds h at zero
asymptotically, and the unknown 1 + d_i gains then cross it by millimetres without one.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping

import gymnasium as gym
import numpy as np

from rcbf_ros.core.dynamics import CarFollowing
from rcbf_ros.envs.base import Controller, EnvSettings, SafetyEnv
from rcbf_ros.envs.nominal import cars_accelerate
from rcbf_ros.parameters.reader import read_parameters, setting


@dataclass(frozen=True)
class CarFollowingSettings(EnvSettings):
    """The car-following env's parameters (defaults: the reference's values)."""

    max_steps: int = setting(300, minimum=1,
                             description='steps per episode before it is truncated')
    """Steps before truncation."""
    initial_positions: tuple[float, ...] = setting(
        (34.0, 28.0, 22.0, 16.0, 10.0), length=5,
        description='initial positions of the five cars (m)')
    """Initial positions of the five cars (m)."""
    initial_velocity: float = setting(30.0,
                                      description='initial velocity of cars 1, 2, 3, 5 (m/s)')
    """Initial velocity of cars 1, 2, 3, 5 (m/s)."""
    initial_velocity_car4: float = setting(35.0, description='initial velocity of car 4 (m/s)')
    """Initial velocity of car 4 (m/s)."""
    velocity_noise: float = setting(
        0.5, minimum=0, description="std of one draw added to every car's initial velocity "
                                    '(m/s)')
    """Std of one draw added to every car's initial velocity (m/s)."""
    disturbance_gain: float = setting(0.1,
                                      description='unknown input gain d_i of cars 1, 2, 3, 5')
    """Unknown input gain d_i of cars 1, 2, 3, 5."""
    leader_amplitude: float = setting(10.0, description="amplitude of the leader's sine "
                                                        'acceleration (m/s^2)')
    """Amplitude of the leader's sine acceleration (m/s^2)."""
    leader_frequency: float = setting(0.2, description="frequency of the leader's sine "
                                                       'acceleration (rad/s)')
    """Frequency of the leader's sine acceleration (rad/s)."""
    reward_scale: float = setting(1.0 / 300.0, description='reward = -reward_scale ||u||^2')
    """reward = -reward_scale ||u||^2."""
    collision_gap: float = setting(3.5, positive=True,
                                   description='true least gap between two cars (m)')
    """True least gap between two cars (m)."""


@dataclass(frozen=True)
class CarControllerSettings:
    """The car-following nominal controller's parameter (``/nominal_controller`` section)."""

    acceleration: float = setting(
        5.0, description="the nominal controller's constant acceleration of car 4 (m/s^2)")
    """Constant acceleration of car 4 (m/s^2)."""


class CarFollowingEnv(SafetyEnv):
    """Car Following (see module docstring)."""

    system_name = 'car_following'
    gymnasium_id = 'rcbf_ros/CarFollowing-v0'
    settings_type = CarFollowingSettings
    controller_settings = CarControllerSettings
    settings: CarFollowingSettings
    h_true_names = ['gap_3_4', 'gap_4_5']

    def __init__(self, params: Mapping[str, Any] | None = None, **overrides: Any) -> None:
        super().__init__(params, overrides)
        self.nominal_system = CarFollowing()
        self.max_steps = self.settings.max_steps
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(15,), dtype=np.float64)
        # Car 4's acceleration has no actuator limit in the model (nor in the paper): the safe
        # action u_RL + u_S may leave any box the policy draws from (the learner's is
        # +/- LearnerConfig.policy_bound), so the plant takes any finite value.
        self.action_space = gym.spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float64)
        self._accelerations = np.zeros(5)

    @classmethod
    def nominal_controller(cls, params: Mapping[str, Any]) -> Controller:
        """Car 4 accelerates into car 3 at ``acceleration`` (:func:`cars_accelerate`).

        Raises:
            ValueError: naming ``acceleration`` when malformed.
        """
        acceleration = read_parameters(CarControllerSettings, params).acceleration
        return lambda x: cars_accelerate(x, acceleration=acceleration)

    def true_accelerations(self, state: np.ndarray, u: np.ndarray, t: float) -> np.ndarray:
        """(5,) v_dot of every car under the TRUE dynamics at time t."""
        f, _ = self.nominal_terms(state)
        inputs = f[1::2].copy()  # nominal u_2, u_3, u_5 (u_1 = u_4 = 0 in the prior)
        s = self.settings
        inputs[0] = (self.nominal_system.k_v * (self.nominal_system.v_des - state[1])
                     + s.leader_amplitude * math.sin(s.leader_frequency * t))
        inputs[3] = 0.0
        accelerations = (1.0 + s.disturbance_gain) * inputs
        accelerations[3] = u[0]
        return accelerations

    def _reset_state(self, options: dict[str, Any]) -> np.ndarray:
        state = np.zeros(10)
        s = self.settings
        state[0::2] = s.initial_positions
        state[1::2] = s.initial_velocity + s.velocity_noise * self.np_random.normal()
        state[7] = s.initial_velocity_car4
        self._accelerations = np.zeros(5)
        return state

    def _true_derivative(self, state: np.ndarray, u: np.ndarray) -> np.ndarray:
        accelerations = self.true_accelerations(state, u, self.t)
        self._accelerations = accelerations
        derivative = np.empty(10)
        derivative[0::2] = state[1::2]
        derivative[1::2] = accelerations
        return derivative

    def _observation(self) -> np.ndarray:
        obs = np.empty(15)
        obs[0::3] = self._state[0::2] / 100.0
        obs[1::3] = self._state[1::2] / 30.0
        obs[2::3] = self._accelerations / 10.0
        return obs

    def _reward_and_goal(self, previous: np.ndarray, u: np.ndarray) -> tuple[float, bool]:
        return -self.settings.reward_scale * float(np.dot(u, u)), False

    def _h_true(self, state: np.ndarray) -> np.ndarray:
        p = state[0::2]
        gap = self.settings.collision_gap
        return np.array([p[2] - p[3] - gap, p[3] - p[4] - gap])

"""Deliberately unsafe nominal controllers: they ignore every obstacle and neighbour.

They exist to exercise the safety filter (tests, demos, the ``nominal_controller`` node): each
drives straight at its objective, so any safety comes from the filter alone. Pure functions of
the QP state (numpy in, numpy out); each system's env binds its own
(:meth:`rcbf_ros.envs.base.SafetyEnv.nominal_controller`).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def unicycle_go_to_goal(state: Sequence[float], goal: Sequence[float] = (2.5, 2.5), *,
                        speed_gain: float = 1.0, turn_gain: float = 3.0,
                        max_speed: float = 1.5) -> np.ndarray:
    """Drive straight at the goal: v = min(k_v d, v_max) cos(e), omega = k_w e.

    Args:
        state: [x, y, theta].
        goal: (x, y) of the goal.
        speed_gain: k_v [1/s].
        turn_gain: k_w [1/s].
        max_speed: v_max [m/s].

    Returns:
        (2,) [v, omega], e the heading error to the goal in (-pi, pi].
    """
    x, y, theta = (float(v) for v in state[:3])
    dx, dy = goal[0] - x, goal[1] - y
    error = _wrap(math.atan2(dy, dx) - theta)
    speed = min(speed_gain * math.hypot(dx, dy), max_speed) * max(math.cos(error), 0.0)
    return np.array([speed, turn_gain * error])


def pvtol_go_to_goal(state: Sequence[float], goal: Sequence[float] = (5.0, -1.5), *,
                     position_gain: float = 0.3, velocity_gain: float = 1.0,
                     max_acceleration: float = 0.5, attitude_gain: float = 3.0,
                     thrust_gain: float = 3.0, max_tilt: float = 0.5,
                     u_limit: float = 2.5) -> np.ndarray:
    """PD go-to-goal for the PVTOL through the thrust vector.

    a_des = sat(k_p (goal - p) - k_d v, a_max); the thrust vector f [-sin th, cos th] must equal
    a_des + [0, 1], so th_des = atan2(-a_x, a_y + 1) (clipped to +/- max_tilt) and
    f_des = ||a_des + [0, 1]||; then omega = k_th (th_des - th), u_f = k_f (f_des - f), both
    clipped to +/- u_limit.

    Args:
        state: [x1, x2, v1, v2, theta, f(, x_h)].
        goal: (x1, x2) of the goal.

    Returns:
        (2,) [omega, u_f].
    """
    p = np.asarray(state[:2], dtype=np.float64)
    v = np.asarray(state[2:4], dtype=np.float64)
    theta, thrust = float(state[4]), float(state[5])
    accel = position_gain * (np.asarray(goal, dtype=np.float64) - p) - velocity_gain * v
    norm = float(np.linalg.norm(accel))
    if norm > max_acceleration:
        accel *= max_acceleration / norm
    theta_des = float(np.clip(math.atan2(-accel[0], accel[1] + 1.0), -max_tilt, max_tilt))
    thrust_des = math.hypot(accel[0], accel[1] + 1.0)
    omega = attitude_gain * _wrap(theta_des - theta)
    u_f = thrust_gain * (thrust_des - thrust)
    return np.clip(np.array([omega, u_f]), -u_limit, u_limit)


def cars_accelerate(state: Sequence[float], *, acceleration: float = 5.0) -> np.ndarray:
    """Car 4 accelerates into car 3 regardless of the gap: u_4 = ``acceleration``.

    Args:
        state: [p1, v1, ..., p5, v5] (unused: the controller is blind on purpose).

    Returns:
        (1,) [u_4].
    """
    return np.array([float(acceleration)])

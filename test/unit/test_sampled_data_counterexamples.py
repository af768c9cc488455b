"""Cases found by searching for counterexamples to the sampled-data margin's bound
(rcbf_ros/core/sampled_data.py).

Each test states the bound |phi_i(x(t), u) - phi_i(x_k, u)| <= nu0_i + c_i^T |u| for a case
that once broke it, with the left side evaluated by the torch assembly of RCBFProblem.qp (not
the margin's code): a look-ahead point behind the robot (l_p < 0), whose margin took l_p with
its sign where the bound needs |l_p|.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.dynamics import Unicycle
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import sampled_data_margin


@pytest.mark.parametrize('lookahead', [-0.5, -0.2, -0.03])
@pytest.mark.parametrize('bearing', [0.0, 1.6, -2.5])
def test_a_point_behind_the_robot_is_covered_by_its_margin(lookahead, bearing):
    """A look-ahead point behind the robot (l_p < 0, which CircleObstacles accepts), the
    robot turning in place at the fastest rate with v = 0 held: the row's true change over
    tau stays within nu0 + c^T |u| and c >= 0, as for the same point at l_p > 0."""
    system = Unicycle(u_min=(-2.0, -3.0), u_max=(2.5, 1.5))
    centre = (math.cos(bearing), math.sin(bearing))
    problem = RCBFProblem(system=system, families=(CircleObstacles(
        centers=(centre,), radii=(0.3,), margin=0.5, heading_index=2, lookahead=lookahead),),
        alpha=1.0, k_c=0.0)
    period = 0.2
    margin = sampled_data_margin(problem, control_period_s=period)
    x_k = np.array([0.0, 0.0, bearing + math.pi / 2])
    held = np.array([0.0, 1.5])
    rest, linear = margin.split_rows(x_k.tolist(), [0.0] * 3, [0.0] * 3)
    nu = float(rest[0] + linear[0] @ np.abs(held))
    change = 0.0
    for rate in (1.5, -3.0):  # the plant turns either way at a limit, v = 0
        states = [x_k + np.array([0.0, 0.0, rate * t]) for t in np.linspace(0.0, period, 201)]
        batch = torch.tensor(np.array(states), dtype=torch.float64)
        phi = problem.qp(batch, torch.tensor(held).expand(201, 2)).h[:, 0].numpy()
        change = max(change, float(np.abs(phi - phi[0]).max()))
    assert np.all(linear >= 0.0) and change <= nu, (change, nu, rest, linear)

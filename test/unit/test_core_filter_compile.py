"""The compiled constraint assembly equals the eager one, and refuses what it cannot trace."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.dynamics import Unicycle
from rcbf_ros.core.filter import compiled_assembly, eager_assembly, SafetyFilter
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.parameters.rules import find_config, load_params

pytestmark = pytest.mark.slow  # each compile takes seconds


@pytest.mark.parametrize('system', ['unicycle', 'car_following', 'pvtol'])
def test_compiled_assembly_matches_eager(system):
    problem = filter_config_from_params(load_params(find_config(system), 'safety_filter')).problem
    eager, compiled = eager_assembly(problem), compiled_assembly(problem)
    gen = torch.Generator().manual_seed(3)
    for _ in range(20):
        x = torch.randn(1, problem.system.n_x, generator=gen, dtype=torch.float64)
        u = torch.randn(1, problem.system.n_u, generator=gen, dtype=torch.float64)
        mean = 0.1 * torch.randn(1, problem.system.n_x, generator=gen, dtype=torch.float64)
        std = 0.1 * torch.rand(1, problem.system.n_x, generator=gen, dtype=torch.float64)
        for got, want in zip(compiled(x, u, mean, std), eager(x, u, mean, std)):
            torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_compiled_filter_gives_the_same_safe_actions():
    problem = filter_config_from_params(load_params(find_config('pvtol'),
                                                    'safety_filter')).problem
    eager, fast = SafetyFilter(problem), SafetyFilter(problem, compile_assembly=True)
    rng = np.random.default_rng(0)
    for _ in range(30):
        x = rng.normal(0, 0.5, problem.system.n_x)
        x[5] += 1.0
        u = rng.uniform(-2, 2, 2)
        a, b = eager.filter(x, u), fast.filter(x, u)
        np.testing.assert_allclose(b.h, a.h, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.u_safe, a.u_safe, atol=1e-6)  # OSQP tolerance


@dataclass(frozen=True)
class BranchingUnicycle(Unicycle):
    """A system whose drift branches in Python on a tensor value: not traceable."""

    n_x: int = field(default=3, init=False)

    def f(self, x):
        if float(x[0, 0]) > 0.3:  # value-dependent Python control flow
            return torch.ones_like(x)
        return torch.zeros_like(x)


def test_value_dependent_python_branching_is_refused():
    problem = RCBFProblem(BranchingUnicycle(), (CircleObstacles(
        centers=((0.0, 0.0),), radii=(0.5,), heading_index=2, lookahead=0.05),))
    with pytest.raises(ValueError, match='compile_assembly'):
        compiled_assembly(problem)

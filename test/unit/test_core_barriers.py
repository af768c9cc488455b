"""Barriers, cascades, Lie derivatives and the robust margin against independent references."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from rcbf_ros.core.barriers import (
    BandBarrier,
    cascade,
    CircleObstacles,
    evaluate,
    HalfPlane,
    PairGap,
)
from rcbf_ros.core.dynamics import CarFollowing, PVTOL, Unicycle
from rcbf_ros.core.qp import robust_margin
from rcbf_ros.core.rcbf import barrier_terms


def finite_difference_gradient(fn, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences of fn: (B, n) -> (B, K), returned as (B, K, n)."""
    cols = []
    for j in range(x.shape[1]):
        step = torch.zeros_like(x)
        step[:, j] = eps
        cols.append((fn(x + step) - fn(x - step)) / (2 * eps))
    return torch.stack(cols, dim=-1)


def random_states(system, batch: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, system.n_x, generator=gen, dtype=torch.float64)
    if isinstance(system, CarFollowing):
        start = torch.tensor([34.0, 28.0, 22.0, 16.0, 10.0], dtype=torch.float64)
        x[:, 0::2] = start + 2 * x[:, 0::2]
        x[:, 1::2] = 30.0 + 3 * x[:, 1::2]
    return x


CASES = [
    ('unicycle-lookahead', Unicycle(),
     lambda s: CircleObstacles(centers=((0.0, 0.0), (1.5, -1.5)), radii=(0.6, 0.5), margin=0.1,
                               heading_index=2, lookahead=0.03)),
    ('unicycle-walls', Unicycle(),
     lambda s: HalfPlane(normals=((1.0, 0.0), (-0.6, 0.8)), offsets=(-3.0, -2.0))),
    ('cars-gap', CarFollowing(),
     lambda s: cascade(PairGap(pairs=((4, 6), (8, 6)), delta=3.5), s, [2.0])),
    ('pvtol-obstacles', PVTOL(),
     lambda s: cascade(CircleObstacles(centers=((1.0, 1.0), (-1.0, 0.5)), radii=(0.4, 0.45)),
                       s, [1.5, 2.5])),
    ('pvtol-operator', PVTOL(),
     lambda s: cascade(BandBarrier(index=0, half_width=0.6, center_index=6), s, [1.0, 3.0])),
    ('pvtol-operator-sides', PVTOL(),
     lambda s: cascade(BandBarrier(index=0, half_width=0.6, center_index=6, form='sides'), s,
                       [1.0, 3.0])),
]


@pytest.mark.parametrize('name,system,make', CASES, ids=[c[0] for c in CASES])
def test_gradient_matches_finite_differences(name, system, make):
    family = make(system)
    x = random_states(system, 16)
    terms = barrier_terms(system, (family,), x)
    numeric = finite_difference_gradient(lambda z: evaluate(family, z), x)
    torch.testing.assert_close(terms.grad_h, numeric, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(terms.h, evaluate(family, x))
    # Lie derivatives are the gradient contracted with f and g.
    torch.testing.assert_close(terms.lf_h, torch.einsum('bkn,bn->bk', numeric, system.f(x)),
                               atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(terms.lg_h, torch.einsum('bkn,bnm->bkm', numeric, system.g(x)),
                               atol=1e-4, rtol=1e-5)


def test_cascade_is_time_derivative_plus_gamma_h_along_the_drift():
    """h* = dh/dt + gamma h along x_dot = f(x): check with a tiny Euler step of the drift."""
    system = PVTOL()
    base = CircleObstacles(centers=((0.5, -0.3),), radii=(0.4,))
    x = random_states(system, 8, seed=3)
    gamma = 1.7
    star = evaluate(cascade(base, system, [gamma]), x)
    dt = 1e-6
    drift = dt * system.f(x)
    h_dot = (evaluate(base, x + drift) - evaluate(base, x - drift)) / (2 * dt)
    torch.testing.assert_close(star, h_dot + gamma * evaluate(base, x), atol=1e-6, rtol=1e-6)


def test_closed_form_cascade_for_car_gap():
    """h = 1/2 ((p3 - p4)^2 - d^2): h* = (p3 - p4)(v3 - v4) + gamma h."""
    system = CarFollowing()
    x = random_states(system, 5, seed=1)
    gamma, delta = 2.0, 3.5
    star = evaluate(cascade(PairGap(pairs=((4, 6),), delta=delta), system, [gamma]), x)[:, 0]
    p3, v3, p4, v4 = x[:, 4], x[:, 5], x[:, 6], x[:, 7]
    expected = (p3 - p4) * (v3 - v4) + gamma * 0.5 * ((p3 - p4) ** 2 - delta ** 2)
    torch.testing.assert_close(star, expected)


@pytest.mark.parametrize('name,system,make', CASES[2:], ids=[c[0] for c in CASES[2:]])
def test_lower_cascade_levels_have_no_input(name, system, make):
    """Cascading is only valid where L_g of the lower level vanishes (relative degree >= 2)."""
    family = make(system)
    lower = family.base
    x = random_states(system, 16, seed=7)
    terms = barrier_terms(system, (lower,), x)
    assert terms.lg_h.abs().max() < 1e-12
    # ...while the top level does see the input (relative degree exactly reached).
    top = barrier_terms(system, (family,), x)
    assert top.lg_h.abs().max() > 1e-3


def test_unicycle_without_lookahead_loses_the_turn_rate():
    """Why the look-ahead exists: with l_p = 0, omega never appears in L_g h."""
    system = Unicycle()
    x = random_states(system, 8)
    plain = CircleObstacles(centers=((0.0, 0.0),), radii=(0.5,))
    ahead = CircleObstacles(centers=((0.0, 0.0),), radii=(0.5,), heading_index=2, lookahead=0.03)
    assert barrier_terms(system, (plain,), x).lg_h[..., 1].abs().max() == 0.0
    assert barrier_terms(system, (ahead,), x).lg_h[..., 1].abs().min() > 0.0


def test_robust_margin_equals_minimum_over_all_hull_vertices():
    gen = torch.Generator().manual_seed(0)
    batch, k, n = 6, 4, 5
    grad = torch.randn(batch, k, n, generator=gen)
    mean = torch.randn(batch, n, generator=gen)
    std = torch.rand(batch, n, generator=gen)
    k_c = 2.0
    closed = robust_margin(grad, mean, std, k_c)
    # The paper's Psi: the 2^n vertices mean +/- k_c std, minimised by enumeration.
    signs = torch.tensor(list(itertools.product([-1.0, 1.0], repeat=n)))  # (2^n, n)
    vertices = mean[:, None, :] + k_c * signs[None] * std[:, None, :]  # (B, 2^n, n)
    brute = torch.einsum('bkn,bvn->bkv', grad, vertices).min(dim=-1).values
    torch.testing.assert_close(closed, brute)


def test_barrier_values_closed_forms():
    x = torch.tensor([[1.0, 2.0, 0.0]], dtype=torch.float64)
    obstacle = CircleObstacles(centers=((0.0, 0.0),), radii=(1.0,), margin=0.5)
    assert evaluate(obstacle, x).item() == pytest.approx(1 + 4 - 1.5 ** 2)
    band = BandBarrier(index=0, half_width=0.6, center=0.5)
    assert evaluate(band, x).item() == pytest.approx(0.36 - 0.25)
    wall = HalfPlane(normals=((0.0, -1.0),), offsets=(-3.0,))
    assert evaluate(wall, x).item() == pytest.approx(1.0)


def test_band_sides_are_the_linear_factors_of_the_quadratic_band():
    x = random_states(PVTOL(), 64, seed=3)
    quadratic = BandBarrier(index=0, half_width=0.6, center_index=6)
    sides = BandBarrier(index=0, half_width=0.6, center_index=6, form='sides', name='op')
    assert sides.count == 2 and sides.names == ['op_upper', 'op_lower']
    h = evaluate(sides, x)
    e = x[:, 0] - x[:, 6]
    torch.testing.assert_close(h, torch.stack([0.6 - e, 0.6 + e], dim=1))
    torch.testing.assert_close(h[:, 0] * h[:, 1], evaluate(quadratic, x)[:, 0])
    # The same set: both sides non-negative exactly where the quadratic is.
    assert torch.equal(h.min(dim=1).values >= 0, evaluate(quadratic, x)[:, 0] >= 0)


def test_quadratic_band_cascade_is_blind_to_velocity_on_the_centre_line():
    """At the operator's centre line, moving fast: the quadratic band's first cascade level
    is delta^2 gamma for any velocity; the side being approached sees the velocity."""
    system = PVTOL()
    states = torch.tensor([[0.0, 0.0, v1, 0.0, 0.0, 1.0, 0.0] for v1 in (0.0, -3.0)],
                          dtype=torch.float64)
    quadratic = cascade(BandBarrier(index=0, half_width=0.5, center_index=6), system, [1.0])
    sides = cascade(BandBarrier(index=0, half_width=0.5, center_index=6, form='sides'), system,
                    [1.0])
    torch.testing.assert_close(evaluate(quadratic, states)[:, 0],
                               torch.tensor([0.25, 0.25], dtype=torch.float64))
    # lower side: e_dot + (delta + e) with e_dot = v1 - k_h e = v1
    torch.testing.assert_close(evaluate(sides, states)[:, 1],
                               torch.tensor([0.5, -2.5], dtype=torch.float64))


def test_band_form_must_be_known():
    with pytest.raises(ValueError, match='form'):
        BandBarrier(index=0, half_width=1.0, form='cubic')


@pytest.mark.parametrize('kwargs,field', [
    (dict(centers=((0.0, 0.0),), radii=(1.0, 2.0)), 'obstacles'),
    (dict(centers=((0.0, 0.0, 1.0),), radii=(1.0,)), 'obstacles.centers'),
    (dict(centers=((0.0, 0.0),), radii=(-1.0,)), 'obstacles.radii'),
    (dict(centers=((0.0, 0.0),), radii=(1.0,), lookahead=0.1), 'obstacles.lookahead'),
])
def test_bad_obstacles_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        CircleObstacles(**kwargs)


def test_cascade_rejects_non_positive_gain():
    with pytest.raises(ValueError, match='gammas'):
        cascade(PairGap(pairs=((0, 2),), delta=1.0), CarFollowing(), [0.0])


def test_float32_and_batch_consistency():
    """Row-wise evaluation: a state's terms do not depend on the rest of the batch."""
    system = PVTOL()
    family = cascade(CircleObstacles(centers=((1.0, 1.0), (0.0, -1.0)), radii=(0.4, 0.4)),
                     system, [1.0, 1.0])
    x = random_states(system, 10, seed=5)
    full = barrier_terms(system, (family,), x)
    single = barrier_terms(system, (family,), x[3:4])
    torch.testing.assert_close(full.grad_h[3:4], single.grad_h)
    assert np.isfinite(full.lg_h.numpy()).all()


def test_numbered_families_name_each_barrier_and_cascades_unwrap_to_the_base():
    from rcbf_ros.core.barriers import uncascaded
    obstacles = CircleObstacles(centers=((0.0, 1.0), (2.0, 3.0)), radii=(0.5, 0.5),
                                name='rock')
    walls = HalfPlane(normals=((1.0, 0.0),), offsets=(-3.0,))
    assert obstacles.names == ['rock_0', 'rock_1'] and walls.names == ['wall_0']
    twice = cascade(obstacles, Unicycle(), [1.0, 2.0])
    assert twice.names == obstacles.names and twice.count == 2
    assert uncascaded(twice) is obstacles and uncascaded(walls) is walls

"""DisturbanceGP's projection bounds (on each output's eigenvectors, and on a basis outputs
share) and the refit's choice of each output's bound: never below the exact variance at any
rank, on any basis and at any state (near-duplicate inputs, noise far below the signal, states
far outside the data), exact at full rank, at least the low-rank bound of the same rank; the
chosen rank the smallest passing one; the one-state path equal to ``predict``."""
from __future__ import annotations

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.learning import gp_bounds
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig

DTYPE = torch.float64
EPS = float(torch.finfo(DTYPE).eps)


def random_gp(*, seed: int, points: int, n_in: int, lengthscale: float, noise_ratio: float,
              neighbours: int = 0, duplicates: int = 0, include_noise: bool = False,
              tolerance: float = 0.01, spread: float = 0.0, second: bool = True
              ) -> DisturbanceGP:
    """Set hyperparameters on random data: output 0 smooth, output 1 another signal at 25 times
    the variance and ``1 + spread`` times the lengthscale (or, without ``second``, zero),
    output 2 exactly zero (no posterior). ``duplicates`` inputs repeat others to 1e-9."""
    generator = torch.Generator().manual_seed(seed)
    x = 2.0 * torch.rand(points, n_in, generator=generator, dtype=DTYPE) - 1.0
    if duplicates:
        source = torch.randint(points, (duplicates,), generator=generator)
        x[-duplicates:] = x[source] + 1e-9 * torch.randn(duplicates, n_in, generator=generator,
                                                         dtype=DTYPE)
    y = torch.stack([torch.sin(3.0 * x[:, 0]), 5.0 * torch.cos(2.0 * x.sum(-1)) * second,
                     torch.zeros(points, dtype=DTYPE)], dim=1)
    gp = DisturbanceGP(n_in, 3, GPConfig(variance_neighbours=neighbours,
                                         include_noise_in_std=include_noise,
                                         bound_std_tolerance=tolerance))
    gp.add(x, y)
    outputscale = torch.tensor([1.0, 25.0, 1.0], dtype=DTYPE)
    lengthscales = torch.full((3, n_in), lengthscale, dtype=DTYPE)
    lengthscales[1] *= 1.0 + spread
    gp.set_hyperparameters(lengthscales, outputscale, noise_ratio * outputscale)
    return gp


def queries(gp: DisturbanceGP, seed: int, count: int = 120) -> torch.Tensor:
    """Training inputs exactly, moved a little, and states far outside the data (up to 1e3)."""
    generator = torch.Generator().manual_seed(seed + 1)
    train = gp.train_x
    at = train[torch.randint(train.shape[0], (count // 3,), generator=generator)]
    near = at + 0.05 * torch.randn(at.shape, generator=generator, dtype=DTYPE)
    far = (2.0 * torch.rand(count - 2 * (count // 3), gp.n_in, generator=generator,
                            dtype=DTYPE) - 1.0)
    far = far * torch.logspace(0.0, 3.0, far.shape[0], dtype=DTYPE)[:, None]
    return torch.cat([at, near, far])


def round_off(gp: DisturbanceGP) -> np.ndarray:
    """(n_active,) the variance round-off of any evaluation, eps M s (1 + s / n)."""
    active = gp.active_outputs
    assert gp.outputscale is not None and gp.noise is not None
    s, n = gp.outputscale[active], gp.noise[active]
    return (64.0 * EPS * max(gp.train_x.shape[0], 16) * s * (1.0 + s / n)).numpy()


def mean_round_off(gp: DisturbanceGP, q: torch.Tensor) -> np.ndarray:
    """(B, n_active) the round-off of any evaluation of the mean k . alpha: eps M |k| . |alpha|
    (alpha is large when the noise is far below the signal or inputs nearly repeat), each k_j
    itself off by eps times its exponent's terms: |q~|^2 + |x~_j|^2 in the exact evaluation's
    expansion (~: over the lengthscales), |log(k_j / s)| in the direct one."""
    c = gp._cache
    assert c is not None
    k = gp_bounds.cross_kernel(c, q)  # (D, B, M)
    exponent = (k / c['outputscale'][:, None, None]).clamp_min(1e-320).log().abs()
    squares = (((q.unsqueeze(0) / c['lengthscales'].unsqueeze(1)) ** 2).sum(-1)[:, :, None]
               + (c['x_scaled'] ** 2).sum(-1)[:, None, :])  # (D, B, M)
    scale = (k.abs() * (1.0 + exponent + squares) * c['alpha'].abs().unsqueeze(1)).sum(-1).T
    return (16.0 * EPS * max(gp.train_x.shape[0], 16) * scale).numpy()


def bound_variance(gp: DisturbanceGP, q: torch.Tensor, kind: str, rank: int) -> np.ndarray:
    """(B, n_active) one bound's variance at one rank on every active output."""
    c = gp._cache
    assert c is not None
    outputs = torch.arange(int(gp.active_outputs.sum()))
    plan = gp_bounds.make_plan(c, [(kind, outputs, rank, None)], gp.config.include_noise_in_std)
    return gp_bounds.predict_plan(plan, q.numpy())[:-1, :, 1].T ** 2


def exact(gp: DisturbanceGP, q: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(B, n_active) the exact mean and variance."""
    mean, std = gp.predict(q, exact=True)
    active = gp.active_outputs
    return mean[:, active].numpy(), (std ** 2)[:, active].numpy()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(2, 90), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.05, 3.0), noise_ratio=st.floats(1e-7, 10.0),
       duplicates=st.integers(0, 2), include_noise=st.booleans())
def test_the_projection_bound_is_never_below_the_exact_variance_at_any_rank(
        seed, points, n_in, lengthscale, noise_ratio, duplicates, include_noise):
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=noise_ratio, duplicates=min(duplicates, points - 1),
                   include_noise=include_noise)
    q = queries(gp, seed)
    mean_exact, var_exact = exact(gp, q)
    slack = round_off(gp)
    n_points = gp.train_x.shape[0]
    previous = None
    for rank in sorted({0, 1, n_points // 3, n_points // 2, n_points - 1, n_points}):
        variance = bound_variance(gp, q, 'projection', rank)
        assert (variance - var_exact >= -slack).all(), rank
        # It drops the low-rank bound's tail term: never below it either.
        low_rank = bound_variance(gp, q, 'low_rank', rank)
        assert (variance - low_rank >= -slack).all(), rank
        # More eigenpairs subtract more.
        if previous is not None:
            assert (variance <= previous + slack).all(), rank
        previous = variance
    # Every eigenpair: the exact variance, to round-off; the mean is the exact one.
    assert np.abs(previous - var_exact).max() <= slack.max()
    c = gp._cache
    assert c is not None
    plan = gp_bounds.make_plan(c, [('projection', torch.arange(2), n_points, None)],
                               include_noise)
    mean = gp_bounds.predict_plan(plan, q.numpy())[:-1, :, 0].T
    assert (np.abs(mean - mean_exact) <= mean_round_off(gp, q)).all()
    # Far outside the data: the prior, exactly.
    far = torch.full((1, n_in), 1e3 * lengthscale * 40.0, dtype=DTYPE)
    prior = (gp.outputscale + gp.noise if include_noise else gp.outputscale)[:2].numpy()
    np.testing.assert_array_equal(bound_variance(gp, far, 'projection', n_points // 2)[0],
                                  (np.sqrt(prior)) ** 2)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(3, 120), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.05, 3.0), noise_ratio=st.floats(1e-7, 10.0),
       neighbours=st.sampled_from([0, 4, 16, 32]), duplicates=st.integers(0, 2),
       include_noise=st.booleans(), tolerance=st.sampled_from([0.0, 0.01, 0.3]),
       spread=st.sampled_from([0.0, 0.02, 0.1, 0.5]))
def test_the_chosen_bound_is_never_below_the_exact_variance(
        seed, points, n_in, lengthscale, noise_ratio, neighbours, duplicates, include_noise,
        tolerance, spread):
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=noise_ratio, neighbours=neighbours, duplicates=duplicates,
                   include_noise=include_noise, tolerance=tolerance, spread=spread)
    q = queries(gp, seed)
    mean_exact, var_exact = exact(gp, q)
    slack = round_off(gp)
    mean, std = gp.predict(q)
    active = gp.active_outputs
    assert ((std ** 2)[:, active].numpy() - var_exact >= -slack).all(), gp.variance_bound
    mean_slack = mean_round_off(gp, q)
    assert (np.abs(mean[:, active].numpy() - mean_exact) <= mean_slack).all()
    assert not mean[:, 2].any() and not std[:, 2].any()
    for row, row_mean, row_std, row_slack in zip(q[::7], mean[::7], std[::7], mean_slack[::7]):
        one_mean, one_std = gp.predict_state(row.numpy())
        assert (np.abs(one_mean - row_mean.numpy()) <= np.append(row_slack, 0.0)).all()
        assert (np.abs(one_std ** 2 - row_std.numpy() ** 2) <= np.append(slack, 0.0)).all()


def test_a_smooth_output_takes_the_projection_bound_at_the_smallest_passing_rank():
    gp = random_gp(seed=3, points=300, n_in=2, lengthscale=0.8, noise_ratio=1e-6,
                   second=False)
    bound, low_rank = gp.variance_bound, gp.variance_rank
    assert bound['bound'] == ('projection',) and bound['shared'] == 0
    ranks = bound['rank']
    assert (ranks % gp_bounds.PROJECTION_RANK_STEP == 0).all()
    assert (ranks + 1 < 2 * low_rank['kept'] + 1).all()  # fewer rows than the low-rank bound
    # The oracle: the probes' exact std against the bound at every multiple of the step.
    c = gp._cache
    assert c is not None
    probes = gp._probe_states(c['lengthscales'])
    exact_std = np.sqrt(np.maximum(exact(gp, probes)[1], 1e-12 * c['outputscale'].numpy()))
    step = gp_bounds.PROJECTION_RANK_STEP
    passing = [rank for rank in range(0, 301, step)
               if (np.sqrt(bound_variance(gp, probes, 'projection', rank)[:, 0])
                   <= 1.01 * exact_std[:, 0]).all()]
    assert int(ranks[0]) == passing[0] and passing == list(range(passing[0], 301, step))
    # Off the probes the tightness is not promised; on the data it holds here.
    q = queries(gp, 3)[:80]
    _, std = gp.predict(q)
    ratio = std[:, :1].numpy() / np.sqrt(exact(gp, q)[1])
    assert ratio.min() >= 1.0 - 1e-6 and ratio.max() <= 1.05


def test_a_looser_tolerance_takes_fewer_pairs_and_none_keeps_every_one():
    bounds = [random_gp(seed=4, points=200, n_in=3, lengthscale=0.7, noise_ratio=1e-5,
                        tolerance=tolerance, second=False).variance_bound
              for tolerance in (0.0, 1e-3, 0.1)]
    # No tolerance: only every eigenpair passes, which the low-rank bound reads in one pass.
    assert bounds[0]['bound'] == ('low_rank',) and (bounds[0]['rank'] == 200).all()
    assert bounds[1]['bound'] == bounds[2]['bound'] == ('projection',)
    assert (200 > bounds[1]['rank']).all() and (bounds[1]['rank'] > bounds[2]['rank']).all()


def test_outputs_of_one_bound_and_similar_rank_share_one_product_and_the_others_do_not():
    gp = random_gp(seed=5, points=256, n_in=2, lengthscale=0.5, noise_ratio=1e-6,
                   neighbours=16)
    c = gp._cache
    assert c is not None
    plan = c['plans']['chosen']
    assert [part['kind'] for part in plan['parts']] == ['shared_projection']
    assert plan['index'].tolist() == [0, 1] and not plan['identity']
    assert plan['take'].tolist() == [0, 1, 2]  # the output without a posterior: the zero row
    mixed = random_gp(seed=7, points=300, n_in=3, lengthscale=0.1, noise_ratio=0.5,
                      neighbours=32)
    assert mixed.variance_bound['bound'] == ('hybrid', 'hybrid')


@pytest.mark.parametrize('bound', ['chosen', 'low_rank'])
def test_a_batch_predicts_each_state_as_any_other_batch_holding_it(bound):
    """To round-off, not bit for bit: a BLAS product may sum its terms in another order for
    another number of rows (OpenBLAS's Haswell kernels do; its SkylakeX ones did not here)."""
    gp = random_gp(seed=6, points=300, n_in=3, lengthscale=0.6, noise_ratio=1e-6,
                   neighbours=16)
    q = queries(gp, 6, count=90)
    mean, std = gp.predict(q, bound=bound)
    order = torch.randperm(q.shape[0], generator=torch.Generator().manual_seed(0))
    for index in (order[:7], order[7:40], order[40:]):
        sub_mean, sub_std = gp.predict(q[index], bound=bound)
        torch.testing.assert_close(sub_mean, mean[index], rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(sub_std, std[index], rtol=1e-9, atol=1e-12)


def test_outputs_of_alike_kernels_share_a_basis_smaller_than_their_ranks_together():
    gp = random_gp(seed=8, points=300, n_in=2, lengthscale=0.6, noise_ratio=1e-6, spread=0.05)
    bound = gp.variance_bound
    assert bound['bound'] == ('shared_projection', 'shared_projection')
    alone = [random_gp(seed=8, points=300, n_in=2, lengthscale=0.6 * scale, noise_ratio=1e-6,
                       second=False).variance_bound['rank'][0] for scale in (1.0, 1.05)]
    assert max(alone) <= bound['shared'] < sum(alone)
    assert (bound['rank'] <= bound['shared']).all()
    c = gp._cache
    assert c is not None
    probes = gp._probe_states(c['lengthscales'])
    _, var_exact = exact(gp, probes)
    _, std = gp.predict(probes)
    ratio = std[:, :2].numpy() / np.sqrt(var_exact)
    assert ratio.min() >= 1.0 - 1e-6 and ratio.max() <= 1.01


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(4, 90), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.05, 3.0), noise_ratio=st.floats(1e-7, 10.0),
       spread=st.floats(0.0, 1.0), duplicates=st.integers(0, 2), include_noise=st.booleans(),
       eigen_part=st.floats(0.0, 1.0))
def test_a_projection_on_any_shared_basis_is_never_below_the_exact_variance(
        seed, points, n_in, lengthscale, noise_ratio, spread, duplicates, include_noise,
        eigen_part):
    """Any orthonormal basis: some of output 0's eigenvectors, the rest random directions."""
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=noise_ratio, duplicates=duplicates, include_noise=include_noise,
                   spread=spread)
    c = gp._cache
    assert c is not None
    n_points = gp.train_x.shape[0]
    size = max(1, n_points // 2)
    generator = torch.Generator().manual_seed(seed)
    own = int(eigen_part * size)
    columns = torch.cat([c['eigenvectors'][0][:, :own],
                         torch.randn(n_points, size - own, generator=generator, dtype=DTYPE)], 1)
    basis = torch.linalg.qr(columns)[0]
    vectors = []
    for output, rank in ((0, size), (1, size // 2)):
        directions, values = gp_bounds.subspace_directions(c, output, basis)
        vectors.append(directions[:, :rank] * values[:rank].rsqrt())
    shared = {**c, 'shared': {'members': torch.arange(2), 'basis': basis, 'vectors': vectors}}
    plan = gp_bounds.make_plan(shared, [('shared_projection', torch.arange(2), size, None)],
                               include_noise)
    q = queries(gp, seed)
    result = gp_bounds.predict_plan(plan, q.numpy())[:-1]
    mean_exact, var_exact = exact(gp, q)
    assert (result[:, :, 1].T ** 2 - var_exact >= -round_off(gp)).all()
    assert (np.abs(result[:, :, 0].T - mean_exact) <= mean_round_off(gp, q)).all()


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(150, 260), n_in=st.integers(1, 3),
       lengthscale=st.floats(0.3, 2.0), noise_ratio=st.floats(1e-7, 1e-3),
       spread=st.floats(0.0, 0.2), include_noise=st.booleans())
def test_where_outputs_share_a_basis_the_chosen_bound_is_never_below_the_exact_variance(
        seed, points, n_in, lengthscale, noise_ratio, spread, include_noise):
    """Smooth outputs of alike lengthscales, mostly on a shared basis (a few on their own)."""
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=noise_ratio, include_noise=include_noise, spread=spread)
    q = queries(gp, seed)
    _, var_exact = exact(gp, q)
    mean, std = gp.predict(q)
    assert ((std ** 2)[:, :2].numpy() - var_exact >= -round_off(gp)).all(), gp.variance_bound
    mean_slack = mean_round_off(gp, q)
    for row, row_mean, row_std, row_slack in zip(q[::11], mean[::11], std[::11],
                                                 mean_slack[::11]):
        one_mean, one_std = gp.predict_state(row.numpy())
        assert (np.abs(one_mean - row_mean.numpy()) <= np.append(row_slack, 0.0)).all()
        assert (np.abs(one_std ** 2 - row_std.numpy() ** 2)
                <= np.append(round_off(gp), 0.0)).all()
